"""POCO point-convolution occupancy network (pure PyTorch), its presets, spatial tables and checkpoints;
what the network sees (`inputs`, shared with training) and the ``poco`` refiner (`refiner`).

Import this package only where torch is available (it is an optional dependency of datagen).
"""

from datagen.pipeline.refine.poco.checkpoint import load_checkpoint, save_checkpoint
from datagen.pipeline.refine.poco.network import PocoModel, input_features
from datagen.pipeline.refine.poco.presets import PRESETS, PocoPreset, get_preset
from datagen.pipeline.refine.poco.spatial import knn, quantized_sampling, spatial_tables

__all__ = [
    "PRESETS",
    "PocoModel",
    "PocoPreset",
    "get_preset",
    "input_features",
    "knn",
    "load_checkpoint",
    "quantized_sampling",
    "save_checkpoint",
    "spatial_tables",
]
