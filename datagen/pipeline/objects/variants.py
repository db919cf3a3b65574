"""Seeded shape variants (``variant=SEED`` on an objects line): more training objects than meshes.

Why: a planner trained on few meshes learns those meshes. A variant is its base object bent out of
shape by a smooth deformation, cheap to make and different enough in proportions and silhouette to
count as another object, while the base's topology, holes and detail stay. Variant ``s`` of an object
is a pure function of ``s`` and the variant's object id (a hash of the base's mesh bytes or built-in
identity, its options and ``s``; unlike the base's id, every spec carries it, also a worker's): its
parameters come from ``default_rng(SeedSequence([s, object id prefix, VARIANT_STREAM]))``, never from a
global seed.

Preparation applies it after units, up axis and centring, before scaling into the size range, in the
bounding-box-centred frame with L = the largest extent after step 1:

1. Anisotropic scaling: per-axis factors uniform in [0.7, 1.4], divided by their geometric mean, so
   the proportions change (up to 2:1 between axes) but not the volume.
2. Twist about the vertical (z) axis: angle proportional to height, ``twist * z / L``, with the twist
   uniform in +-[10, 40] degrees, so an object as tall as it is wide turns by that much over its
   height and a flat one (a gear, a plate) less, instead of being sheared into a propeller.
3. Bend: the z axis curved into a circular arc of curvature ``bend / L`` in a vertical plane at a
   uniform azimuth, bend uniform in [10, 30] degrees (both ends move toward the azimuth). The radius
   (at least L / 30 degrees = 1.9 L) exceeds every point's distance from the axis (at most 0.71 L), so
   the map stays one-to-one.

Each step is a smooth, orientation-preserving bijection of the object's box (Jacobian determinants 1,
1 and r/R > 0.6), so a watertight mesh stays watertight and faces keep their orientation. The twist
and the bend are never near zero, so no variant is just its base rescaled. Long edges are first
subdivided to L/20 (coarser when that would exceed `MAX_FACES`): a cube's 12 faces would otherwise
stay flat under a bend. `describe_variant` gives the drawn parameters (``datagen objects show`` prints
them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import trimesh

from datagen.errors import InvalidArgument
from datagen.pipeline.objects.spec import ObjectSpec

VARIANT_STREAM = 0x7A81
"""Tags the variant stream in its SeedSequence, apart from every other use of the same numbers."""
SCALE_RANGE = (0.7, 1.4)
TWIST_DEG = (10.0, 40.0)
"""Magnitude of the twist over a height of L; the sign is drawn too."""
BEND_DEG = (10.0, 30.0)
"""Bend over a height of L."""
EDGE_FRACTION = 1.0 / 20.0
"""Subdivide edges longer than this fraction of L before deforming."""
MAX_FACES = 200_000
"""Subdivision never takes a mesh past this many faces (a finer mesh is deformed as it is)."""
SEED_SPACE = 1_000_000
"""``datagen objects variants`` draws its seeds below this (short, readable names: ``mug-v482913``)."""
MAX_VARIANTS = 1_000
"""At most this many variants per object from ``datagen objects variants``."""
SEEDS_STREAM = 0x7A82

Vertices = npt.NDArray[np.float64]
Faces = npt.NDArray[np.int64]


@dataclass(frozen=True)
class VariantParameters:
    """The drawn deformation of one variant; angles in degrees."""

    seed: int
    scale: tuple[float, float, float]
    """Per-axis factors (x, y, z), geometric mean 1."""
    twist: float
    """Signed turn about z over a height equal to the largest extent."""
    bend: float
    """Bend of the z axis over a height equal to the largest extent."""
    azimuth: float
    """Direction in the xy plane, from +x toward +y, that the bent ends move toward."""

    def __str__(self) -> str:
        sx, sy, sz = self.scale
        return (
            f"variant {self.seed}: scale {sx:.3f} x {sy:.3f} x {sz:.3f}, twist {self.twist:+.1f} deg, "
            f"bend {self.bend:.1f} deg toward azimuth {self.azimuth:.0f} deg"
        )


def draw_parameters(seed: int, object_id: str) -> VariantParameters:
    """Variant ``seed`` of the object ``object_id``: the same inputs always give the same parameters."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, int(object_id[:16], 16), VARIANT_STREAM]))
    factors = rng.uniform(*SCALE_RANGE, size=3)
    factors = factors / np.exp(np.log(factors).mean())
    twist = float(rng.uniform(*TWIST_DEG)) * (1.0 if rng.random() < 0.5 else -1.0)
    return VariantParameters(
        seed=seed,
        scale=(float(factors[0]), float(factors[1]), float(factors[2])),
        twist=twist,
        bend=float(rng.uniform(*BEND_DEG)),
        azimuth=float(rng.uniform(0.0, 360.0)),
    )


def draw_variant_seeds(count: int, seed: int) -> list[int]:
    """``count`` distinct variant seeds drawn from ``seed``, ascending: the same inputs, the same seeds."""
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_VARIANTS:
        raise InvalidArgument(f"--count {count!r} is out of range; ask for 1 to {MAX_VARIANTS} variants per object")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InvalidArgument(f"--seed {seed!r} is not allowed; use a non-negative integer")
    rng = np.random.default_rng(np.random.SeedSequence([seed, SEEDS_STREAM]))
    return sorted(int(value) for value in rng.choice(SEED_SPACE, size=count, replace=False))


def describe_variant(spec: ObjectSpec) -> VariantParameters | None:
    """The deformation preparation applies to ``spec``; None when it is no variant."""
    if spec.options.variant is None:
        return None
    return draw_parameters(spec.options.variant, spec.object_id)


def make_variant(vertices: Vertices, faces: Faces, spec: ObjectSpec) -> tuple[Vertices, Faces]:
    """Subdivide and deform a bounding-box-centred mesh into ``spec``'s variant (unchanged when none)."""
    parameters = describe_variant(spec)
    if parameters is None:
        return vertices, faces
    vertices, faces = subdivide_for_bending(vertices, faces)
    return deform(vertices, parameters, _extents(vertices)), faces


def deform(points: Vertices, parameters: VariantParameters, extents: Vertices) -> Vertices:
    """Scale, twist and bend points of a centred box of ``extents`` (a smooth bijection of that box)."""
    scaled = points * np.asarray(parameters.scale)
    largest = float((extents * np.asarray(parameters.scale)).max())
    if largest <= 0.0:
        return scaled
    return _bend(_twist(scaled, math.radians(parameters.twist) / largest), parameters, largest)


def _twist(points: Vertices, rate: float) -> Vertices:
    """Turn each horizontal slice about z by ``rate * z`` radians."""
    angle = rate * points[:, 2]
    c, s = np.cos(angle), np.sin(angle)
    x, y = points[:, 0], points[:, 1]
    return np.column_stack((c * x - s * y, s * x + c * y, points[:, 2]))


def _bend(points: Vertices, parameters: VariantParameters, largest: float) -> Vertices:
    """Curve the z axis into an arc of radius ``largest / bend`` whose centre lies toward the azimuth:
    a point at distance r from that centre's vertical line turns about it by z / radius."""
    radius = largest / math.radians(parameters.bend)
    azimuth = math.radians(parameters.azimuth)
    direction = np.array([math.cos(azimuth), math.sin(azimuth)])
    distance = radius - points[:, :2] @ direction
    angle = points[:, 2] / radius
    bent = points.copy()
    bent[:, :2] += np.outer(distance * 2.0 * np.sin(angle / 2.0) ** 2, direction)  # r (1 - cos), stably
    bent[:, 2] = distance * np.sin(angle)
    return bent


def subdivide_for_bending(vertices: Vertices, faces: Faces) -> tuple[Vertices, Faces]:
    """Split edges longer than L/20 (at shared midpoints, so watertight stays watertight), coarser when
    that would take the mesh past `MAX_FACES`; a mesh already that fine is returned as it is."""
    if len(faces) >= MAX_FACES:
        return vertices, faces
    longest = _longest_edges(vertices, faces)
    max_edge = EDGE_FRACTION * float(_extents(vertices).max())
    while _faces_after_split(longest, max_edge) > MAX_FACES:
        max_edge *= math.sqrt(2.0)
    if max_edge <= 0.0 or longest.max() <= max_edge:
        return vertices, faces
    new_vertices, new_faces = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=max_edge, max_iter=32)
    return np.asarray(new_vertices, dtype=np.float64), np.asarray(new_faces, dtype=np.int64)


def _faces_after_split(longest: Vertices, max_edge: float) -> int:
    """Faces after halving every face until its longest edge is at most ``max_edge`` (an upper estimate
    of the adaptive split, which halves only the long edges)."""
    if max_edge <= 0.0:
        return 0
    halvings = np.ceil(np.log2(np.maximum(longest / max_edge, 1.0)))
    return int((4.0**halvings).sum())


def _longest_edges(vertices: Vertices, faces: Faces) -> Vertices:
    triangles = vertices[faces]
    edges = triangles - np.roll(triangles, 1, axis=1)
    return np.sqrt((edges**2).sum(axis=2)).max(axis=1)


def _extents(vertices: Vertices) -> Vertices:
    return vertices.max(axis=0) - vertices.min(axis=0)
