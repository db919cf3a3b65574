"""Files of a POCO training run: the run folder's resumable checkpoints and the shipped weights file.

A training checkpoint (``last.pt``, ``best.pt``) holds the state dict, the optimiser state, the preset,
the step and a JSON ``extra`` (best validation so far, the tuned threshold); `export_weights` turns one
into the weights file the ``poco`` refiner loads (`datagen.pipeline.refine.poco.checkpoint`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from datagen.pipeline.refine.poco.inputs import TRAINING_SCALE
from datagen.pipeline.refine.poco.network import PocoModel


def save_training_state(
    path: Path, model: PocoModel, optimizer: torch.optim.Optimizer, step: int, extra: dict[str, Any]
) -> None:
    payload = {
        "state_dict": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "preset": dataclasses.asdict(model.preset),
        "step": int(step),
        "extra": json.dumps(extra),
    }
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    os.close(fd)
    torch.save(payload, tmp)
    os.replace(tmp, path)


def export_weights(checkpoint: Path, out: Path, threshold: float | None = None, half: bool = True) -> None:
    """Write the shipped weights file (fp16 storage by default) from a training checkpoint."""
    payload = torch.load(checkpoint, map_location="cpu", weights_only=True)
    state = payload["state_dict"]
    if half:
        state = {k: (v.half() if v.is_floating_point() else v) for k, v in state.items()}
    extra = json.loads(payload.get("extra", "{}"))
    if threshold is not None:
        extra["threshold"] = threshold
    torch.save(
        {
            "state_dict": state,
            "preset": payload["preset"],
            "step": payload.get("step", 0),
            "training_scale": TRAINING_SCALE,
            "extra": json.dumps(extra),
        },
        out,
    )
