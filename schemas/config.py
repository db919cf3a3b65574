"""`GenerationConfig`: everything that changes a sample, and its hash.

The config defines a dataset. Two datasets with the same config hash and the same meshes hold the
same samples. Files the config names (a view-space file, the refiner's weights) enter the hash by the
sha256 of their content, never by their path, so moving a file keeps the hash. ``poco_weights =
"builtin"`` names the weights shipped with datagen (`builtin_poco_weights`): their content enters the
hash too, so upgraded weights make another dataset, while the config keeps saying "builtin".

Defaults are those of the AIR-OSVP paper as fixed by ``docs/pipeline.md``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from schemas.errors import DatagenError
from schemas.objectives import OBJECTIVES, Objective, label_fields, objective_named
from schemas.refiners import RefinerKind, refiner_kind

MAX_VIEWS = 64
"""Cases are stored as one uint64 bit mask, so at most 64 candidate views."""

BUILTIN_VIEW_SPACE = "builtin"
GENERATED_VIEW_SPACE = "generated"
BUILTIN_POCO_WEIGHTS = "builtin"
BUILTIN_POCO_WEIGHTS_FILE: Path | None = None
"""The shipped weights' path when set (tests point it at a copy); otherwise `builtin_poco_weights`
finds the ``poco_version``'s file (`PocoVersion.weights_file`) in ``datagen/data`` beside the installed
datagen package."""

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]

RECORDED = {"recorded": True}
"""The validation context of a config a dataset recorded (`schemas.dataset.DatasetInfo`): a refiner or
label objective that a plug-in registered where the dataset was made is taken by its name where the
plug-in is not installed, so the dataset reads anywhere; only what needs the plug-in's code (making
samples, checking labels with its judge) asks for it."""


def _recorded(info: ValidationInfo) -> bool:
    return isinstance(info.context, dict) and bool(info.context.get("recorded"))


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class CameraConfig(_Frozen):
    """Pinhole intrinsics (the authors' RealSense values) and the sensor range.

    Lens distortion is ignored on purpose: the authors' distortion code misassigns its
    coefficients and applies them twice (README, differences from the paper).
    """

    width: int = Field(1280, ge=16, le=16384, strict=True)
    height: int = Field(720, ge=16, le=16384, strict=True)
    fx: PositiveFloat = 915.6066894531250
    fy: PositiveFloat = 913.3266601562500
    cx: float = 647.1453247070312
    cy: float = 372.5153198242188
    max_range: PositiveFloat = 1.0

    @model_validator(mode="after")
    def _principal_point_inside(self) -> CameraConfig:
        if not (0 < self.cx < self.width):
            raise ValueError(f"camera.cx = {self.cx} must lie inside the image: 0 < cx < width ({self.width})")
        if not (0 < self.cy < self.height):
            raise ValueError(f"camera.cy = {self.cy} must lie inside the image: 0 < cy < height ({self.height})")
        return self


class ViewSpaceConfig(_Frozen):
    """Where the candidate views come from.

    ``source`` is ``builtin`` (the authors' 32 Tammes positions), ``generated`` (a seeded spread of
    ``count`` positions maximising the minimum angular separation) or the path of a view-space file
    (first line the count, then ``x y z`` per line, metres). Positions are rescaled to ``radius``.
    """

    source: str = BUILTIN_VIEW_SPACE
    count: int = Field(32, ge=1, le=MAX_VIEWS, strict=True)
    radius: PositiveFloat = 0.4
    generator_seed: int = Field(0, ge=0, strict=True)

    @model_validator(mode="after")
    def _builtin_has_32(self) -> ViewSpaceConfig:
        if self.source == BUILTIN_VIEW_SPACE and self.count != 32:
            raise ValueError(
                f"view_space.count = {self.count} needs view_space.source = 'generated' or a file: "
                "the built-in view space has exactly 32 views"
            )
        return self

    @property
    def is_file(self) -> bool:
        return self.source not in (BUILTIN_VIEW_SPACE, GENERATED_VIEW_SPACE)


DEFAULT_COVER_CAP = 1024
"""Minimum covers listed per sample by default (schema version 2)."""


@dataclass(frozen=True)
class PocoVersion:
    """What a ``poco_version`` ships beside its computation (the neighbour search of each version is
    `datagen.pipeline.refine.poco.refiner.KNN_BACKENDS`'s): the file ``poco_weights = "builtin"``
    loads, and the preset and threshold a config takes unless it names its own."""

    weights_file: str
    """In ``datagen/data``."""
    preset: str
    threshold: float


POCO_VERSIONS: dict[int, PocoVersion] = {
    1: PocoVersion("poco_small.pt", "small_sv", 0.65),
    2: PocoVersion("poco_small.pt", "small_sv", 0.65),
    3: PocoVersion("poco_small.pt", "small_sv", 0.65),
    4: PocoVersion("poco_fast.pt", "fast_sv", 0.375),
}
"""Versions 1-3 change only the neighbour search of the network trained on synthetic shapes; version 4
is the `fast_sv` network (decoder K 16, 1,500 encoder points) trained on real scans too
(datagen/data/POCO_MODEL_CARD.md), with version 2's search."""
LATEST_POCO_VERSION = 2
"""The newest ``poco_version`` whose labels were judged against version 1's (docs/pipeline.md section
4.1): what a new config uses unless told."""
NEWEST_POCO_VERSION = max(POCO_VERSIONS)
"""The newest ``poco_version`` there is; those above `LATEST_POCO_VERSION` are chosen by name only."""

FIELDS_ADDED_LATER: dict[str, object] = {
    "label_tie_break": "index",
    "label_cover_cap": DEFAULT_COVER_CAP,
    "poco_version": 1,
    "label_objective": "cover",
}
"""Fields that enter the hash only when they differ from the value that reproduces what datasets
made before them hold; a stored config without one reads as that value (`stored_config`)."""

REFINER_FIELDS_ADDED_LATER = frozenset({"poco_version"})
"""Fields added after datasets of other refiners existed: they enter the hash only when the config's
refiner reads them (`RefinerKind.fields`), so those datasets keep their identity."""


def stored_config(data: Any) -> Any:
    """A config as a dataset or a job recorded it, with the fields it predates filled in with the values
    that reproduce it (a ``dataset.json`` written before ``poco_version`` existed is version 1, whatever
    a new config's default is now)."""
    if isinstance(data, dict):
        return {**FIELDS_ADDED_LATER, **data}
    return data


SCENE_FIELDS = (
    "voxel_size",
    "grid_offset",
    "size_range",
    "mm_threshold",
    "gt_density",
    "view_space",
    "camera",
    "imaging",
)
"""`GenerationConfig.scene_identity`'s fields: object preparation, ground truth, the views and imaging."""


class GenerationConfig(_Frozen):
    """Every setting that changes a sample (hashed into every sample and into ``dataset.json``)."""

    seed: int = Field(0, ge=0, lt=2**63, strict=True)
    # Section 0: keys
    voxel_size: PositiveFloat = 0.002
    grid_offset: tuple[float, float, float] = (0.2718, 0.3141, 0.1618)
    # Section 1: preparation
    size_range: tuple[PositiveFloat, PositiveFloat] = (0.05, 0.15)
    mm_threshold: PositiveFloat = 10.0
    rotations: int = Field(8, ge=1, le=360, strict=True)
    gt_density: PositiveFloat = 256.0
    # Section 2: views and camera
    view_space: ViewSpaceConfig = ViewSpaceConfig()
    camera: CameraConfig = CameraConfig()
    # Section 3: imaging
    imaging: Literal["targets", "pixels"] = "targets"
    # Section 4: refinement
    refiner: str = "poco"
    """Which registered refiner predicts R(O) (`schemas.refiners.REFINERS`: none, carve, poisson, poco
    and any installed plug-in)."""
    band: PositiveFloat = 0.01
    poco_preset: str = "small_sv"
    """The network's architecture; unless given, the ``poco_version``'s (`POCO_VERSIONS`)."""
    poco_weights: str = BUILTIN_POCO_WEIGHTS
    """'builtin' (the ``poco_version``'s shipped file: datagen/data/poco_small.pt, for version 4
    poco_fast.pt) or the path of a weights file."""
    poco_threshold: float = Field(0.65, gt=0.0, lt=1.0, allow_inf_nan=False)
    """p(inside) above which a queried band key is kept (tuned on held-out training shapes); unless
    given, the ``poco_version``'s."""
    finetune_steps: int = Field(0, ge=0, le=1000, strict=True)
    poco_version: int = Field(LATEST_POCO_VERSION, ge=1, le=NEWEST_POCO_VERSION, strict=True)
    """Which computation of the ``poco`` refiner defines R(O) (`datagen.pipeline.refine.poco.refiner`):
    1, the original (every dataset made before the field, which reads as 1); 2, the decoder's
    neighbour table from pykdtree instead of scipy's cKDTree, ~13 % less refinement CPU. The two
    searches break ties between equidistant input points differently, which flips ~1 % of the keys
    of R(O); 3, every neighbour table with one defined answer (nearest first, ties by index:
    `spatial.knn_ordered`), searched on the refiner's device, so a GPU's R(O) is the CPU's; 4,
    version 2's search with another network (`POCO_VERSIONS`: the fast_sv preset, weights trained on
    real scans too, threshold 0.375), about half version 2's refinement CPU. A new config takes the
    newest judged version (`LATEST_POCO_VERSION`); a stored one keeps its own."""
    poisson_depth: int = Field(8, ge=5, le=12, strict=True)
    """Octree depth of the ``poisson`` refiner (2**depth cells across the observed cloud's box)."""
    # Section 5: filter
    alpha: int = Field(10, ge=1, le=MAX_VIEWS, strict=True)
    # Section 6: input cases
    sampling: Literal["longtail"] = "longtail"
    # Section 7: labels
    empty_labels: Literal["keep", "drop"] = "keep"
    solver_time_limit: PositiveFloat = 10.0
    """Seconds of wall clock a single solve may run before its task fails and is run again (at least
    600 s: `datagen.pipeline.setcover.SAFETY_NET_SECONDS`). Only a safety net: whether a case gets a
    label is decided by node budgets, the same on every machine; this value stays in the hash for the
    datasets made when it decided."""
    label_tie_break: Literal["index", "coverage"] = "index"
    """Which of the equally small covers is the label: 'index' (the lexicographically smallest view
    indices, docs/pipeline.md section 7) or 'coverage' (lexicographically smallest with views ranked by how many
    keys of U each covers, most first: a rule a planner can learn from geometry, where the index
    order is arbitrary)."""
    label_cover_cap: int = Field(DEFAULT_COVER_CAP, ge=1, le=1 << 20, strict=True)
    """Most minimum covers a sample lists beside its label; past it the count of minimum covers is
    a lower bound (the support, the views of any minimum cover, stays exact)."""
    label_objective: str = "cover"
    """What a label is (docs/pipeline.md section 7.5; a registered `schemas.objectives.Objective`): 'cover',
    the paper's (the fewest views covering P_full's keys the input misses); 'max_coverage', the at most
    `label_budget` views that see the most
    of what all views see; 'partial_cover', the fewest views that bring what is seen to `label_tau` of
    what all views see, seeing the most among those. The last two are judged on the visibility sets V_i,
    the coverage `datagen evaluate` reports."""
    label_budget: int = Field(3, ge=1, le=MAX_VIEWS, strict=True)
    """'max_coverage': most views a label may hold beyond the input views."""
    label_tau: float = Field(0.9, gt=0.0, le=1.0, allow_inf_nan=False)
    """'partial_cover': the share of what all views see that input and label must see together."""

    @model_validator(mode="before")
    @classmethod
    def _poco_version_defaults(cls, data: Any) -> Any:
        """The preset and threshold the config does not name are its ``poco_version``'s, so a version
        brings its network whole and ``poco_version = 2`` alone goes back to version 2's."""
        if not isinstance(data, dict):
            return data
        number = data.get("poco_version", LATEST_POCO_VERSION)
        version = POCO_VERSIONS.get(number) if isinstance(number, int) else None
        if version is None:
            return data  # the field's own check names the allowed range
        return {"poco_version": number, "poco_preset": version.preset, "poco_threshold": version.threshold, **data}

    @field_validator("grid_offset")
    @classmethod
    def _offset_in_unit_cell(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        for component in value:
            if not (0.0 <= component < 1.0) or not math.isfinite(component):
                raise ValueError(f"each component must be in [0, 1) voxels, got {component}")
        return value

    @field_validator("label_objective")
    @classmethod
    def _registered_objective(cls, value: str, info: ValidationInfo) -> str:
        if not _recorded(info):
            objective_named(value)
        return value

    @field_validator("refiner")
    @classmethod
    def _registered_refiner(cls, value: str, info: ValidationInfo) -> str:
        if not _recorded(info):
            refiner_kind(value)
        return value

    @field_validator("size_range")
    @classmethod
    def _ordered_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        if value[0] > value[1]:
            raise ValueError(f"needs min <= max, got [{value[0]}, {value[1]}]")
        return value

    @model_validator(mode="after")
    def _alpha_within_views(self) -> GenerationConfig:
        n = self.view_space.count
        if not (1 <= self.alpha <= n):
            raise ValueError(f"alpha = {self.alpha} is outside the allowed range 1..{n} (view_space.count)")
        return self

    @model_validator(mode="after")
    def _tie_break_of_covers(self) -> GenerationConfig:
        objective = OBJECTIVES.get(self.label_objective)  # None: a recorded plug-in's, not installed here
        if objective is not None and not objective.ranks_ties and self.label_tie_break != "index":
            raise ValueError(
                f"label_tie_break = {self.label_tie_break!r} ranks views by the cover problem's U; the "
                f"{self.label_objective!r} objective breaks ties by view index: leave label_tie_break = 'index'"
            )
        return self

    @property
    def num_views(self) -> int:
        return self.view_space.count

    @property
    def refiner_kind(self) -> RefinerKind:
        """The refiner's registered `RefinerKind`."""
        return refiner_kind(self.refiner)

    @property
    def objective(self) -> Objective:
        """The label objective's registered `Objective`."""
        return objective_named(self.label_objective)

    def objective_text(self) -> str:
        """The label objective with the parameter it reads: ``cover``, ``max_coverage (budget 3)``, ..."""
        objective = self.objective
        used = [f"{objective.text_names.get(name, name)} {getattr(self, name)}" for name in objective.fields]
        return self.label_objective + (f" ({', '.join(used)})" if used else "")

    def tau_keys(self, reference: int) -> int:
        """The least number of keys that is at least `label_tau` of ``reference`` keys (tau read as the
        decimal it was written as, so 0.9 of 1,000 keys is 900, not 901)."""
        return math.ceil(Fraction(self.label_tau).limit_denominator(1_000_000) * reference)

    @property
    def band_keys_sq(self) -> int:
        """The band radius as a squared key distance: |dk|^2 <= this (25 for the defaults)."""
        return math.floor((self.band / self.voxel_size) ** 2 + 1e-9)

    def named_files(self) -> dict[str, Path]:
        """The files this config names, by field: a view-space file, the POCO weights (the shipped
        file for "builtin")."""
        files = {"poco_weights": self.poco_weights_path()}
        if self.view_space.is_file:
            files["view_space.source"] = Path(self.view_space.source)
        return files

    def poco_weights_path(self) -> Path:
        """The weights file the ``poco`` refiner loads."""
        if self.poco_weights == BUILTIN_POCO_WEIGHTS:
            return builtin_poco_weights(self.poco_version)
        return Path(self.poco_weights)

    def canonical_dict(self) -> dict[str, Any]:
        """The config as plain data with files replaced by the sha256 of their content.

        File paths are resolved when the config is loaded (relative to the config file), so the
        path here is the one to read. The shipped weights enter by content like any other file when
        the ``poco`` refiner loads them, so ``"builtin"`` and the path of the same file hash alike;
        other refiners never load them, so there ``"builtin"`` stays the word and their datasets keep
        their identity across an upgrade of the shipped weights.
        """
        data = self.model_dump(mode="json")
        for name, value in FIELDS_ADDED_LATER.items():
            if data[name] == value:
                del data[name]  # a dataset made before the field existed keeps its hash
        kind = self.refiner_kind
        for name in REFINER_FIELDS_ADDED_LATER - set(kind.fields):
            data.pop(name, None)  # a refiner that does not read it: its datasets keep their hash
        for name in label_fields() - set(self.objective.fields):
            del data[name]  # a field the objective does not read changes no sample
        if self.view_space.is_file:
            data["view_space"]["source"] = "sha256:" + file_sha256(Path(self.view_space.source))
        for name in kind.files:  # what the refiner loads enters by content
            data[name] = "sha256:" + file_sha256(self.named_files()[name])
        if self.poco_weights != BUILTIN_POCO_WEIGHTS:  # a path names its file by content, whoever reads it
            data["poco_weights"] = "sha256:" + file_sha256(self.poco_weights_path())
        return data

    def scene_identity(self) -> dict[str, Any]:
        """The fields that decide what each view sees of a prepared object (`SCENE_FIELDS`, files by
        content): two configs that agree here image every object alike, whatever their refiner, labels
        or rotations. A trained planner expects the scene identity of its training data."""
        data = self.canonical_dict()
        return {name: data[name] for name in SCENE_FIELDS}

    def config_hash(self) -> str:
        """sha256 of the canonical JSON (sorted keys, no spaces, floats by repr)."""
        return hashlib.sha256(canonical_json(self.canonical_dict()).encode()).hexdigest()


def canonical_json(data: Any) -> str:
    """Sorted keys, no spaces; Python's json writes floats by repr, which round-trips exactly."""
    return json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)


def builtin_poco_weights(version: int = 1) -> Path:
    """The POCO weights shipped with datagen for a ``poco_version`` (``datagen/data/poco_small.pt`` for
    versions 1-3), found without importing datagen (`BUILTIN_POCO_WEIGHTS_FILE` overrides)."""
    if BUILTIN_POCO_WEIGHTS_FILE is not None:
        return BUILTIN_POCO_WEIGHTS_FILE
    spec = importlib.util.find_spec("datagen")
    if spec is None or not spec.submodule_search_locations:
        raise DatagenError(
            "poco_weights = 'builtin' needs the datagen package, which is not installed here; "
            "set poco_weights to a weights file"
        )
    return Path(next(iter(spec.submodule_search_locations))) / "data" / POCO_VERSIONS[version].weights_file


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except FileNotFoundError:
        raise MissingConfigFile(
            f"{path}: file named by the config not found; it enters the config hash by its content "
            "(restore it, or reinstall datagen for the built-in weights)",
            path,
        ) from None
    return digest.hexdigest()


class MissingConfigFile(DatagenError):
    """A file the config names (its content enters the hash) is not there; ``filename`` names it."""

    def __init__(self, message: str, path: Path | str = "") -> None:
        super().__init__(message)
        self.filename = str(path)
