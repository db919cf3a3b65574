"""The built-in shapes: named, fixed parameter sets of the families in ``datagen.shapes.families``.

A built-in's object id hashes ``builtin_generator_identity`` (family, name, every parameter and
``BUILTIN_GENERATOR_VERSION``), never the mesh bytes, which may differ between library versions. Every
parameter of the family is spelled out here, so a changed default in ``families.py`` cannot silently change
a built-in without changing its identity; bump the version whenever a family's geometry changes.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import trimesh

from datagen.shapes import families as shapes

BUILTIN_GENERATOR_VERSION: int = 1
"""Bump when the geometry of any built-in changes (a family's code, not only its parameters here)."""


@dataclass(frozen=True)
class BuiltinShape:
    """One built-in: which family builds it, with which parameters."""

    name: str
    family: str
    """Name of the generator function in ``datagen.shapes.families``."""
    params: dict[str, float | int]
    """Every argument of the family, explicitly (metres, radians, counts)."""
    description: str
    """One line, for ``datagen objects builtins``."""


_BUILTINS: tuple[BuiltinShape, ...] = (
    BuiltinShape(
        "mug",
        "mug",
        {
            "radius": 0.04,
            "height": 0.095,
            "wall": 0.005,
            "handle_radius": 0.026,
            "handle_thickness": 0.011,
            "sections": 64,
        },
        "straight cup with a round loop handle, open top, 5 mm wall",
    ),
    BuiltinShape(
        "bowl",
        "bowl",
        {
            "radius": 0.065,
            "height": 0.055,
            "wall": 0.005,
            "foot_radius": 0.032,
            "foot_height": 0.006,
            "sections": 72,
        },
        "rounded bowl on a ring foot, 5 mm wall",
    ),
    BuiltinShape(
        "bottle",
        "bottle",
        {
            "radius": 0.032,
            "height": 0.14,
            "wall": 0.004,
            "shoulder": 0.09,
            "neck_radius": 0.012,
            "neck_height": 0.028,
            "sections": 64,
        },
        "hollow bottle: straight body, smooth shoulder, open neck with a lip",
    ),
    BuiltinShape(
        "vase",
        "vase",
        {
            "base_radius": 0.03,
            "belly_radius": 0.05,
            "waist_radius": 0.022,
            "lip_radius": 0.034,
            "height": 0.145,
            "wall": 0.0045,
            "sections": 64,
        },
        "hollow vase with a belly, a narrow waist and a flared lip",
    ),
    BuiltinShape(
        "torus",
        "torus",
        {"major_radius": 0.045, "minor_radius": 0.014, "sections": 64},
        "ring lying flat (torus)",
    ),
    BuiltinShape(
        "torus_knot",
        "torus_knot",
        {
            "p": 2,
            "q": 3,
            "major_radius": 0.042,
            "minor_radius": 0.018,
            "tube_radius": 0.0075,
            "samples": 240,
            "tube_sections": 16,
        },
        "trefoil: a round tube along the (2, 3) torus knot, lying flat",
    ),
    BuiltinShape(
        "torus_knot_3_5",
        "torus_knot",
        {
            "p": 3,
            "q": 5,
            "major_radius": 0.045,
            "minor_radius": 0.02,
            "tube_radius": 0.0055,
            "samples": 320,
            "tube_sections": 14,
        },
        "a thinner tube along the (3, 5) torus knot, lying flat",
    ),
    BuiltinShape(
        "box_with_hole",
        "box_with_hole",
        {
            "size_x": 0.09,
            "size_y": 0.05,
            "size_z": 0.06,
            "hole_radius": 0.016,
            "cross_hole_radius": 0.0,
            "sections": 48,
        },
        "block with a round through hole along y",
    ),
    BuiltinShape(
        "box_with_two_holes",
        "box_with_hole",
        {
            "size_x": 0.1,
            "size_y": 0.06,
            "size_z": 0.05,
            "hole_radius": 0.013,
            "cross_hole_radius": 0.008,
            "sections": 48,
        },
        "block with a horizontal bore and a vertical bore off to one side",
    ),
    BuiltinShape(
        "l_bracket",
        "l_bracket",
        {
            "length": 0.09,
            "height": 0.07,
            "width": 0.045,
            "thickness": 0.008,
            "hole_radius": 0.005,
            "gusset": 0.025,
            "sections": 32,
        },
        "right-angle bracket with a web and a bolt hole in each plate",
    ),
    BuiltinShape(
        "capsule",
        "capsule",
        {"length": 0.11, "radius": 0.022, "sections": 48},
        "pill lying on its side",
    ),
    BuiltinShape(
        "cone",
        "cone",
        {"radius": 0.045, "height": 0.11, "tip_radius": 0.0, "sections": 64},
        "cone standing on its base",
    ),
    BuiltinShape(
        "stacked_cylinders",
        "stacked_cylinders",
        {
            "radius_bottom": 0.045,
            "height_bottom": 0.03,
            "radius_middle": 0.032,
            "height_middle": 0.035,
            "radius_top": 0.018,
            "height_top": 0.04,
            "offset": 0.012,
            "sections": 48,
        },
        "three cylinders stacked off-axis like blocks",
    ),
    BuiltinShape(
        "chair",
        "chair",
        {
            "seat_size": 0.055,
            "seat_height": 0.05,
            "seat_thickness": 0.007,
            "leg_size": 0.0065,
            "back_height": 0.055,
            "back_thickness": 0.006,
        },
        "chair frame: four legs, a seat and a backrest on two posts",
    ),
    BuiltinShape(
        "table",
        "table",
        {
            "top_length": 0.13,
            "top_width": 0.085,
            "top_thickness": 0.008,
            "height": 0.075,
            "leg_radius": 0.005,
            "inset": 0.012,
            "sections": 24,
        },
        "table: slab on four round legs with a stretcher frame",
    ),
    BuiltinShape(
        "dumbbell",
        "dumbbell",
        {
            "bar_radius": 0.007,
            "bar_length": 0.08,
            "weight_radius": 0.028,
            "weight_width": 0.024,
            "sections": 48,
        },
        "hand weight lying on its side",
    ),
    BuiltinShape(
        "mushroom",
        "mushroom",
        {"stem_radius": 0.012, "stem_height": 0.06, "cap_radius": 0.05, "cap_height": 0.035, "sections": 64},
        "stem under a wide domed cap (overhang)",
    ),
    BuiltinShape(
        "lamp",
        "lamp",
        {
            "base_radius": 0.04,
            "base_height": 0.01,
            "stem_radius": 0.005,
            "stem_height": 0.1,
            "shade_radius": 0.05,
            "shade_height": 0.045,
            "wall": 0.004,
            "sections": 64,
        },
        "table lamp: disc base, thin stem, hollow conical shade",
    ),
    BuiltinShape(
        "gear",
        "gear",
        {
            "teeth": 14,
            "outer_radius": 0.05,
            "tooth_depth": 0.008,
            "thickness": 0.014,
            "bore_radius": 0.01,
            "hub_radius": 0.02,
            "hub_height": 0.008,
        },
        "spur-gear-like disc with a hub and a bore, lying flat",
    ),
    BuiltinShape(
        "hex_nut",
        "hex_nut",
        {"across_flats": 0.07, "height": 0.035, "bore_radius": 0.017, "chamfer": 0.006, "sections": 48},
        "large hexagonal nut with chamfered corners",
    ),
    BuiltinShape(
        "chess_pawn",
        "chess_pawn",
        {"base_radius": 0.03, "height": 0.1, "head_radius": 0.016, "sections": 64},
        "chess pawn: stepped base, tapering body, collar, ball head",
    ),
    BuiltinShape(
        "cylinder_and_ball",
        "primitive_pair",
        {
            "first": 1,
            "second": 2,
            "size_first": 0.075,
            "size_second": 0.05,
            "shift_x": 0.012,
            "shift_y": -0.006,
            "tilt": 0.35,
            "sections": 40,
        },
        "union of a cylinder and a ball sunk off-centre into its top",
    ),
)

_BY_NAME: dict[str, BuiltinShape] = {shape.name: shape for shape in _BUILTINS}


def builtin_names() -> list[str]:
    """Every built-in name, sorted (the order of listings and of ``examples/builtin.txt``)."""
    return sorted(_BY_NAME)


def get_builtin(name: str) -> BuiltinShape:
    """The built-in called ``name``; ``KeyError(name)`` when there is none."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(name) from None


def builtin_generator_identity(name: str) -> dict[str, Any]:
    """What a built-in's object id is made of: family, name, parameters and generator version."""
    shape = get_builtin(name)
    return {
        "generator": shape.family,
        "name": shape.name,
        "params": dict(shape.params),
        "version": BUILTIN_GENERATOR_VERSION,
    }


@functools.cache
def _build(name: str) -> trimesh.Trimesh:
    """Build once per process: the booleans cost tens of milliseconds and a job asks many times."""
    shape = get_builtin(name)
    return shapes.FAMILIES[shape.family](**shape.params)


def make_builtin(name: str) -> trimesh.Trimesh:
    """A fresh copy of the built-in mesh (callers may transform it freely)."""
    return _build(name).copy()
