"""What an export is asked (`Options`) and the names every layout shares: the authors' 32 views and
8 rotations, the split names, the root files and the reasons a sample is skipped.
"""

from __future__ import annotations

from dataclasses import dataclass

AUTHORS_VIEWS = 32
"""Outputs of every authors' network (AIR-OSVP, MA-SCVP, SC-Net, NBVNet, PC-NBV): the width of their
state, label and score vectors."""


AUTHORS_ROTATIONS = 8
"""Their ``rotate_<k>`` is a yaw of 360/8 = 45 degrees x k."""


ROTATION_NAMES = ("authors", "yaw")
"""``authors``: ``rotate_<k>`` with their meaning (refused where an angle has none); ``yaw``: ``yaw_<degrees>``."""


TRAIN = "train"


TEST = "test"


SPLITS = (TRAIN, TEST)


TRAIN_SPLIT = "train_split"


TEST_SPLIT = "test_split"


PROVENANCE_MD = "PROVENANCE.md"


PROVENANCE_JSON = "provenance.json"


ROOT_FILES = (TRAIN_SPLIT, TEST_SPLIT, PROVENANCE_MD, PROVENANCE_JSON)
"""What every export writes at its root."""


EMPTY_LABEL = "empty label"


NO_POINTS = "no points"


NO_NEXT_VIEW = "no next view"


PHRASES = {EMPTY_LABEL: "an empty label", NO_POINTS: "no points", NO_NEXT_VIEW: "no next view"}
"""How a provenance line names the samples skipped for each reason."""


@dataclass(frozen=True)
class Options:
    """The user's choices; a layout fills its defaults and refuses what it cannot use (`Layout.resolve`)."""

    num_points: int | None = None
    gt_points: int | None = None
    seed: int = 0
    val_fraction: float = 0.2
    rotation_names: str = "authors"
