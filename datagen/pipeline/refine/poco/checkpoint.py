"""Saving and loading POCO weights.

Files are plain ``torch.save`` dicts ``{"state_dict", "preset", ...}``; the official release's
``checkpoint.pth`` (``{"epoch", "state_dict", "optimizer"}``) and bare state dicts load too, since our
module tree has the same names. Loading always uses ``weights_only=True`` (no pickled code runs) and
``strict=True`` (a missing or extra tensor is an error, never silently ignored).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from datagen.pipeline.refine.poco.network import PocoModel
from datagen.pipeline.refine.poco.presets import PRESETS, PocoPreset, get_preset

PathLike = str | os.PathLike[str]


def save_checkpoint(model: PocoModel, path: PathLike, *, epoch: int | None = None) -> None:
    """Write the model's state dict with its preset (as plain values, loadable with weights_only)."""
    payload: dict[str, Any] = {
        "state_dict": model.state_dict(),
        "preset": dataclasses.asdict(model.preset),
    }
    if epoch is not None:
        payload["epoch"] = int(epoch)
    torch.save(payload, os.fspath(path))


def extract_state_dict(payload: Any) -> dict[str, Tensor]:
    """The state dict of a loaded file: its ``state_dict`` entry, or the file itself when bare.

    A DataParallel ``module.`` prefix is removed, since it only records how the weights were trained.
    """
    if isinstance(payload, Mapping) and "state_dict" in payload:
        payload = payload["state_dict"]
    if not isinstance(payload, Mapping) or not all(isinstance(v, Tensor) for v in payload.values()):
        raise ValueError("not a POCO checkpoint: expected a state dict or a dict holding 'state_dict'")
    state = dict(payload)
    if state and all(key.startswith("module.") for key in state):
        state = {key[len("module.") :]: value for key, value in state.items()}
    return state


def infer_preset(state: Mapping[str, Tensor]) -> PocoPreset:
    """The preset whose shapes the state dict has (widths, heads, input channels).

    The decoder's K is not stored in the weights: a known preset with matching shapes supplies it,
    otherwise the official 64 is assumed.
    """
    try:
        hidden, channels = state["net.cv0.cv.weight"].shape[:2]
        latent = state["net.fcout.weight"].shape[0]
        heads = state["projection.fc_query.weight"].shape[0]
    except KeyError as error:
        raise ValueError(f"not a POCO state dict (missing {error})") from None
    shape = (int(hidden), int(channels), int(latent), int(heads))
    for preset in PRESETS.values():
        if (preset.hidden, preset.input_channels, preset.latent, preset.heads) == shape:
            return preset
    return PocoPreset(
        name="custom", hidden=shape[0], input_channels=shape[1], latent=shape[2], decoder_k=64, heads=shape[3]
    )


def load_checkpoint(
    path: PathLike,
    preset: PocoPreset | str | None = None,
    *,
    map_location: str | torch.device = "cpu",
) -> PocoModel:
    """A `PocoModel` (in eval mode) holding the weights of ``path``.

    The preset is, in order: the one given, the one saved with the file, or one inferred from shapes.
    """
    payload = torch.load(os.fspath(path), map_location=map_location, weights_only=True)
    state = extract_state_dict(payload)
    if preset is not None:
        chosen = get_preset(preset)
    elif isinstance(payload, Mapping) and isinstance(payload.get("preset"), Mapping):
        chosen = PocoPreset(**payload["preset"])
    else:
        chosen = infer_preset(state)
    model = PocoModel(chosen)
    model.load_state_dict(state, strict=True)
    return model.to(map_location).eval()
