"""``osvp soup``: one network whose weights are the mean of several checkpoints of the same run's lineage.

Averaging the weights of checkpoints that share a starting point (a run and its fine-tunes, or the
epochs of one run) is a cheap regulariser: the mean sits nearer the middle of the basin they all
found, and it plays as one network at one network's cost, unlike an ensemble. Checkpoints of
different networks, presets, view spaces, point counts, inputs or targets cannot be averaged and are
refused in one line. The soup keeps the first checkpoint's record (options, history, decoding) and
adds ``soup``: the sha256 of every ingredient, so its card says what it is made of.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from osvp.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint
from osvp.train import file_sha256

MUST_AGREE = ("architecture", "preset", "num_views", "num_points", "source")
"""What every ingredient must share with the first for their weights to mean the same thing."""


def _identity(checkpoint: Checkpoint, key: str) -> object:
    return checkpoint.target if key == "target" else checkpoint.data.get(key)


def soup_weights(checkpoints: Sequence[Checkpoint]) -> dict[str, torch.Tensor]:
    """The mean of the ingredients' floating-point tensors; counters (integer tensors such as a batch
    norm's ``num_batches_tracked``) are the first's."""
    first = checkpoints[0]
    for other in checkpoints[1:]:
        for key in (*MUST_AGREE, "target"):
            if _identity(other, key) != _identity(first, key):
                raise CheckpointError(
                    f"{other.path}: its {key} differs from {first.path}'s; a soup averages checkpoints of one "
                    "network trained for one target"
                )
        if set(other.data["model"]) != set(first.data["model"]):
            raise CheckpointError(f"{other.path}: its weights are not {first.path}'s layers; soup one network")
    weights: dict[str, torch.Tensor] = {}
    for name, tensor in first.data["model"].items():
        if tensor.is_floating_point():
            stacked = torch.stack([c.data["model"][name].to(torch.float64) for c in checkpoints])
            weights[name] = stacked.mean(dim=0).to(tensor.dtype)
        else:
            weights[name] = tensor.clone()
    return weights


def make_soup(paths: Sequence[Path], out: Path) -> Path:
    """Write the soup of ``paths`` (two or more checkpoints) to ``out``."""
    if len(paths) < 2:
        raise CheckpointError("a soup needs two or more checkpoints; give them after --out")
    checkpoints = [load_checkpoint(path) for path in paths]
    first = checkpoints[0].data
    data: dict[str, Any] = {key: value for key, value in first.items() if key not in ("format", "version")}
    data["model"] = soup_weights(checkpoints)
    for dropped in ("optimiser", "scheduler"):  # a soup is played, never resumed
        data.pop(dropped, None)
    data["soup"] = [{"file": Path(path).name, "sha256": file_sha256(Path(path))} for path in paths]
    save_checkpoint(out, data)
    return out
