"""View space (docs/pipeline.md section 2): the built-in table, the seeded generator and view-space files.

Truths used here are independent of the code under test: separations are recomputed from scratch with
arccos of dot products, the built-in table is compared with its documented properties (32 Tammes
points at 0.4 m on the upper hemisphere), and file round trips compare against the written numbers.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from datagen.errors import ViewSpaceError
from datagen.pipeline.viewspace import (
    build_view_space,
    builtin_positions,
    generate_directions,
    min_separation_degrees,
    read_view_space_file,
)
from schemas.config import ViewSpaceConfig


def brute_min_separation(positions: np.ndarray) -> float:
    """Smallest pairwise angle in degrees, by an explicit loop over pairs (no shared code)."""
    best = 180.0
    for a, b in itertools.combinations(np.asarray(positions, dtype=np.float64), 2):
        cosine = float(a @ b) / (math.sqrt(float(a @ a)) * math.sqrt(float(b @ b)))
        best = min(best, math.degrees(math.acos(max(-1.0, min(1.0, cosine)))))
    return best


# ---------------------------------------------------------------------------------------- built-in


def test_builtin_table_has_32_views_on_the_upper_hemisphere_at_0_4_m():
    space = build_view_space(ViewSpaceConfig())
    assert space.count == 32
    assert space.positions.shape == (32, 3)
    radii = np.linalg.norm(space.positions, axis=1)
    np.testing.assert_allclose(radii, 0.4, rtol=0, atol=1e-6)
    assert (space.positions[:, 2] >= 0).all()
    assert np.isfinite(space.positions).all()


def test_builtin_table_is_a_good_spread():
    positions = build_view_space(ViewSpaceConfig()).positions
    separation = brute_min_separation(positions)
    assert separation >= 26.0, separation
    # the library's fast version agrees with the brute-force one
    assert min_separation_degrees(positions) == pytest.approx(separation, abs=1e-9)
    # all 32 views are distinct
    assert len({tuple(np.round(p, 9)) for p in positions}) == 32


def test_builtin_raw_table_is_the_authors_radius():
    raw = builtin_positions()
    assert raw.shape == (32, 3)
    # the authors' file lists the positions at 0.4 m with 6 significant digits
    np.testing.assert_allclose(np.linalg.norm(raw, axis=1), 0.4, atol=1e-5)


def test_radius_scales_the_builtin_table():
    base = build_view_space(ViewSpaceConfig()).positions
    scaled = build_view_space(ViewSpaceConfig(radius=0.7)).positions
    np.testing.assert_allclose(np.linalg.norm(scaled, axis=1), 0.7, atol=1e-12)
    np.testing.assert_allclose(scaled / 0.7, base / 0.4, atol=1e-12)


# --------------------------------------------------------------------------------------- generator


def test_generator_reaches_25_degrees_for_32_views():
    directions = generate_directions(32, seed=0)
    assert directions.shape == (32, 3)
    assert brute_min_separation(directions) >= 25.0


def test_generator_is_deterministic_for_a_seed():
    first = generate_directions(32, seed=7)
    second = generate_directions(32, seed=7)
    np.testing.assert_array_equal(first, second)


def test_generator_differs_across_seeds():
    a = generate_directions(32, seed=1)
    b = generate_directions(32, seed=2)
    assert not np.allclose(a, b, atol=1e-6)
    # also as sets of directions (not just a permutation of the same spread)
    nearest = np.arccos(np.clip(a @ b.T, -1.0, 1.0)).min(axis=1)
    assert np.degrees(nearest).max() > 1.0


# Lower bounds on the minimum separation: a good hemisphere spread gets about 62, 40, 19.6 degrees.
@pytest.mark.parametrize(("count", "floor_degrees"), [(8, 50.0), (16, 35.0), (64, 17.0)])
def test_generated_view_space_for_other_counts(count, floor_degrees):
    config = ViewSpaceConfig(source="generated", count=count, radius=0.4, generator_seed=3)
    space = build_view_space(config)
    assert space.count == count
    np.testing.assert_allclose(np.linalg.norm(space.positions, axis=1), 0.4, atol=1e-12)
    assert (space.positions[:, 2] >= 0).all()
    separation = brute_min_separation(space.positions)
    assert separation >= floor_degrees
    assert space.min_separation_degrees() == pytest.approx(separation, abs=1e-9)
    # the generated space is the unit spread scaled
    np.testing.assert_allclose(space.positions, generate_directions(count, 3) * 0.4, atol=1e-15)


def test_generator_refuses_out_of_range_counts():
    with pytest.raises(ViewSpaceError, match="outside the allowed range"):
        generate_directions(0, 0)
    with pytest.raises(ViewSpaceError, match="outside the allowed range"):
        generate_directions(65, 0)


def test_min_separation_of_known_configurations():
    # the octahedron's upper vertices: 90 degrees apart
    square = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, 1]], dtype=float)
    assert min_separation_degrees(square) == pytest.approx(90.0)
    assert min_separation_degrees(square * 3.0) == pytest.approx(90.0)
    assert min_separation_degrees(np.array([[0.0, 0.0, 1.0]])) == 180.0
    tilted = np.array([[0.0, 0.0, 1.0], [math.sin(0.1), 0.0, math.cos(0.1)]])
    assert min_separation_degrees(tilted) == pytest.approx(math.degrees(0.1), abs=1e-9)


# ------------------------------------------------------------------------------------------- files


def write_view_file(path: Path, positions: np.ndarray) -> Path:
    lines = [str(len(positions))] + [" ".join(repr(float(v)) for v in row) for row in positions]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("count", [1, 5, 12, 64])
def test_view_space_file_round_trip(tmp_path, count):
    rng = np.random.default_rng(count)
    raw = rng.normal(size=(count, 3))
    raw[:, 2] = np.abs(raw[:, 2])
    raw *= rng.uniform(0.5, 3.0, size=(count, 1))  # any length: positions are rescaled to the radius
    path = write_view_file(tmp_path / "views.txt", raw)

    np.testing.assert_array_equal(read_view_space_file(path), raw)
    space = build_view_space(ViewSpaceConfig(source=str(path), count=count, radius=0.4))
    assert space.count == count
    expected = raw / np.linalg.norm(raw, axis=1, keepdims=True) * 0.4
    np.testing.assert_allclose(space.positions, expected, rtol=0, atol=1e-15)


def test_view_space_file_of_the_builtin_table_matches_the_builtin(tmp_path):
    path = write_view_file(tmp_path / "views32.txt", builtin_positions())
    from_file = build_view_space(ViewSpaceConfig(source=str(path), count=32))
    builtin = build_view_space(ViewSpaceConfig())
    np.testing.assert_array_equal(from_file.positions, builtin.positions)


def test_view_space_file_tolerates_blank_lines_and_extra_spaces(tmp_path):
    path = tmp_path / "views.txt"
    path.write_text("\n 2 \n\n0 0 1\n\n  1.0   0.0\t0.0  \n\n", encoding="utf-8")
    np.testing.assert_array_equal(read_view_space_file(path), [[0, 0, 1], [1, 0, 0]])


def test_view_space_file_count_must_match_config(tmp_path):
    path = write_view_file(tmp_path / "views.txt", np.eye(3))
    with pytest.raises(ViewSpaceError, match=r"holds 3 views but view_space.count = 4"):
        build_view_space(ViewSpaceConfig(source=str(path), count=4))


MALFORMED = {
    "empty": ("", "first line must be the view count"),
    "blank": ("\n  \n\n", "first line must be the view count"),
    "count not integer": ("2.0\n0 0 1\n1 0 0\n", "first line must be the view count"),
    "count with coordinates": ("0 0 1\n1 0 0\n", "first line must be the view count"),
    "negative count": ("-1\n0 0 1\n", "first line must be the view count"),
    "zero count": ("0\n", "outside the allowed range 1..64"),
    "count above 64": ("65\n" + "0 0 1\n" * 65, "outside the allowed range 1..64"),
    "too few rows": ("3\n0 0 1\n1 0 0\n", "says 3 views but 2 follow"),
    "too many rows": ("1\n0 0 1\n1 0 0\n", "says 1 views but 2 follow"),
    "two numbers": ("2\n0 0\n1 0\n", "three"),
    "four numbers": ("2\n0 0 1 1\n1 0 0 1\n", "three"),
    "ragged rows": ("2\n0 0 1\n1 0\n", "three numbers"),
    "not a number": ("2\n0 0 1\n1 zero 0\n", "three numbers"),
    "nan": ("2\n0 0 1\nnan 0 1\n", "finite"),
    "infinite": ("2\n0 0 1\n1 inf 0\n", "finite"),
    "view at origin": ("2\n0 0 1\n0 0 0\n", "at the origin"),
    "below the hemisphere": ("2\n0 0 1\n1 0 -0.1\n", "upper hemisphere"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_view_space_files_raise_a_clear_error(tmp_path, case):
    text, message = MALFORMED[case]
    path = tmp_path / "bad.txt"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ViewSpaceError) as info:
        read_view_space_file(path)
    assert message in str(info.value)
    # the message names the file, so a user knows which one to fix
    assert str(path) in str(info.value)
    with pytest.raises(ViewSpaceError):
        build_view_space(ViewSpaceConfig(source=str(path), count=2))


def test_missing_view_space_file_names_the_path(tmp_path):
    path = tmp_path / "nowhere" / "views.txt"
    with pytest.raises(ViewSpaceError) as info:
        build_view_space(ViewSpaceConfig(source=str(path), count=2))
    assert str(path) in str(info.value)
    assert "cannot read" in str(info.value)
