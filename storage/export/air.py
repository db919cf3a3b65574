"""``--layout air``: AIR-OSVP's text layout, so their loader and trainer (COSC_Dataset, train.py) run unchanged.

``<out>/<object>/rotate_<k>/cloud_<c>.txt`` ("x y z" per line, exactly N points, seeded),
``state_<c>.txt`` (32 lines 0/1), ``ids_<c>.txt`` (label view ids, one per line, ascending), plus the
split and provenance files every layout writes.

What their code needs, and what this layout therefore guarantees (docs/authors-code.md section 7.2):

- companions are found by replacing "cloud" in the whole path, so neither the output path nor an
  object folder may contain it;
- their recall divides by the label size: a sample with an empty label would make it NaN (and no
  best checkpoint is ever saved), so such samples are skipped and counted; so are samples without
  points (an empty cloud file);
- every cloud has the same number of points (their ``do_sample: False`` batching).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from storage.export.base import Layout, Place, Run, Writer
from storage.export.options import EMPTY_LABEL, NO_POINTS
from storage.export.publish import write_text
from storage.export.streams import sample_rng
from storage.export.text import ids_text, state_text
from storage.readers.reader import Dataset, Sample

AUTHORS_CODE = "psc0628/AIR-OSVP @ c233bbf, poco_pointr/pointrVP/{COSC_Dataset.py,train.py}"


class AirLayout(Layout):
    name = "air"
    reader = "AIR-OSVP's loader and trainer"
    read_by = AUTHORS_CODE
    summary = "AIR-OSVP's text files (cloud, state, ids; needs --points)"
    path_word = "cloud"
    name_word = "cloud"
    needs_points = True
    needs_next_view = False
    fields = ("points", "view_state", "label")
    skip_reasons: ClassVar[Mapping[str, str]] = {
        EMPTY_LABEL: "no view needed: their recall divides by the label size, one such sample makes it NaN and "
        "no best checkpoint is saved; their generator writes none",
        NO_POINTS: "their loader cannot read an empty cloud file",
    }
    split_use = (
        "their train.py trains on train_split objects only (its validation is 20% of their samples, numpy "
        "seed 42, also trained on) and reads test_split without using it"
    )

    def skipped(self, dataset: Dataset) -> list[str]:
        labels = dataset.values("label", keep=False)
        points = dataset.values("num_points", keep=False)
        pairs = zip(labels, points, strict=True)
        return [EMPTY_LABEL if not label else NO_POINTS if not count else "" for label, count in pairs]

    def start(self, run: Run) -> Writer:
        return _AirWriter(run)

    def dataset_note(self, dataset: Dataset) -> str:
        tie_break = dataset.info.config.label_tie_break
        return (
            f"labels are exact minimum covers, the lexicographically smallest in the {tie_break!r} view order, "
            "theirs Gurobi's choice"
        )


class _AirWriter(Writer):
    def __init__(self, run: Run) -> None:
        self.run = run
        self.num_points = int(run.options.num_points or 0)
        self.resampled = 0

    def write(self, place: Place, sample: Sample) -> None:
        target, whole = self.run.target, sample["points"]
        replace = whole.shape[0] < self.num_points
        self.resampled += replace
        chosen = sample_rng(self.run.options.seed, place.sample_id).choice(
            whole.shape[0], size=self.num_points, replace=replace
        )
        cloud = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in whole[chosen].tolist())
        write_text(place.folder / f"cloud_{place.case}.txt", cloud, target)
        write_text(place.folder / f"state_{place.case}.txt", state_text(sample["view_state"]), target)
        write_text(place.folder / f"ids_{place.case}.txt", ids_text(sample["label"]), target)

    def finish(self) -> None:
        """Nothing per split: their loader lists the folders."""

    def lines(self) -> list[str]:
        config = self.run.dataset.info.config
        voxel_mm = f"{config.voxel_size * 1000:g} mm"
        return [
            f"points: {self.num_points} per cloud (every cloud the same size, as their do_sample: False batching "
            f"needs), drawn from the sample's refined cloud P(O_S) of {voxel_mm} voxel centres without "
            f"replacement, with replacement for the {self.resampled} samples that have fewer; seeded by "
            f"(seed {self.run.options.seed}, sample id)"
        ]

    def facts(self) -> dict[str, Any]:
        return {
            "points": {
                "per_cloud": self.num_points,
                "source": "points: the refined cloud P(O_S), voxel centres",
                "sampling": "uniform without replacement; with replacement when the cloud has fewer points",
                "rng": "numpy default_rng(SeedSequence([seed, sha256(sample_id) first 8 bytes, little-endian]))",
                "seed": self.run.options.seed,
                "drawn_with_replacement": self.resampled,
                "format": "x y z per line, %.6f",
            }
        }


AIR = AirLayout()
