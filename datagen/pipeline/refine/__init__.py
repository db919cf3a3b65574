"""Refiners (docs/pipeline.md section 4): R(O) = the band keys a refiner predicts occupied.

``none`` (the raw observation), ``carve`` (space carving), ``poisson`` (screened Poisson surface,
needs Open3D) and ``poco`` (the learned network) share one interface; `make_refiner` picks one.
"""

from datagen.pipeline.refine.base import Refiner, RefineRequest, band_keys, refined_keys
from datagen.pipeline.refine.factory import make_refiner

__all__ = ["RefineRequest", "Refiner", "band_keys", "make_refiner", "refined_keys"]
