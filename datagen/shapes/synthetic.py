"""A seeded synthetic shape set: random members of the families of ``datagen.shapes.families``.

Mesh ``i`` of seed ``s`` is drawn from its own generator, ``default_rng(SeedSequence([s, i]))``, so it does
not depend on how many meshes were asked for, on the order of drawing, or on any global seed: the first
ten meshes of a 100-mesh set are the 10-mesh set. Files are binary PLY written by trimesh from bare
vertices and faces (no cached normals, colours or attributes), which makes equal seeds give equal bytes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from datagen.errors import InvalidArgument, OutputError
from datagen.shapes import families as shapes

MAX_SYNTH_COUNT = 100_000
MIN_EXTENT = 0.05
MAX_EXTENT = 0.15
_ATTEMPTS = 20
"""Draws per mesh before giving up; a draw is redone when its parameters make no valid solid."""

Params = dict[str, float | int]
Sampler = Callable[[np.random.Generator], Params]


def _u(rng: np.random.Generator, low: float, high: float) -> float:
    """A uniform draw rounded to 0.1 mm-ish precision, so parameters print and hash readably."""
    return round(float(rng.uniform(low, high)), 5)


def _mug(rng: np.random.Generator) -> Params:
    """Cups, three in four with a handle sized to fit under the rim."""
    height = _u(rng, 0.06, 0.11)
    thickness = _u(rng, 0.008, 0.012)
    handle_radius = 0.0
    if rng.random() < 0.75:
        upper = min(0.032, 0.48 * height - thickness / 2.0 - 0.005)
        handle_radius = _u(rng, min(0.016, upper), upper)
    return {
        "radius": _u(rng, 0.028, 0.045),
        "height": height,
        "wall": _u(rng, 0.004, 0.006),
        "handle_radius": handle_radius,
        "handle_thickness": thickness,
        "sections": 56,
    }


def _bowl(rng: np.random.Generator) -> Params:
    radius = _u(rng, 0.04, 0.07)
    return {
        "radius": radius,
        "height": _u(rng, 0.03, 0.06),
        "wall": _u(rng, 0.004, 0.006),
        "foot_radius": round(radius * _u(rng, 0.35, 0.55), 5),
        "foot_height": _u(rng, 0.003, 0.008),
        "sections": 64,
    }


def _bottle(rng: np.random.Generator) -> Params:
    height = _u(rng, 0.1, 0.15)
    radius = _u(rng, 0.02, 0.038)
    return {
        "radius": radius,
        "height": height,
        "wall": _u(rng, 0.004, 0.005),
        "shoulder": round(height * _u(rng, 0.5, 0.7), 5),
        "neck_radius": _u(rng, 0.009, min(0.015, radius - 0.005)),
        "neck_height": round(height * _u(rng, 0.15, 0.25), 5),
        "sections": 56,
    }


def _vase(rng: np.random.Generator) -> Params:
    return {
        "base_radius": _u(rng, 0.02, 0.035),
        "belly_radius": _u(rng, 0.035, 0.06),
        "waist_radius": _u(rng, 0.015, 0.03),
        "lip_radius": _u(rng, 0.022, 0.045),
        "height": _u(rng, 0.09, 0.15),
        "wall": _u(rng, 0.004, 0.005),
        "sections": 56,
    }


def _torus(rng: np.random.Generator) -> Params:
    major = _u(rng, 0.03, 0.055)
    return {
        "major_radius": major,
        "minor_radius": _u(rng, 0.008, min(0.022, 0.5 * major, 0.074 - major)),
        "sections": 56,
    }


def _torus_knot(rng: np.random.Generator) -> Params:
    p, q = [(2, 3), (3, 2), (2, 5), (3, 4), (3, 5)][int(rng.integers(5))]
    major = _u(rng, 0.032, 0.048)
    minor = round(major * _u(rng, 0.35, 0.5), 5)
    tube = _u(rng, 0.0045, 0.008)
    return {
        "p": p,
        "q": q,
        "major_radius": major,
        "minor_radius": minor,
        "tube_radius": tube,
        "samples": 80 * max(p, q),
        "tube_sections": 14,
    }


def _box_with_hole(rng: np.random.Generator) -> Params:
    size_x, size_z = _u(rng, 0.05, 0.12), _u(rng, 0.03, 0.09)
    cross = _u(rng, 0.004, 0.2 * min(size_x, size_z)) if rng.random() < 0.4 else 0.0
    return {
        "size_x": size_x,
        "size_y": _u(rng, 0.03, 0.08),
        "size_z": size_z,
        "hole_radius": round(min(size_x, size_z) * _u(rng, 0.2, 0.35), 5),
        "cross_hole_radius": cross,
        "sections": 40,
    }


def _l_bracket(rng: np.random.Generator) -> Params:
    length, height = _u(rng, 0.06, 0.12), _u(rng, 0.04, 0.1)
    width, thickness = _u(rng, 0.035, 0.07), _u(rng, 0.005, 0.01)
    gusset = round(min(length, height) * _u(rng, 0.2, 0.4), 5) if rng.random() < 0.6 else 0.0
    room = min(length, height) - thickness - gusset
    hole = min(_u(rng, 0.003, 0.006), room / 2.0 - 0.004, width / 4.0 - 0.004)
    return {
        "length": length,
        "height": height,
        "width": width,
        "thickness": thickness,
        "hole_radius": round(max(hole, 0.002), 5),
        "gusset": gusset,
        "sections": 24,
    }


def _capsule(rng: np.random.Generator) -> Params:
    length = _u(rng, 0.06, 0.14)
    return {"length": length, "radius": _u(rng, 0.012, min(0.035, 0.4 * length)), "sections": 40}


def _cone(rng: np.random.Generator) -> Params:
    radius = _u(rng, 0.025, 0.06)
    tip = round(radius * _u(rng, 0.1, 0.5), 5) if rng.random() < 0.4 else 0.0
    return {"radius": radius, "height": _u(rng, 0.05, 0.13), "tip_radius": tip, "sections": 56}


def _stacked_cylinders(rng: np.random.Generator) -> Params:
    bottom = _u(rng, 0.03, 0.05)
    middle = round(bottom * _u(rng, 0.6, 0.85), 5)
    return {
        "radius_bottom": bottom,
        "height_bottom": _u(rng, 0.015, 0.04),
        "radius_middle": middle,
        "height_middle": _u(rng, 0.015, 0.04),
        "radius_top": round(middle * _u(rng, 0.4, 0.8), 5),
        "height_top": _u(rng, 0.015, 0.045),
        "offset": round((bottom - middle) * _u(rng, 0.0, 0.4), 5),
        "sections": 40,
    }


def _chair(rng: np.random.Generator) -> Params:
    return {
        "seat_size": _u(rng, 0.04, 0.07),
        "seat_height": _u(rng, 0.035, 0.06),
        "seat_thickness": _u(rng, 0.005, 0.009),
        "leg_size": _u(rng, 0.005, 0.008),
        "back_height": _u(rng, 0.03, 0.06),
        "back_thickness": _u(rng, 0.005, 0.008),
    }


def _table(rng: np.random.Generator) -> Params:
    length = _u(rng, 0.08, 0.14)
    return {
        "top_length": length,
        "top_width": round(length * _u(rng, 0.5, 0.9), 5),
        "top_thickness": _u(rng, 0.006, 0.012),
        "height": _u(rng, 0.045, 0.09),
        "leg_radius": _u(rng, 0.004, 0.007),
        "inset": _u(rng, 0.008, 0.016),
        "sections": 20,
    }


def _dumbbell(rng: np.random.Generator) -> Params:
    length = _u(rng, 0.06, 0.12)
    return {
        "bar_radius": _u(rng, 0.005, 0.009),
        "bar_length": length,
        "weight_radius": _u(rng, 0.018, 0.035),
        "weight_width": _u(rng, 0.012, 0.3 * length),
        "sections": 40,
    }


def _mushroom(rng: np.random.Generator) -> Params:
    return {
        "stem_radius": _u(rng, 0.007, 0.016),
        "stem_height": _u(rng, 0.03, 0.07),
        "cap_radius": _u(rng, 0.025, 0.06),
        "cap_height": _u(rng, 0.015, 0.04),
        "sections": 56,
    }


def _lamp(rng: np.random.Generator) -> Params:
    stem = _u(rng, 0.06, 0.12)
    return {
        "base_radius": _u(rng, 0.025, 0.045),
        "base_height": _u(rng, 0.006, 0.012),
        "stem_radius": _u(rng, 0.004, 0.007),
        "stem_height": stem,
        "shade_radius": _u(rng, 0.025, 0.055),
        "shade_height": round(stem * _u(rng, 0.3, 0.5), 5),
        "wall": _u(rng, 0.004, 0.005),
        "sections": 56,
    }


def _gear(rng: np.random.Generator) -> Params:
    outer = _u(rng, 0.03, 0.07)
    # keep each tooth at least 4 mm wide at the tip (0.24 of the pitch)
    most = max(8, int(2.0 * math.pi * outer * 0.24 / 0.004))
    bore = round(outer * _u(rng, 0.15, 0.3), 5)
    depth = _u(rng, 0.004, 0.01)
    hub = min(bore + _u(rng, 0.006, 0.012), outer - depth - 0.004)
    return {
        "teeth": int(rng.integers(8, min(most, 24) + 1)),
        "outer_radius": outer,
        "tooth_depth": depth,
        "thickness": _u(rng, 0.006, 0.02),
        "bore_radius": bore,
        "hub_radius": round(hub, 5),
        "hub_height": _u(rng, 0.004, 0.012) if rng.random() < 0.6 else 0.0,
    }


def _hex_nut(rng: np.random.Generator) -> Params:
    flats = _u(rng, 0.045, 0.09)
    return {
        "across_flats": flats,
        "height": round(flats * _u(rng, 0.4, 0.8), 5),
        "bore_radius": round(flats * _u(rng, 0.2, 0.32), 5),
        "chamfer": round(flats * _u(rng, 0.04, 0.08), 5),
        "sections": 40,
    }


def _chess_pawn(rng: np.random.Generator) -> Params:
    base = _u(rng, 0.02, 0.035)
    return {
        "base_radius": base,
        "height": _u(rng, 0.07, 0.13),
        "head_radius": round(base * _u(rng, 0.4, 0.6), 5),
        "sections": 56,
    }


def _primitive_pair(rng: np.random.Generator) -> Params:
    size = _u(rng, 0.05, 0.1)
    reach = 0.25 * size
    return {
        "first": int(rng.integers(len(shapes.PRIMITIVE_KINDS))),
        "second": int(rng.integers(len(shapes.PRIMITIVE_KINDS))),
        "size_first": size,
        "size_second": round(size * _u(rng, 0.5, 0.9), 5),
        "shift_x": _u(rng, -reach, reach),
        "shift_y": _u(rng, -reach, reach),
        "tilt": _u(rng, -0.6, 0.6),
        "sections": 32,
    }


FAMILY_WEIGHTS: dict[str, tuple[float, Sampler]] = {
    "mug": (0.10, _mug),
    "bowl": (0.06, _bowl),
    "bottle": (0.06, _bottle),
    "vase": (0.06, _vase),
    "torus": (0.04, _torus),
    "torus_knot": (0.05, _torus_knot),
    "box_with_hole": (0.07, _box_with_hole),
    "l_bracket": (0.05, _l_bracket),
    "capsule": (0.03, _capsule),
    "cone": (0.03, _cone),
    "stacked_cylinders": (0.05, _stacked_cylinders),
    "chair": (0.05, _chair),
    "table": (0.05, _table),
    "dumbbell": (0.03, _dumbbell),
    "mushroom": (0.04, _mushroom),
    "lamp": (0.04, _lamp),
    "gear": (0.05, _gear),
    "hex_nut": (0.03, _hex_nut),
    "chess_pawn": (0.03, _chess_pawn),
    "primitive_pair": (0.08, _primitive_pair),
}
"""Family proportions of the synthetic set (normalised when drawn) and each family's parameter sampler."""


def draw_shape(seed: int, index: int) -> tuple[str, Params, trimesh.Trimesh]:
    """Family, parameters and mesh of synthetic shape ``index`` of ``seed``.

    A draw whose parameters make no valid solid, or a size outside [MIN_EXTENT, MAX_EXTENT], is redrawn
    from the same generator, so the outcome is still a function of (seed, index) alone.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    names = list(FAMILY_WEIGHTS)
    weights = np.array([FAMILY_WEIGHTS[name][0] for name in names])
    for _ in range(_ATTEMPTS):
        family = names[int(rng.choice(len(names), p=weights / weights.sum()))]
        params = FAMILY_WEIGHTS[family][1](rng)
        try:
            mesh = shapes.FAMILIES[family](**params)
        except shapes.ShapeError:
            continue
        if MIN_EXTENT <= float(mesh.extents.max()) <= MAX_EXTENT:
            return family, params, mesh
    raise RuntimeError(f"seed {seed}, shape {index}: no valid shape in {_ATTEMPTS} draws (a sampler is off)")


def ply_bytes(mesh: trimesh.Trimesh) -> bytes:
    """Binary PLY of the bare geometry: a fresh mesh so no cached normals or visuals leak into the file."""
    bare = trimesh.Trimesh(vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces), process=False)
    data: Any = trimesh.exchange.ply.export_ply(bare, encoding="binary", vertex_normal=False, include_attributes=False)
    return bytes(data)


def synthesize(count: int, seed: int, out_dir: Path) -> Path:
    """Write ``count`` synthetic meshes and ``objects.txt`` listing them into ``out_dir``; return the list.

    Lines read ``synth_0000.ply name=synth_0000_mug``: paths are relative to the objects file, and the
    name carries the family so listings are readable.
    """
    if isinstance(count, bool) or not isinstance(count, int | np.integer) or not 1 <= count <= MAX_SYNTH_COUNT:
        raise InvalidArgument(f"count={count!r} is out of range; synthesize between 1 and {MAX_SYNTH_COUNT} meshes")
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InvalidArgument(f"seed={seed!r} is not allowed; use a non-negative integer")
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise OutputError(f"{out_dir}: exists and is not a folder; choose another --out") from None
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot create the output folder ({exc.strerror})") from None
    digits = max(4, len(str(count - 1)))
    lines = [f"# {count} synthetic shapes, seed {seed} (datagen.shapes.synthetic; same seed, same bytes)"]
    for index in range(int(count)):
        family, _, mesh = draw_shape(seed, index)
        stem = f"synth_{index:0{digits}d}"
        _write_atomic(out_dir / f"{stem}.ply", ply_bytes(mesh))
        lines.append(f"{stem}.ply name={stem}_{family}")
    objects_file = out_dir / "objects.txt"
    _write_atomic(objects_file, ("\n".join(lines) + "\n").encode("utf-8"))
    return objects_file


def _write_atomic(path: Path, data: bytes) -> None:
    """Write through a temporary sibling and rename, so an interrupted run leaves no half-written file."""
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_bytes(data)
    temporary.replace(path)
