"""Refiners (PIPELINE.md section 4): R(O) = the band keys a refiner predicts occupied.

``none`` ships now; ``poco``, ``poisson`` and ``carve`` plug in behind the same interface.
"""

from datagen.refine.base import Refiner, RefineRequest, band_keys, refined_keys
from datagen.refine.registry import make_refiner

__all__ = ["RefineRequest", "Refiner", "band_keys", "make_refiner", "refined_keys"]
