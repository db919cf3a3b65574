"""Object preparation (docs/pipeline.md section 1): load, units, up axis, centre, variant, size, yaw.

Every failure a user's file can cause raises `ObjectError` with one line naming the file and the
fix; the caller records it and goes on with the other objects.
"""

from __future__ import annotations

import math
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import trimesh

from datagen.errors import ObjectError
from datagen.pipeline.camera import max_fitting_radius
from datagen.pipeline.objects.ply_strips import PlyError, has_strips, read_strip_ply
from datagen.pipeline.objects.spec import BUILTIN_PREFIX, ObjectSpec
from datagen.pipeline.objects.variants import make_variant
from datagen.shapes import builtins
from schemas.config import GenerationConfig

MIN_AREA_M2 = 1e-12
FLAT_RATIO = 0.01
"""A mesh whose thinnest principal extent is below this share of its largest is flat: every view sees
nearly all of it (from one side or the other), so its labels are degenerate."""


@dataclass(frozen=True)
class PreparedObject:
    """A mesh in the object frame: z up, bounding-box centre at the origin, final size."""

    spec: ObjectSpec
    vertices: npt.NDArray[np.float64]
    faces: npt.NDArray[np.int64]
    units_guessed: str
    """'m' or 'mm': what the file's units were taken to be."""
    scale: float
    """Total factor applied to the file's coordinates (units times size scaling; a variant's deformation
    comes between the two and is not part of it)."""
    size: float
    """Largest bounding-box extent after preparation, metres."""
    watertight: bool

    @property
    def bounding_radius(self) -> float:
        """Radius of the origin-centred sphere holding the mesh; yaw about z keeps it."""
        return float(np.sqrt((self.vertices**2).sum(axis=1).max()))

    @property
    def thinness(self) -> float:
        """The mesh's thinnest extent over its largest, along its principal axes (0 for a plane)."""
        centred = self.vertices - self.vertices.mean(axis=0)
        axes = np.linalg.svd(centred, full_matrices=False)[2]
        extents = np.ptp(centred @ axes.T, axis=0)
        return float(extents.min() / extents.max()) if extents.max() > 0 else 0.0

    def flat_warning(self) -> str | None:
        """One line naming a flat or degenerate mesh (`FLAT_RATIO`), or None: such a mesh is made, but
        a user should know that its labels say little."""
        thinness = self.thinness
        if thinness >= FLAT_RATIO:
            return None
        where = f"{self.spec.origin}: " if self.spec.origin else ""
        return (
            f"{where}{self.spec.name}: flat (thinnest extent {thinness:.2%} of its size): every view sees nearly "
            "all of it, so its labels are degenerate; leave it out unless a sheet is meant"
        )

    def task_vertices(self, rotation: int, rotations: int) -> npt.NDArray[np.float64]:
        """Vertices in the frame of task rotation r: yawed by r * 360/rotations degrees about z."""
        return yaw(self.vertices, 2.0 * math.pi * rotation / rotations)


def yaw(vertices: npt.NDArray[np.float64], angle: float) -> npt.NDArray[np.float64]:
    c, s = math.cos(angle), math.sin(angle)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return vertices @ rotation.T


def load_mesh(spec: ObjectSpec) -> trimesh.Trimesh:
    """The object's raw mesh (file units and axes), scenes merged, textures ignored."""
    if spec.source.startswith(BUILTIN_PREFIX):
        return builtins.make_builtin(spec.source[len(BUILTIN_PREFIX) :])
    path = Path(spec.source)
    if not path.is_file():
        raise ObjectError(f"{path}: mesh file not found; fix the path in the objects file ({spec.origin})")
    if path.suffix.lower() == ".ply" and has_strips(path):
        return _load_strip_ply(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(str(path), force="mesh", process=False, skip_materials=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        reason = _load_failure(exc)
        raise ObjectError(
            f"{path}: not a readable mesh ({reason}); give an OBJ, PLY, STL, OFF or GLB file with faces"
        ) from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise ObjectError(
            f"{path}: holds no triangle faces (read as {type(loaded).__name__}); datagen needs a surface "
            "mesh, not a point cloud"
        )
    return loaded


TRUNCATED = "the file ends before the vertices and faces its header counts: truncated or damaged"
"""What a parser's shape error means to a user: numpy's "cannot reshape array of size 15 into shape
(8,3)" is what a truncated OFF, PLY or STL file gives."""


def _load_failure(exc: Exception) -> str:
    """The loader's failure in one line a user can act on."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    shape_error = ("cannot reshape", "buffer is smaller", "index", "out of bounds", "unpack requires")
    if isinstance(exc, ValueError | IndexError | struct.error) and any(word in text for word in shape_error):
        return TRUNCATED
    return text


def _load_strip_ply(path: Path) -> trimesh.Trimesh:
    """A PLY with triangle strips, which trimesh would read as bare points (`ply_strips`)."""
    try:
        vertices, faces = read_strip_ply(path)
    except PlyError as exc:
        raise ObjectError(
            f"{path}: malformed triangle-strip PLY ({exc}); re-export it with triangle strips or faces"
        ) from None
    except OSError as exc:
        raise ObjectError(f"{path}: cannot read the mesh ({exc.strerror or exc})") from None
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def prepare_object(spec: ObjectSpec, config: GenerationConfig) -> PreparedObject:
    """Load and normalise one object; raises `ObjectError` with the fix on bad input."""
    mesh = load_mesh(spec)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    where = spec.source
    if faces.size == 0 or vertices.size == 0:
        raise ObjectError(f"{where}: the mesh has no faces; export the surface with its triangles")
    if not np.isfinite(vertices).all():
        raise ObjectError(f"{where}: the mesh has NaN or infinite vertex coordinates; repair or re-export it")
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0 or float(mesh.area) <= MIN_AREA_M2 * max(1.0, _extent(mesh.vertices)) ** 2:
        raise ObjectError(f"{where}: the mesh has zero surface area (all faces degenerate); it cannot be imaged")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)

    units = spec.options.units
    units_guessed = units if units != "auto" else ("mm" if np.abs(vertices).max() >= config.mm_threshold else "m")
    unit_scale = 0.001 if units_guessed == "mm" else 1.0
    vertices = vertices * unit_scale
    if spec.options.up == "y":
        # +90 degrees about x takes +y to +z; a rotation, never the mirroring y/z swap.
        vertices = vertices @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]).T
    size = _extent(vertices)
    vertices = _centred(vertices)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if spec.options.variant is not None:
        vertices, faces = make_variant(vertices, faces, spec)
        size = _extent(vertices)
        vertices = _centred(vertices)
    if size <= 0:
        raise ObjectError(f"{where}: the mesh has zero extent; it cannot be imaged")
    target = spec.options.size if spec.options.size is not None else _clamp(size, config.size_range)
    size_scale = target / size
    vertices = vertices * size_scale

    prepared = PreparedObject(
        spec=spec,
        vertices=vertices,
        faces=faces,
        units_guessed=units_guessed,
        scale=unit_scale * size_scale,
        size=target,
        watertight=bool(mesh.is_watertight),  # a variant keeps it: shared-midpoint splits, a bijection
    )
    check_fits_image(prepared, config)
    return prepared


def check_fits_image(prepared: PreparedObject, config: GenerationConfig) -> None:
    """Refuse an object whose bounding sphere some view would not see whole."""
    limit = max_fitting_radius(config.camera, config.view_space.radius)
    radius = prepared.bounding_radius
    if radius > limit:
        largest = prepared.size * limit / radius
        raise ObjectError(
            f"{prepared.spec.source}: size {prepared.size:.4g} m does not fit the image: its bounding "
            f"sphere (radius {radius:.4g} m) exceeds the {limit:.4g} m every view at "
            f"{config.view_space.radius} m sees; use size <= {math.floor(largest * 1000) / 1000:.3f}"
        )


def _clamp(value: float, bounds: tuple[float, float]) -> float:
    return min(max(value, bounds[0]), bounds[1])


def _centred(vertices: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Translated so that the bounding-box centre is at the origin."""
    return vertices - (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0


def _extent(vertices: npt.NDArray[np.float64]) -> float:
    return float((vertices.max(axis=0) - vertices.min(axis=0)).max())
