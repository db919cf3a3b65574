"""Built-in shapes, their registry, and the seeded synthetic set."""

from __future__ import annotations

import inspect
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from datagen.shapes import builtins
from datagen.shapes import families as shapes
from datagen.shapes import synthetic as synth

ROOT = Path(__file__).resolve().parents[2]
NAMES = builtins.builtin_names()


def test_there_are_enough_builtins_with_sorted_unique_names() -> None:
    assert len(NAMES) >= 14
    assert sorted(NAMES) == NAMES
    assert len(set(NAMES)) == len(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_builtin_is_a_watertight_volume_of_tabletop_size(name: str) -> None:
    mesh = builtins.make_builtin(name)
    assert mesh.is_watertight
    assert mesh.is_volume
    assert mesh.volume > 0
    assert mesh.body_count == 1
    assert 0.06 <= float(mesh.extents.max()) <= 0.15
    assert 1000 <= len(mesh.faces) <= 40_000
    assert abs(float(mesh.bounds[0, 2])) < 1e-9


@pytest.mark.parametrize("name", NAMES)
def test_builtin_is_deterministic(name: str) -> None:
    shape = builtins.get_builtin(name)
    fresh = shapes.FAMILIES[shape.family](**shape.params)
    cached = builtins.make_builtin(name)
    assert np.array_equal(fresh.vertices, cached.vertices)
    assert np.array_equal(fresh.faces, cached.faces)


def test_make_builtin_returns_independent_copies() -> None:
    first = builtins.make_builtin("mug")
    first.apply_translation([1.0, 0.0, 0.0])
    assert float(builtins.make_builtin("mug").bounds[0, 0]) < 0.5


@pytest.mark.parametrize("name", NAMES)
def test_builtin_params_spell_out_every_family_argument(name: str) -> None:
    """Defaults in families.py must not be able to change a built-in behind its identity's back."""
    shape = builtins.get_builtin(name)
    assert shape.family in shapes.FAMILIES
    expected = set(inspect.signature(shapes.FAMILIES[shape.family]).parameters)
    assert set(shape.params) == expected
    assert shape.description and "\n" not in shape.description


def test_identities_are_json_and_distinct() -> None:
    identities = [builtins.builtin_generator_identity(name) for name in NAMES]
    encoded = [json.dumps(identity, sort_keys=True) for identity in identities]
    assert len(set(encoded)) == len(NAMES)
    for name, identity in zip(NAMES, identities, strict=True):
        assert identity["name"] == name
        assert identity["version"] == builtins.BUILTIN_GENERATOR_VERSION
        assert identity["generator"] == builtins.get_builtin(name).family
        assert json.loads(json.dumps(identity)) == identity


def test_unknown_builtin_raises_key_error() -> None:
    with pytest.raises(KeyError):
        builtins.get_builtin("no_such_shape")
    with pytest.raises(KeyError):
        builtins.builtin_generator_identity("no_such_shape")


def test_example_lists_exactly_the_builtins() -> None:
    lines = (ROOT / "examples" / "builtin.txt").read_text(encoding="utf-8").splitlines()
    listed = [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]
    assert listed == [f"builtin:{name}" for name in NAMES]


def test_torus_knot_tube_does_not_touch_itself() -> None:
    """Every surface vertex must be at least one tube radius from every part of the centre curve."""
    for name in ("torus_knot", "torus_knot_3_5"):
        params = builtins.get_builtin(name).params
        t = np.linspace(0.0, 2.0 * np.pi, 20_000, endpoint=False)
        curve, _ = shapes._knot_curve(
            int(params["p"]),
            int(params["q"]),
            float(params["major_radius"]),
            float(params["minor_radius"]),
            t,
        )
        mesh = builtins.make_builtin(name)
        # _finish lifted the knot to rest on z = 0. Each ring's vertices average to its centre and the
        # sampled centre line averages to z = 0, so the mean vertex height is exactly that lift.
        curve[:, 2] += float(mesh.vertices[:, 2].mean())
        distance, _ = cKDTree(curve).query(mesh.vertices)
        assert float(distance.min()) > 0.99 * float(params["tube_radius"])


def test_torus_knot_refuses_a_self_intersecting_tube() -> None:
    with pytest.raises(shapes.ShapeError):
        shapes.torus_knot(tube_radius=0.02)


def test_revolve_profile_makes_closed_volumes() -> None:
    from shapely.geometry import Polygon

    solid = shapes.revolve_profile(Polygon([(0, 0), (0.03, 0), (0.02, 0.05), (0, 0.05)]), 24)
    ring = shapes.revolve_profile(Polygon([(0.02, 0), (0.03, 0), (0.03, 0.01), (0.02, 0.01)]), 24)
    for mesh in (solid, ring):
        assert mesh.is_watertight and mesh.is_volume and mesh.volume > 0


def _listed(objects_file: Path) -> list[tuple[Path, str]]:
    rows = []
    for line in objects_file.read_text(encoding="utf-8").splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        path, *options = line.split()
        pairs = dict(option.split("=", 1) for option in options)
        rows.append((objects_file.parent / path, pairs["name"]))
    return rows


def _file_bytes(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def synth_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synth.synthesize(24, 11, tmp_path_factory.mktemp("synth_a"))


def test_synthesize_lists_existing_watertight_meshes(synth_set: Path) -> None:
    assert synth_set.name == "objects.txt"
    rows = _listed(synth_set)
    assert [path.name for path, _ in rows] == [f"synth_{i:04d}.ply" for i in range(24)]
    assert len({name for _, name in rows}) == 24
    families = set()
    for path, name in rows:
        assert path.is_file()
        families.add(name.split("_", 2)[2])
        mesh = trimesh.load(path, force="mesh", process=False)  # as the pipeline loads files
        assert mesh.is_watertight and mesh.is_volume, name
        assert synth.MIN_EXTENT <= float(mesh.extents.max()) <= synth.MAX_EXTENT, name
        assert len(mesh.faces) <= 40_000
    assert len(families) >= 8


def test_synthesize_same_seed_same_bytes(synth_set: Path, tmp_path: Path) -> None:
    again = synth.synthesize(24, 11, tmp_path / "again")
    assert _file_bytes(again.parent) == _file_bytes(synth_set.parent)


def test_synthesize_prefix_is_stable(synth_set: Path, tmp_path: Path) -> None:
    """Mesh i depends on (seed, i) only, so a shorter run writes the same first meshes."""
    short = synth.synthesize(3, 11, tmp_path / "short")
    for name in ("synth_0000.ply", "synth_0001.ply", "synth_0002.ply"):
        assert (short.parent / name).read_bytes() == (synth_set.parent / name).read_bytes()


def test_synthesize_other_seed_differs(synth_set: Path, tmp_path: Path) -> None:
    other = synth.synthesize(3, 12, tmp_path / "other")
    for name in ("synth_0000.ply", "synth_0001.ply", "synth_0002.ply"):
        assert (other.parent / name).read_bytes() != (synth_set.parent / name).read_bytes()


@pytest.mark.parametrize("count", [0, -3])
def test_synthesize_rejects_count_below_one(count: int, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"between 1 and"):
        synth.synthesize(count, 0, tmp_path)
    assert not any(tmp_path.iterdir())
