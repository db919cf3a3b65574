"""Parametrised, deterministic generators of watertight tabletop-like meshes (metres, z up).

Every family is a plain function of explicit numbers so that a built-in's identity can be the function
name plus its parameters: no randomness lives here (the synthetic family draws the numbers elsewhere).
Rotationally symmetric objects are drawn as a 2D profile in the (r, z) half-plane with shapely and
revolved by ``revolve_profile``; vessels get their wall thickness by buffering a centre line of the wall.
Everything else is built from trimesh primitives united or cut with manifold3d. Each family returns a
mesh that ``_finish`` has checked to be a watertight, outward-facing volume resting on z = 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt
import trimesh
from shapely import affinity
from shapely.geometry import LineString, Point, Polygon, box
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

FloatArray = npt.NDArray[np.float64]

MIN_FACES = 1000
"""Meshes with fewer faces are subdivided (flat, so the shape is unchanged) up to at least this many."""

_AXIS_TOL = 1e-12
"""Profile vertices closer than this to the axis are treated as lying on it (they become one vertex)."""
_MIN_PROFILE_STEP = 2e-4
"""Profile edges shorter than this (0.2 mm) are merged away: they only add slivers at 2 mm voxels."""


class ShapeError(ValueError):
    """Parameters that cannot make a valid (watertight, non-self-intersecting) solid."""


# ---------------------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------------------


def _finish(mesh: trimesh.Trimesh, what: str) -> trimesh.Trimesh:
    """Merge, orient outward, put the base on z = 0 and refuse anything that is not a closed volume.

    The pipeline voxelises and ray-casts these meshes, so an open or inside-out mesh would silently give
    wrong occupancy; failing here names the family instead.
    """
    mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces), process=True)
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    mesh.apply_translation([0.0, 0.0, -float(mesh.bounds[0, 2])])
    if not (mesh.is_watertight and mesh.is_volume and mesh.volume > 0):
        raise ShapeError(f"{what}: the generated mesh is not a closed, consistently wound volume")
    if mesh.body_count != 1:
        raise ShapeError(f"{what}: the parts do not meet; the mesh falls into {mesh.body_count} pieces")
    while len(mesh.faces) < MIN_FACES:
        # boxy parts come out of the booleans with a few hundred faces; splitting every triangle in four
        # keeps the shape and gives surface sampling and normals a denser, more even mesh
        mesh = mesh.subdivide()
    return mesh


def _boolean(meshes: Sequence[trimesh.Trimesh], operation: str) -> trimesh.Trimesh:
    """Union, intersection or difference through manifold3d: exact, robust, and needs no Blender."""
    if operation == "union":
        result = trimesh.boolean.union(list(meshes), engine="manifold")
    elif operation == "intersection":
        result = trimesh.boolean.intersection(list(meshes), engine="manifold")
    else:
        result = trimesh.boolean.difference(list(meshes), engine="manifold")
    return trimesh.Trimesh(vertices=np.asarray(result.vertices), faces=np.asarray(result.faces))


def union(meshes: Sequence[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Boolean union of closed meshes."""
    return _boolean(meshes, "union")


def difference(base: trimesh.Trimesh, cutters: Sequence[trimesh.Trimesh]) -> trimesh.Trimesh:
    """``base`` minus every cutter."""
    return _boolean([base, *cutters], "difference")


def _box(size: Sequence[float], center: Sequence[float]) -> trimesh.Trimesh:
    """Axis-aligned box of ``size`` centred at ``center``."""
    return trimesh.creation.box(extents=size, transform=trimesh.transformations.translation_matrix(center))


def _cylinder(
    radius: float, height: float, center: Sequence[float], axis: str = "z", sections: int = 32
) -> trimesh.Trimesh:
    """Cylinder centred at ``center`` whose axis is the world ``axis``."""
    rotation = {
        "z": np.eye(4),
        "x": trimesh.transformations.rotation_matrix(math.pi / 2, [0.0, 1.0, 0.0]),
        "y": trimesh.transformations.rotation_matrix(math.pi / 2, [1.0, 0.0, 0.0]),
    }[axis]
    transform = trimesh.transformations.translation_matrix(center) @ rotation
    return trimesh.creation.cylinder(radius=radius, height=height, sections=sections, transform=transform)


def _clean_ring(coords: FloatArray) -> FloatArray:
    """Drop repeated and near-repeated ring vertices so no revolved triangle is a sliver."""
    keep: list[FloatArray] = []
    for point in coords:
        if keep and float(np.hypot(*(point - keep[-1]))) < _MIN_PROFILE_STEP:
            # keep the axis vertex when one of the pair lies on the axis, so the profile still closes there
            if abs(point[0]) <= _AXIS_TOL < abs(keep[-1][0]):
                keep[-1] = point
            continue
        keep.append(point)
    while len(keep) > 3 and float(np.hypot(*(keep[0] - keep[-1]))) < _MIN_PROFILE_STEP:
        if abs(keep[-1][0]) <= _AXIS_TOL < abs(keep[0][0]):
            keep[0] = keep[-1]
        keep.pop()
    return np.asarray(keep, dtype=np.float64)


def _profile_chain(profile: Polygon) -> tuple[FloatArray, bool]:
    """The profile boundary as a chain of (r, z) points, and whether it is closed (misses the axis).

    A profile touching the axis becomes an open chain running counter-clockwise from the bottom axis
    point to the top one (the axis edge itself sweeps no area); one clear of the axis stays a ring.
    """
    if profile.geom_type != "Polygon" or len(profile.interiors) > 0:
        raise ShapeError("a revolved profile must be one polygon without holes")
    ring = np.asarray(orient(profile, 1.0).exterior.coords, dtype=np.float64)[:-1]
    if float(ring[:, 0].min()) < -_AXIS_TOL:
        raise ShapeError("a revolved profile must lie in the half-plane r >= 0")
    ring[np.abs(ring[:, 0]) <= _AXIS_TOL, 0] = 0.0
    ring = _clean_ring(ring)
    on_axis = ring[:, 0] == 0.0
    if not on_axis.any():
        return ring, True
    leaving = np.flatnonzero(on_axis & ~np.roll(on_axis, -1))
    if len(leaving) != 1 or int(on_axis.sum()) < 2:
        raise ShapeError("a revolved profile may touch the axis along one segment only")
    rolled = np.roll(ring, -int(leaving[0]), axis=0)
    rolled_on_axis = np.roll(on_axis, -int(leaving[0]))
    # rolled starts at the bottom axis point, then the off-axis run, then the axis run back down
    end = int(np.flatnonzero(rolled_on_axis[1:])[0]) + 1
    return rolled[: end + 1], False


def revolve_profile(profile: Polygon, sections: int) -> trimesh.Trimesh:
    """Revolve an (r, z) polygon about the z axis into a closed mesh.

    Written out rather than taken from ``trimesh.creation.revolve`` because that drops triangles below an
    absolute area (1e-8), which can open holes in millimetre-scale profiles measured in metres; here every
    profile vertex on the axis is one shared vertex and every other one a full ring, so the result is
    closed by construction.
    """
    if sections < 8:
        raise ShapeError(f"sections={sections} is too coarse; use at least 8")
    chain, closed = _profile_chain(profile)
    theta = np.arange(sections) * (2.0 * math.pi / sections)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    index = np.empty((len(chain), sections), dtype=np.int64)
    vertices: list[FloatArray] = []
    count = 0
    for k, (r, z) in enumerate(chain):
        if r == 0.0:
            vertices.append(np.array([[0.0, 0.0, z]]))
            index[k, :] = count
            count += 1
        else:
            vertices.append(np.column_stack([r * cos_t, r * sin_t, np.full(sections, z)]))
            index[k, :] = count + np.arange(sections)
            count += sections
    faces: list[npt.NDArray[np.int64]] = []
    segments = len(chain) if closed else len(chain) - 1
    for k in range(segments):
        a, b = index[k], index[(k + 1) % len(chain)]
        a_next, b_next = np.roll(a, -1), np.roll(b, -1)
        if chain[k, 0] != 0.0:
            faces.append(np.column_stack([a, a_next, b]))
        if chain[(k + 1) % len(chain), 0] != 0.0:
            faces.append(np.column_stack([a_next, b_next, b]))
    mesh = trimesh.Trimesh(vertices=np.vstack(vertices), faces=np.vstack(faces), process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _wall(centerline: Sequence[tuple[float, float]], wall: float, resolution: int = 4) -> Polygon:
    """A wall of thickness ``wall`` around a centre line in the (r, z) plane, with rounded rims."""
    band = LineString(centerline).buffer(wall / 2.0, quad_segs=resolution, cap_style="round", join_style="round")
    return _clip_to_half_plane(band)


def _clip_to_half_plane(shape: Polygon) -> Polygon:
    """Keep the r >= 0 half of a profile, so the part drawn across the axis closes the bottom."""
    bounds = shape.bounds
    clipped = shape.intersection(box(0.0, bounds[1] - 1.0, bounds[2] + 1.0, bounds[3] + 1.0))
    if clipped.geom_type != "Polygon":
        raise ShapeError("the profile falls apart into several pieces; check the wall and radii")
    return clipped


def _merge_profiles(parts: Sequence[Polygon]) -> Polygon:
    """Union of overlapping profile pieces into one polygon (an error if they do not touch)."""
    merged = unary_union(list(parts))
    if merged.geom_type != "Polygon":
        raise ShapeError("profile pieces do not overlap; they would revolve into separate bodies")
    return _clip_to_half_plane(merged)


def _smooth_curve(points: Sequence[tuple[float, float]], samples: int) -> list[tuple[float, float]]:
    """A Catmull-Rom spline through ``points``: gives vases and bottles soft outlines."""
    pts = np.asarray(points, dtype=np.float64)
    padded = np.vstack([2 * pts[0] - pts[1], pts, 2 * pts[-1] - pts[-2]])
    out: list[tuple[float, float]] = []
    for i in range(1, len(padded) - 2):
        p0, p1, p2, p3 = padded[i - 1], padded[i], padded[i + 1], padded[i + 2]
        for t in np.linspace(0.0, 1.0, samples, endpoint=False):
            point = 0.5 * (
                2 * p1 + (p2 - p0) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2 + (3 * p1 - p0 - 3 * p2 + p3) * t**3
            )
            out.append((float(point[0]), float(point[1])))
    out.append((float(pts[-1, 0]), float(pts[-1, 1])))
    return out


def _vessel_profile(outline: Sequence[tuple[float, float]], wall: float) -> Polygon:
    """Profile of an open vessel: ``outline`` is the wall's centre line from the axis at the bottom to
    the rim; the bottom is a flat disc of thickness ``wall`` resting on z = 0."""
    return _wall([(0.0, wall / 2.0), *outline], wall)


# ---------------------------------------------------------------------------------------------------------
# Vessels (revolved, hollow)
# ---------------------------------------------------------------------------------------------------------


def mug(
    radius: float = 0.04,
    height: float = 0.095,
    wall: float = 0.005,
    handle_radius: float = 0.026,
    handle_thickness: float = 0.011,
    sections: int = 64,
) -> trimesh.Trimesh:
    """A straight cup with a round-section loop handle (``handle_radius`` 0 gives a handleless cup).

    The handle is a torus minus a cylinder a little wider than the cavity: what is left of the loop ends
    inside the wall, so the union with the cup has no coincident faces and nothing pokes into the cup.
    """
    r_mid = radius - wall / 2.0
    body_outline = [(r_mid, wall / 2.0), (r_mid, height - wall / 2.0)]
    cup = revolve_profile(_vessel_profile(body_outline, wall), sections)
    if handle_radius <= 0:
        return _finish(cup, "mug")
    loop = trimesh.creation.torus(
        major_radius=handle_radius,
        minor_radius=handle_thickness / 2.0,
        major_sections=48,
        minor_sections=16,
        transform=trimesh.transformations.translation_matrix([radius, 0.0, height * 0.52])
        @ trimesh.transformations.rotation_matrix(math.pi / 2, [1.0, 0.0, 0.0]),
    )
    inside = revolve_profile(box(0.0, -0.01, radius - 0.6 * wall, height + 0.01), sections)
    handle = difference(loop, [inside])
    return _finish(union([cup, handle]), "mug")


def bowl(
    radius: float = 0.065,
    height: float = 0.055,
    wall: float = 0.005,
    foot_radius: float = 0.032,
    foot_height: float = 0.006,
    sections: int = 72,
) -> trimesh.Trimesh:
    """A rounded bowl on a ring foot; the rim flares out as a quarter ellipse from the foot."""
    angles = np.linspace(0.0, math.pi / 2.0, 14)[1:]
    r_rim = radius - wall / 2.0
    z0 = foot_height + wall / 2.0
    curve = [
        (
            foot_radius + (r_rim - foot_radius) * math.sin(a),
            z0 + (height - wall / 2.0 - z0) * (1 - math.cos(a)),
        )
        for a in angles
    ]
    shell = _wall([(0.0, z0), (foot_radius, z0), *curve], wall)
    foot = box(foot_radius - 0.9 * wall - 0.004, 0.0, foot_radius + 0.3 * wall, z0)
    return _finish(revolve_profile(_merge_profiles([shell, foot]), sections), "bowl")


def bottle(
    radius: float = 0.032,
    height: float = 0.14,
    wall: float = 0.004,
    shoulder: float = 0.09,
    neck_radius: float = 0.012,
    neck_height: float = 0.028,
    sections: int = 64,
) -> trimesh.Trimesh:
    """A bottle: straight body, smooth shoulder, narrow neck with a thickened lip, open at the top."""
    r_body = radius - wall / 2.0
    r_neck = neck_radius - wall / 2.0
    neck_base = height - neck_height
    outline = [
        (r_body, wall / 2.0),
        (r_body, shoulder),
        *_smooth_curve(
            [
                (r_body, shoulder),
                ((r_body + r_neck) / 2.0 + 0.003, (shoulder + neck_base) / 2.0),
                (r_neck, neck_base),
            ],
            8,
        )[1:],
        (r_neck, height - wall / 2.0),
    ]
    shell = _vessel_profile(outline, wall)
    lip = box(r_neck, height - 0.006, neck_radius + 0.0025, height)
    return _finish(revolve_profile(_merge_profiles([shell, lip]), sections), "bottle")


def vase(
    base_radius: float = 0.03,
    belly_radius: float = 0.05,
    waist_radius: float = 0.022,
    lip_radius: float = 0.034,
    height: float = 0.145,
    wall: float = 0.0045,
    sections: int = 64,
) -> trimesh.Trimesh:
    """A vase with a belly, a narrow waist and a flared lip, drawn as a spline through four radii."""

    def mid(radius: float) -> float:
        return radius - wall / 2.0

    knots = [
        (mid(base_radius), wall / 2.0),
        (mid(belly_radius), 0.35 * height),
        (mid(waist_radius), 0.75 * height),
        (mid(lip_radius), height - wall / 2.0),
    ]
    outline = _smooth_curve(knots, 12)
    return _finish(revolve_profile(_vessel_profile(outline, wall), sections), "vase")


# ---------------------------------------------------------------------------------------------------------
# Solids of revolution
# ---------------------------------------------------------------------------------------------------------


def torus(major_radius: float = 0.045, minor_radius: float = 0.014, sections: int = 64) -> trimesh.Trimesh:
    """A ring lying flat on the table."""
    if minor_radius >= major_radius:
        raise ShapeError("torus: minor_radius must be smaller than major_radius (else it self-intersects)")
    profile = Point(major_radius, 0.0).buffer(minor_radius, quad_segs=max(4, sections // 6))
    return _finish(revolve_profile(profile, sections), "torus")


def capsule(length: float = 0.11, radius: float = 0.022, sections: int = 48) -> trimesh.Trimesh:
    """A pill lying on its side: cylinder of ``length`` (tip to tip) with hemispherical ends."""
    if length <= 2 * radius:
        raise ShapeError("capsule: length must exceed the diameter")
    half = length / 2.0 - radius
    profile = _clip_to_half_plane(LineString([(0.0, -half), (0.0, half)]).buffer(radius, quad_segs=sections // 4))
    mesh = revolve_profile(profile, sections)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0.0, 1.0, 0.0]))
    return _finish(mesh, "capsule")


def cone(radius: float = 0.045, height: float = 0.11, tip_radius: float = 0.0, sections: int = 64) -> trimesh.Trimesh:
    """A cone (or a frustum when ``tip_radius`` > 0) standing on its base."""
    if tip_radius > 0:
        profile = Polygon([(0.0, 0.0), (radius, 0.0), (tip_radius, height), (0.0, height)])
    else:
        profile = Polygon([(0.0, 0.0), (radius, 0.0), (0.0, height)])
    return _finish(revolve_profile(profile, sections), "cone")


def mushroom(
    stem_radius: float = 0.012,
    stem_height: float = 0.06,
    cap_radius: float = 0.05,
    cap_height: float = 0.035,
    sections: int = 64,
) -> trimesh.Trimesh:
    """A stem widening at the foot under a flat-bottomed domed cap."""
    stem = Polygon(
        [
            (0.0, 0.0),
            (stem_radius * 1.5, 0.0),
            (stem_radius * 1.1, 0.012),
            (stem_radius, stem_height * 0.6),
            (stem_radius, stem_height + 0.005),
            (0.0, stem_height + 0.005),
        ]
    )
    dome = affinity.scale(Point(0.0, 0.0).buffer(1.0, quad_segs=12), cap_radius, cap_height)
    dome = affinity.translate(dome, 0.0, stem_height).intersection(
        box(0.0, stem_height - 0.006, cap_radius + 1.0, stem_height + cap_height + 1.0)
    )
    return _finish(revolve_profile(_merge_profiles([stem, dome]), sections), "mushroom")


def dumbbell(
    bar_radius: float = 0.007,
    bar_length: float = 0.08,
    weight_radius: float = 0.028,
    weight_width: float = 0.024,
    sections: int = 48,
) -> trimesh.Trimesh:
    """A hand weight lying on the table: two rounded discs on a bar (revolved, then laid along x)."""
    half = bar_length / 2.0
    bar = box(0.0, -half, bar_radius, half)
    fillet = min(0.004, weight_width / 4.0)
    disc = box(0.0, half - weight_width, weight_radius - fillet, half).buffer(fillet, quad_segs=4)
    other = affinity.scale(disc, 1.0, -1.0, origin=(0.0, 0.0))
    mesh = revolve_profile(_merge_profiles([bar, disc, other]), sections)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0.0, 1.0, 0.0]))
    return _finish(mesh, "dumbbell")


def lamp(
    base_radius: float = 0.04,
    base_height: float = 0.01,
    stem_radius: float = 0.005,
    stem_height: float = 0.1,
    shade_radius: float = 0.05,
    shade_height: float = 0.045,
    wall: float = 0.004,
    sections: int = 64,
) -> trimesh.Trimesh:
    """A table lamp: a disc base, a thin stem and a hollow conical shade hanging from its top."""
    top = stem_height + wall / 2.0
    base = (
        box(0.0, 0.0, base_radius, base_height)
        .buffer(0.002, quad_segs=3)
        .intersection(box(0.0, 0.0, base_radius + 1.0, base_height + 1.0))
    )
    stem = box(0.0, 0.0, stem_radius, top)
    shade = _wall([(0.0, top), (shade_radius * 0.45, top), (shade_radius - wall / 2.0, top - shade_height)], wall)
    return _finish(revolve_profile(_merge_profiles([base, stem, shade]), sections), "lamp")


def stacked_cylinders(
    radius_bottom: float = 0.045,
    height_bottom: float = 0.03,
    radius_middle: float = 0.032,
    height_middle: float = 0.035,
    radius_top: float = 0.018,
    height_top: float = 0.04,
    offset: float = 0.012,
    sections: int = 48,
) -> trimesh.Trimesh:
    """Three cylinders stacked like blocks, the upper two pushed off-axis by ``offset`` in turn."""
    overlap = 0.001
    bottom = _cylinder(radius_bottom, height_bottom, [0.0, 0.0, height_bottom / 2.0], sections=sections)
    z1 = height_bottom - overlap
    middle = _cylinder(
        radius_middle,
        height_middle + overlap,
        [offset, 0.0, z1 + (height_middle + overlap) / 2.0],
        sections=sections,
    )
    z2 = z1 + height_middle
    top = _cylinder(
        radius_top,
        height_top + overlap,
        [offset * 1.8, offset * 0.6, z2 + (height_top + overlap) / 2.0],
        sections=sections,
    )
    return _finish(union([bottom, middle, top]), "stacked_cylinders")


# ---------------------------------------------------------------------------------------------------------
# Swept tube
# ---------------------------------------------------------------------------------------------------------


def _knot_curve(p: int, q: int, major: float, minor: float, t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Points and unit tangents of the (p, q) torus knot on a torus of radii ``major``, ``minor``."""
    r = major + minor * np.cos(q * t)
    points = np.column_stack([r * np.cos(p * t), r * np.sin(p * t), minor * np.sin(q * t)])
    dr = -minor * q * np.sin(q * t)
    tangents = np.column_stack(
        [
            dr * np.cos(p * t) - r * p * np.sin(p * t),
            dr * np.sin(p * t) + r * p * np.cos(p * t),
            minor * q * np.cos(q * t),
        ]
    )
    return points, tangents / np.linalg.norm(tangents, axis=1, keepdims=True)


def _transported_normals(tangents: FloatArray) -> FloatArray:
    """Rotation-minimising normals along a closed curve, with the closing twist spread evenly.

    A Frenet frame flips at inflections; transporting a normal keeps the tube from twisting, and the
    leftover angle at the seam is shared out so the last ring meets the first one exactly.
    """
    count = len(tangents)
    seed = np.cross(tangents[0], [0.0, 0.0, 1.0])
    if np.linalg.norm(seed) < 1e-6:
        seed = np.cross(tangents[0], [1.0, 0.0, 0.0])
    normals = np.empty_like(tangents)
    current = seed / np.linalg.norm(seed)
    for i in range(count + 1):
        t = tangents[i % count]
        current = current - np.dot(current, t) * t
        current /= np.linalg.norm(current)
        if i < count:
            normals[i] = current
    # ``current`` is now the transported first normal after one full turn
    twist = math.atan2(float(np.dot(np.cross(current, normals[0]), tangents[0])), float(np.dot(current, normals[0])))
    angles = twist * np.arange(count) / count
    binormals = np.cross(tangents, normals)
    return np.cos(angles)[:, None] * normals + np.sin(angles)[:, None] * binormals


def _check_tube_clearance(points: FloatArray, tube_radius: float) -> None:
    """Refuse a tube that would touch itself: distant parts of the curve must stay two radii apart and the
    curve must bend no tighter than the tube radius."""
    steps = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)[:-1]])
    total = float(steps.sum())
    separation = np.abs(arc[:, None] - arc[None, :])
    separation = np.minimum(separation, total - separation)
    distance = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    far = separation > math.pi * tube_radius
    if far.any() and float(distance[far].min()) < 2.2 * tube_radius:
        raise ShapeError(
            f"torus_knot: tube radius {tube_radius} makes the tube touch itself "
            f"(closest approach {float(distance[far].min()):.4f} m); use a thinner tube or a larger knot"
        )
    previous, following = np.roll(points, 1, axis=0), np.roll(points, -1, axis=0)
    a = np.linalg.norm(points - previous, axis=1)
    b = np.linalg.norm(following - points, axis=1)
    c = np.linalg.norm(following - previous, axis=1)
    area2 = np.linalg.norm(np.cross(points - previous, following - points), axis=1)
    with np.errstate(divide="ignore"):
        bend_radius = np.where(area2 > 0, a * b * c / (2.0 * area2), np.inf)
    if float(bend_radius.min()) < 1.2 * tube_radius:
        raise ShapeError(f"torus_knot: the curve bends tighter than the tube radius {tube_radius}")


def torus_knot(
    p: int = 2,
    q: int = 3,
    major_radius: float = 0.042,
    minor_radius: float = 0.018,
    tube_radius: float = 0.0075,
    samples: int = 240,
    tube_sections: int = 16,
) -> trimesh.Trimesh:
    """A round tube swept along the closed (p, q) torus knot, lying flat (a trefoil for (2, 3))."""
    if math.gcd(p, q) != 1 or p < 1 or q < 1:
        raise ShapeError(f"torus_knot: p={p} and q={q} must be positive and coprime to make one closed knot")
    t = np.arange(samples, dtype=np.float64) * (2.0 * math.pi / samples)
    points, tangents = _knot_curve(p, q, major_radius, minor_radius, t)
    _check_tube_clearance(points, tube_radius)
    normals = _transported_normals(tangents)
    binormals = np.cross(tangents, normals)
    phi = np.arange(tube_sections) * (2.0 * math.pi / tube_sections)
    rings = (
        points[:, None, :]
        + tube_radius * np.cos(phi)[None, :, None] * normals[:, None, :]
        + tube_radius * np.sin(phi)[None, :, None] * binormals[:, None, :]
    )
    i, j = np.meshgrid(np.arange(samples), np.arange(tube_sections), indexing="ij")
    a = i * tube_sections + j
    b = i * tube_sections + (j + 1) % tube_sections
    c = ((i + 1) % samples) * tube_sections + j
    d = ((i + 1) % samples) * tube_sections + (j + 1) % tube_sections
    faces = np.vstack(
        [
            np.column_stack([a.ravel(), c.ravel(), b.ravel()]),
            np.column_stack([b.ravel(), c.ravel(), d.ravel()]),
        ]
    )
    mesh = trimesh.Trimesh(vertices=rings.reshape(-1, 3), faces=faces, process=False)
    return _finish(mesh, "torus_knot")


# ---------------------------------------------------------------------------------------------------------
# Prismatic and assembled parts
# ---------------------------------------------------------------------------------------------------------


def box_with_hole(
    size_x: float = 0.09,
    size_y: float = 0.05,
    size_z: float = 0.06,
    hole_radius: float = 0.016,
    cross_hole_radius: float = 0.0,
    sections: int = 48,
) -> trimesh.Trimesh:
    """A block bored through along y; ``cross_hole_radius`` > 0 adds a vertical bore offset along x."""
    block = _box([size_x, size_y, size_z], [0.0, 0.0, size_z / 2.0])
    cutters = [_cylinder(hole_radius, size_y + 0.02, [0.0, 0.0, size_z / 2.0], axis="y", sections=sections)]
    if cross_hole_radius > 0:
        x = size_x / 2.0 - max(cross_hole_radius + 0.006, size_x * 0.2)
        cutters.append(_cylinder(cross_hole_radius, size_z + 0.02, [x, 0.0, size_z / 2.0], sections=sections))
    return _finish(difference(block, cutters), "box_with_hole")


def l_bracket(
    length: float = 0.09,
    height: float = 0.07,
    width: float = 0.045,
    thickness: float = 0.008,
    hole_radius: float = 0.005,
    gusset: float = 0.025,
    sections: int = 32,
) -> trimesh.Trimesh:
    """An angle bracket: two plates at a right angle, a central triangular web, a bolt hole in each plate."""
    outline = Polygon(
        [
            (0.0, 0.0),
            (length, 0.0),
            (length, thickness),
            (thickness, thickness),
            (thickness, height),
            (0.0, height),
        ]
    )
    parts = [_extrude_xz(outline, width)]
    if gusset > 0:
        # the web starts 1 mm inside both plates so the union meets no coincident faces
        inner = thickness - 0.001
        web = Polygon([(inner, inner), (thickness + gusset, inner), (inner, thickness + gusset)])
        parts.append(_extrude_xz(web, max(0.006, thickness * 0.75)))
    free = thickness + max(gusset, 0.0)
    cutters = [
        _cylinder(
            hole_radius,
            thickness * 3,
            [(length + free) / 2.0, width * 0.25, thickness / 2.0],
            sections=sections,
        ),
        _cylinder(
            hole_radius,
            thickness * 3,
            [thickness / 2.0, -width * 0.25, (height + free) / 2.0],
            axis="x",
            sections=sections,
        ),
    ]
    mesh = difference(union(parts), cutters)
    mesh.apply_translation([-length / 2.0, 0.0, 0.0])
    return _finish(mesh, "l_bracket")


def _extrude_xz(outline: Polygon, width: float) -> trimesh.Trimesh:
    """Extrude a polygon drawn in the (x, z) plane by ``width`` along y, centred on y = 0."""
    solid = trimesh.creation.extrude_polygon(outline, width)
    # rotating +90 degrees about x sends the drawing's y to z and the extrusion direction to -y
    solid.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [1.0, 0.0, 0.0]))
    solid.apply_translation([0.0, width / 2.0, 0.0])
    return solid


def chair(
    seat_size: float = 0.055,
    seat_height: float = 0.05,
    seat_thickness: float = 0.007,
    leg_size: float = 0.0065,
    back_height: float = 0.055,
    back_thickness: float = 0.006,
) -> trimesh.Trimesh:
    """A chair: four square legs, a seat slab and a backrest on two posts, united into one solid."""
    half = seat_size / 2.0 - leg_size / 2.0
    legs = [
        _box([leg_size, leg_size, seat_height], [sx * half, sy * half, seat_height / 2.0])
        for sx in (-1.0, 1.0)
        for sy in (-1.0, 1.0)
    ]
    seat_z = seat_height + seat_thickness / 2.0 - 0.001
    seat = _box([seat_size, seat_size, seat_thickness], [0.0, 0.0, seat_z])
    top = seat_height + seat_thickness - 0.001
    back_y = -seat_size / 2.0 + back_thickness / 2.0
    posts = [
        _box([leg_size, back_thickness, back_height], [sx * half, back_y, top + back_height / 2.0 - 0.001])
        for sx in (-1.0, 1.0)
    ]
    rail_height = back_height * 0.4
    rail = _box([seat_size, back_thickness, rail_height], [0.0, back_y, top + back_height - rail_height / 2.0])
    return _finish(union([*legs, seat, *posts, rail]), "chair")


def table(
    top_length: float = 0.13,
    top_width: float = 0.085,
    top_thickness: float = 0.008,
    height: float = 0.075,
    leg_radius: float = 0.005,
    inset: float = 0.012,
    sections: int = 24,
) -> trimesh.Trimesh:
    """A table: a slab on four round legs joined by a low stretcher frame."""
    leg_height = height - top_thickness + 0.001
    xs, ys = top_length / 2.0 - inset, top_width / 2.0 - inset
    legs = [
        _cylinder(leg_radius, leg_height, [sx * xs, sy * ys, leg_height / 2.0], sections=sections)
        for sx in (-1.0, 1.0)
        for sy in (-1.0, 1.0)
    ]
    top = _box([top_length, top_width, top_thickness], [0.0, 0.0, height - top_thickness / 2.0])
    bar = leg_radius * 1.4
    z = height * 0.25
    stretchers = [_box([2 * xs, bar, bar], [0.0, sy * ys, z]) for sy in (-1.0, 1.0)] + [
        _box([bar, 2 * ys, bar], [sx * xs, 0.0, z]) for sx in (-1.0, 1.0)
    ]
    return _finish(union([*legs, top, *stretchers]), "table")


def gear(
    teeth: int = 14,
    outer_radius: float = 0.05,
    tooth_depth: float = 0.008,
    thickness: float = 0.014,
    bore_radius: float = 0.01,
    hub_radius: float = 0.02,
    hub_height: float = 0.008,
) -> trimesh.Trimesh:
    """A spur-gear-like disc lying flat: trapezoidal teeth, a raised hub and a through bore."""
    if teeth < 6:
        raise ShapeError("gear: use at least 6 teeth")
    root = outer_radius - tooth_depth
    pitch = 2.0 * math.pi / teeth
    outline: list[tuple[float, float]] = []
    for k in range(teeth):
        base = k * pitch
        for frac, radius in ((-0.25, root), (-0.12, outer_radius), (0.12, outer_radius), (0.25, root)):
            angle = base + frac * pitch
            outline.append((radius * math.cos(angle), radius * math.sin(angle)))
    body = trimesh.creation.extrude_polygon(Polygon(outline), thickness)
    if hub_height > 0:
        hub = _cylinder(hub_radius, hub_height + 0.001, [0.0, 0.0, thickness + (hub_height - 0.001) / 2.0], sections=48)
        body = union([body, hub])
    bore = _cylinder(bore_radius, 2 * (thickness + hub_height), [0.0, 0.0, thickness], sections=32)
    return _finish(difference(body, [bore]), "gear")


def hex_nut(
    across_flats: float = 0.07,
    height: float = 0.035,
    bore_radius: float = 0.017,
    chamfer: float = 0.006,
    sections: int = 48,
) -> trimesh.Trimesh:
    """A large hexagonal nut with a round bore and 30-degree chamfers on the corners of both faces.

    ``chamfer`` is how far the chamfer cone pulls the corners in at each face.
    """
    circumradius = across_flats / math.sqrt(3.0)
    hexagon = Polygon(
        [(circumradius * math.cos(k * math.pi / 3), circumradius * math.sin(k * math.pi / 3)) for k in range(6)]
    )
    prism = trimesh.creation.extrude_polygon(hexagon, height)
    face_radius = circumradius - chamfer
    widest = face_radius + math.sqrt(3.0) * height / 2.0
    if widest <= circumradius:
        raise ShapeError("hex_nut: the nut is too flat for this chamfer")
    double_cone = revolve_profile(
        Polygon([(0.0, 0.0), (face_radius, 0.0), (widest, height / 2.0), (face_radius, height), (0.0, height)]),
        sections,
    )
    # turn the cone half a facet so none of its vertices lands exactly on a corner edge of the prism:
    # such exact touches make the boolean split vertices that then merge into non-manifold edges
    double_cone.apply_transform(trimesh.transformations.rotation_matrix(math.pi / sections, [0.0, 0.0, 1.0]))
    body = _boolean([prism, double_cone], "intersection")
    bore = _cylinder(bore_radius, height + 0.02, [0.0, 0.0, height / 2.0], sections=sections)
    return _finish(difference(body, [bore]), "hex_nut")


def chess_pawn(
    base_radius: float = 0.03,
    height: float = 0.1,
    head_radius: float = 0.016,
    sections: int = 64,
) -> trimesh.Trimesh:
    """A chess pawn: a stepped base, a tapering body, a collar and a ball head."""
    base = box(0.0, 0.0, base_radius, 0.012).buffer(0.002, quad_segs=3)
    step = box(0.0, 0.0, base_radius * 0.8, 0.02)
    body = Polygon([(0.0, 0.0), (base_radius * 0.62, 0.0), (base_radius * 0.3, height * 0.62), (0.0, height * 0.62)])
    collar = box(0.0, height * 0.6, head_radius * 1.2, height * 0.65)
    neck = box(0.0, height * 0.6, head_radius * 0.6, height - head_radius)
    head = Point(0.0, height - head_radius).buffer(head_radius, quad_segs=10)
    profile = _merge_profiles([base, step, body, collar, neck, head]).intersection(box(0.0, 0.0, 1.0, 1.0))
    return _finish(revolve_profile(profile, sections), "chess_pawn")


PRIMITIVE_KINDS = ("box", "cylinder", "sphere", "cone", "capsule")
"""What the integer codes of ``primitive_pair`` stand for, in order."""


def _primitive(kind: int, size: float, sections: int) -> tuple[trimesh.Trimesh, float]:
    """A primitive about ``size`` across, resting on z = 0 and centred on the z axis; and its height."""
    if kind == 0:
        height = 0.8 * size
        mesh = _box([size, 0.85 * size, height], [0.0, 0.0, height / 2.0])
    elif kind == 1:
        height = 0.8 * size
        mesh = _cylinder(size / 2.0, height, [0.0, 0.0, height / 2.0], sections=sections)
    elif kind == 2:
        height = size
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=size / 2.0)
        mesh.apply_translation([0.0, 0.0, size / 2.0])
    elif kind == 3:
        height = size
        mesh = revolve_profile(Polygon([(0.0, 0.0), (size / 2.0, 0.0), (0.0, height)]), sections)
    elif kind == 4:
        height = size
        mesh = trimesh.creation.capsule(height=size / 2.0, radius=size / 4.0, count=[sections, sections // 2])
        mesh.apply_translation([0.0, 0.0, size / 2.0])
    else:
        raise ShapeError(
            f"primitive kind {kind} is unknown; use 0..{len(PRIMITIVE_KINDS) - 1} ({', '.join(PRIMITIVE_KINDS)})"
        )
    return mesh, height


def primitive_pair(
    first: int = 1,
    second: int = 2,
    size_first: float = 0.075,
    size_second: float = 0.05,
    shift_x: float = 0.012,
    shift_y: float = -0.006,
    tilt: float = 0.35,
    sections: int = 40,
) -> trimesh.Trimesh:
    """Two primitives (codes in ``PRIMITIVE_KINDS``) united: the second, tilted by ``tilt`` radians about
    x, is centred three quarters up the first and shifted sideways, so the two always overlap."""
    base, base_height = _primitive(first, size_first, sections)
    top, top_height = _primitive(second, size_second, sections)
    top.apply_translation([0.0, 0.0, -top_height / 2.0])
    top.apply_transform(trimesh.transformations.rotation_matrix(tilt, [1.0, 0.0, 0.0]))
    top.apply_translation([shift_x, shift_y, 0.75 * base_height])
    return _finish(union([base, top]), "primitive_pair")


FAMILIES: dict[str, Callable[..., trimesh.Trimesh]] = {
    family.__name__: family
    for family in (
        mug,
        bowl,
        bottle,
        vase,
        torus,
        capsule,
        cone,
        mushroom,
        dumbbell,
        lamp,
        stacked_cylinders,
        torus_knot,
        box_with_hole,
        l_bracket,
        chair,
        table,
        gear,
        hex_nut,
        chess_pawn,
        primitive_pair,
    )
}
"""Every shape family by function name: what built-ins and the synthetic set may name as ``family``."""
