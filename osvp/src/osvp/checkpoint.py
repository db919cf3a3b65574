"""Checkpoints: what a trained planner is, saved so that only tensors and plain data come back.

A checkpoint holds the network's preset and view count, the point count it was trained with, the
training options and history, the dataset it came from, and the model and optimiser states. It is
read with ``torch.load(weights_only=True)``, so a file cannot run code; anything else wrong with it
is a `CheckpointError` naming the file and the fix.

Version 2 adds how the planner turns probabilities into views: ``decoding`` (its default, see
`osvp.decoding`) and ``tuned_threshold`` (chosen on the run's validation samples); the training
target is in the stored options. A version-1 checkpoint still loads and plans (target ``label``,
the paper's 0.5 rule, no tuned threshold), but a run is never resumed from one. A checkpoint names
its network family (``architecture``, `osvp.architectures`); one without the field holds ``osvp``.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from osvp.architectures import DEFAULT_ARCHITECTURE, Architecture, Preset, architecture
from schemas.errors import DatagenError

FORMAT = "osvp-checkpoint"
VERSION = 2
READABLE_VERSIONS = (1, 2)
REQUIRED = ("format", "version", "preset", "num_views", "num_points", "source", "model", "epoch", "training")


class CheckpointError(DatagenError):
    """A checkpoint is missing, corrupt, or does not fit the data it is used with."""


@dataclass(frozen=True)
class Checkpoint:
    path: Path
    data: dict[str, Any]

    @property
    def architecture(self) -> Architecture:
        """The network family (`osvp.architectures`); ``osvp`` for a checkpoint that names none."""
        return architecture(str(self.data.get("architecture", DEFAULT_ARCHITECTURE)))

    @property
    def preset(self) -> Preset:
        return self.architecture.parse_preset(self.data["preset"])

    @property
    def num_views(self) -> int:
        return int(self.data["num_views"])

    @property
    def num_points(self) -> int:
        return int(self.data["num_points"])

    @property
    def source(self) -> str:
        return str(self.data["source"])

    @property
    def epoch(self) -> int:
        """Epochs completed."""
        return int(self.data["epoch"])

    @property
    def training(self) -> dict[str, Any]:
        """The options the run was started with, the dataset's identity and the history."""
        return dict(self.data["training"])

    @property
    def version(self) -> int:
        return int(self.data["version"])

    @property
    def target(self) -> str:
        """The training target (`osvp.loss.TARGETS`); ``label`` before version 2."""
        return str(self.training["options"].get("target", "label"))

    @property
    def generation_config(self) -> dict[str, Any] | None:
        """The generation config (plain data) of the dataset the run trained on; None before it was recorded."""
        stored = self.data.get("generation_config")
        return dict(stored) if isinstance(stored, dict) else None

    @property
    def tuned_threshold(self) -> float | None:
        """The ``tuned`` decoding's threshold, chosen on the run's validation samples; None before version 2."""
        value = self.data.get("tuned_threshold")
        return None if value is None else float(value)

    @property
    def decoding(self) -> str:
        """The default decoding: the stored one, else ``tuned`` when there is a tuned threshold, else
        the paper's ``threshold``."""
        stored = self.data.get("decoding")
        if stored is not None:
            return str(stored)
        return "tuned" if self.tuned_threshold is not None else "threshold"

    def network(self, device: str | torch.device = "cpu") -> nn.Module:
        """The trained network, in eval mode."""
        network = self.architecture.build(self.preset, self.num_views)
        try:
            network.load_state_dict(self.data["model"])
        except RuntimeError as exc:
            raise CheckpointError(f"{self.path}: its weights do not fit its own preset ({_reason(exc)})") from None
        return network.to(device).eval()

    def require(self, num_views: int, num_points: int | None = None, what: str = "the dataset") -> None:
        """Refuse data of another view count (and, when given, another point count)."""
        if num_views != self.num_views:
            raise CheckpointError(
                f"{self.path}: trained for {self.num_views} views but {what} has {num_views}; "
                "use a checkpoint trained on a dataset with this view space"
            )
        if num_points is not None and num_points != self.num_points:
            raise CheckpointError(
                f"{self.path}: trained on {self.num_points} points per cloud, asked for {num_points}; "
                f"leave --points out or give {self.num_points}"
            )


def save_checkpoint(path: Path, data: dict[str, Any]) -> None:
    """Write atomically (temporary file, then rename), so a kill never leaves half a checkpoint."""
    payload = {"format": FORMAT, "version": VERSION, **data}
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save(payload, temporary)
    os.replace(temporary, path)


def _reason(exc: BaseException, limit: int = 160) -> str:
    """The first sentence of a loader's error: torch's zip errors run on into advice for its own
    developers, which a user's one line has no room for."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    text = text.split(". ")[0].rstrip(".")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def load_checkpoint(path: str | Path) -> Checkpoint:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found; give a file written by `osvp train` (best.pt, last.pt)")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError) as exc:
        raise CheckpointError(f"{path}: not a readable osvp checkpoint ({_reason(exc)}); re-run `osvp train`") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an osvp checkpoint (no '{FORMAT}' marker); give a file from `osvp train`")
    if data.get("version") not in READABLE_VERSIONS:
        version = data.get("version")
        known = ", ".join(str(v) for v in READABLE_VERSIONS)
        raise CheckpointError(f"{path}: checkpoint version {version} is not one of {known}; retrain with this osvp")
    missing = [key for key in REQUIRED if key not in data]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {', '.join(missing)}; it is damaged, re-run `osvp train`")
    try:
        architecture(str(data.get("architecture", DEFAULT_ARCHITECTURE))).parse_preset(data["preset"])
    except (ValueError, TypeError) as exc:
        raise CheckpointError(f"{path}: bad network in checkpoint ({exc}); use a checkpoint of this osvp") from None
    return Checkpoint(path=path, data=data)
