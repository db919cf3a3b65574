"""Seeded shape variants (datagen/pipeline/objects/variants.py), their preparation, and the
``datagen objects variants`` command (datagen/cli/inputs.py) that lists them: a variant is a smooth,
orientation-preserving deformation that keeps a watertight mesh watertight, is a pure function of its
seed and object, still fits the image, and its listing round-trips through `read_objects_file`."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
import typer
from typer.testing import CliRunner

from datagen.cli import common
from datagen.pipeline.camera import max_fitting_radius
from datagen.pipeline.objects import variants
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import PreparedObject, prepare_object
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec, builtin_object_id, file_object_id
from datagen.pipeline.objects.variants import (
    VariantParameters,
    deform,
    describe_variant,
    draw_parameters,
    draw_variant_seeds,
    subdivide_for_bending,
)
from datagen.shapes import builtins
from schemas.config import GenerationConfig

CONFIG = GenerationConfig()
TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
EXTREME = VariantParameters(seed=0, scale=(1.4 / 0.98, 0.7 / 0.98, 0.98), twist=-40.0, bend=30.0, azimuth=30.0)
"""The strongest deformation the ranges allow: 2:1 proportions, full twist, full bend."""


def builtin_spec(name: str, variant: int | None = None) -> ObjectSpec:
    identity = builtins.builtin_generator_identity(name)
    options = ObjectOptions(variant=variant)
    return ObjectSpec(
        source=f"builtin:{name}",
        name=name,
        options=options,
        object_id=builtin_object_id(identity, options),
        generator=identity,
    )


def cube_spec(folder: Path, variant: int | None) -> ObjectSpec:
    """A 12-face cube, resolved through an objects file as a job does."""
    (folder / "cube.obj").write_bytes(trimesh.exchange.obj.export_obj(trimesh.creation.box()).encode())
    (folder / "cube.txt").write_text("cube.obj" + ("" if variant is None else f" variant={variant}") + "\n")
    (spec,) = read_objects_file(folder / "cube.txt").objects
    return spec


def as_mesh(prepared: PreparedObject) -> trimesh.Trimesh:
    return trimesh.Trimesh(vertices=prepared.vertices, faces=prepared.faces, process=False)


def centred_box_points(extents: np.ndarray, count: int = 9) -> np.ndarray:
    axes = [np.linspace(-e / 2, e / 2, count) for e in extents]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def jacobians(points: np.ndarray, parameters: VariantParameters, extents: np.ndarray) -> np.ndarray:
    """Central differences of `deform` at each point, (n, 3, 3) with [i, :, k] = d deform / d x_k."""
    step = 1e-6 * float(extents.max())
    columns = []
    for axis in range(3):
        offset = np.zeros(3)
        offset[axis] = step
        columns.append(deform(points + offset, parameters, extents) - deform(points - offset, parameters, extents))
    return np.stack(columns, axis=2) / (2 * step)


# ---------------------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------------------


def test_parameters_stay_in_their_documented_ranges() -> None:
    for seed in range(200):
        p = draw_parameters(seed, f"{seed:064x}")
        scale = np.array(p.scale)
        assert math.exp(np.log(scale).mean()) == pytest.approx(1.0)  # proportions change, the volume does not
        assert scale.max() / scale.min() <= 2.0 + 1e-12
        assert 10.0 <= abs(p.twist) <= 40.0
        assert 10.0 <= p.bend <= 30.0
        assert 0.0 <= p.azimuth < 360.0


def test_parameters_and_seeds_are_pinned() -> None:
    """A variant is the same object in every release: its id, drawn parameters and listed seeds are fixed."""
    object_id = "b9b349d4d5053c55ec1fdfcdf30de635c7661b0108a6fac86f523fd3b45e08ac"
    assert file_object_id(TETRA.encode(), ObjectOptions(variant=1)) == object_id
    drawn = draw_parameters(1, object_id)
    assert drawn.scale == pytest.approx((1.1415870044573606, 0.7158017650986559, 1.2237655373014642), rel=1e-12)
    assert (drawn.twist, drawn.bend, drawn.azimuth) == pytest.approx((33.549032829, 15.982558918, 19.257474937))
    assert draw_variant_seeds(3, 9) == [103378, 560629, 747472]


def test_parameters_are_a_function_of_seed_and_object() -> None:
    spec = builtin_spec("capsule", variant=5)
    assert describe_variant(spec) == describe_variant(replace(spec, name="renamed"))
    assert describe_variant(spec) == draw_parameters(5, spec.object_id)
    assert describe_variant(builtin_spec("capsule", variant=6)) != describe_variant(spec)
    assert describe_variant(builtin_spec("cone", variant=5)) != describe_variant(spec)
    assert describe_variant(builtin_spec("capsule")) is None
    assert str(describe_variant(spec)).startswith("variant 5: scale ")


# ---------------------------------------------------------------------------------------------------------
# The deformation
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("extents", [(1.0, 1.0, 1.0), (1.0, 1.0, 0.1), (0.2, 0.2, 1.0), (1.0, 0.3, 0.6)])
def test_deformation_preserves_orientation_everywhere_in_the_box(extents: tuple[float, float, float]) -> None:
    """Positive Jacobian determinant on the whole box even at the strongest parameters: no folding."""
    box = np.array(extents)
    points = centred_box_points(box)
    determinants = np.linalg.det(jacobians(points, EXTREME, box))
    assert determinants.min() > 0.5


def test_twist_and_bend_are_what_the_docstring_says() -> None:
    """On the z axis of a unit cube: no scaling, the top turns by the twist and bends by the bend."""
    box = np.ones(3)
    twist_only = VariantParameters(seed=0, scale=(1.0, 1.0, 1.0), twist=40.0, bend=1e-9, azimuth=0.0)
    top = deform(np.array([[0.5, 0.0, 0.5], [0.5, 0.0, -0.5]]), twist_only, box)
    turns = np.degrees(np.arctan2(top[:, 1], top[:, 0]))
    assert turns[0] - turns[1] == pytest.approx(40.0)
    bend_only = VariantParameters(seed=0, scale=(1.0, 1.0, 1.0), twist=1e-9, bend=30.0, azimuth=90.0)
    axis = deform(np.array([[0.0, 0.0, -0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.5]]), bend_only, box)
    assert axis[0, 1] == pytest.approx(axis[2, 1]) and axis[0, 1] > 0.0  # both ends move toward +y
    assert axis[1] == pytest.approx([0.0, 0.0, 0.0])
    ends = jacobians(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5]]), bend_only, box)[:, :, 2]  # d/dz: tangents
    cosine = ends[0] @ ends[1] / (np.linalg.norm(ends[0]) * np.linalg.norm(ends[1]))
    assert math.degrees(math.acos(cosine)) == pytest.approx(30.0, rel=1e-4)


def test_cube_variant_is_subdivided_bent_and_still_closed(tmp_path: Path) -> None:
    plain = prepare_object(cube_spec(tmp_path, None), CONFIG)
    varied = prepare_object(cube_spec(tmp_path, 4), CONFIG)
    assert len(plain.faces) == 12
    assert len(varied.faces) > 20 * 12  # flat faces got vertices to bend with
    mesh = as_mesh(varied)
    assert mesh.is_watertight and mesh.is_winding_consistent and varied.watertight
    assert mesh.volume > 0
    # no longer a box: the vertices of the top face are no longer in one plane
    top = varied.vertices[varied.vertices[:, 2] > varied.vertices[:, 2].max() - 0.1 * varied.size]
    assert np.ptp(top[:, 2]) > 1e-3 * varied.size


def test_no_face_flips_against_the_deformation() -> None:
    """Every deformed face's normal agrees with the deformation's map of its original normal."""
    spec = builtin_spec("box_with_hole", variant=1)
    mesh = builtins.make_builtin("box_with_hole")
    vertices = mesh.vertices - (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
    vertices, faces = subdivide_for_bending(vertices, np.asarray(mesh.faces, dtype=np.int64))
    extents = np.ptp(vertices, axis=0)
    parameters = describe_variant(spec)
    assert parameters is not None
    before = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    after = trimesh.Trimesh(vertices=deform(vertices, parameters, extents), faces=faces, process=False)
    maps = jacobians(before.triangles_center, parameters, extents)
    expected = np.linalg.solve(maps.transpose(0, 2, 1), before.face_normals[:, :, None])[:, :, 0]
    assert (np.einsum("ij,ij->i", expected, after.face_normals) > 0).all()


@pytest.mark.parametrize("name", ["capsule", "box_with_hole"])
def test_variant_stays_watertight_and_is_not_a_similarity(name: str) -> None:
    plain = prepare_object(builtin_spec(name), CONFIG)
    varied = prepare_object(builtin_spec(name, variant=2), CONFIG)
    mesh = as_mesh(varied)
    assert mesh.is_watertight and varied.watertight and mesh.volume > 0
    # a similarity keeps the sorted ratios of the principal extents; the deformation changes them
    ratios = [np.sort(trimesh.bounds.oriented_bounds(as_mesh(p))[1]) for p in (plain, varied)]
    assert np.abs(ratios[0] / ratios[0].max() - ratios[1] / ratios[1].max()).max() > 0.02


def test_deformed_vertices_are_no_similarity_of_the_originals() -> None:
    """The best rotation + scale + shift onto the original vertices leaves a residual of several % of the size."""
    mesh = builtins.make_builtin("capsule")
    vertices = mesh.vertices - (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
    parameters = describe_variant(builtin_spec("capsule", variant=2))
    assert parameters is not None
    moved = deform(vertices, parameters, np.ptp(vertices, axis=0))
    a, b = vertices - vertices.mean(axis=0), moved - moved.mean(axis=0)
    u, singular, vt = np.linalg.svd(b.T @ a)
    scale = singular.sum() / (b**2).sum()
    residual = np.sqrt(((scale * b @ (u @ vt) - a) ** 2).sum(axis=1).mean())
    assert residual > 0.02 * np.ptp(vertices, axis=0).max()


def test_same_seed_same_vertices_other_seeds_differ() -> None:
    first = prepare_object(builtin_spec("capsule", variant=11), CONFIG)
    again = prepare_object(builtin_spec("capsule", variant=11), CONFIG)
    other = prepare_object(builtin_spec("capsule", variant=12), CONFIG)
    assert np.array_equal(first.vertices, again.vertices) and np.array_equal(first.faces, again.faces)
    assert first.vertices.shape == other.vertices.shape
    assert not np.allclose(first.vertices, other.vertices)


@pytest.mark.parametrize("name", builtins.builtin_names())
def test_a_variant_of_every_builtin_prepares_and_fits_the_image(name: str) -> None:
    prepared = prepare_object(builtin_spec(name, variant=1), CONFIG)  # check_fits_image runs inside
    assert prepared.bounding_radius <= max_fitting_radius(CONFIG.camera, CONFIG.view_space.radius)
    assert CONFIG.size_range[0] <= prepared.size <= CONFIG.size_range[1]
    assert np.ptp(prepared.vertices, axis=0).max() == pytest.approx(prepared.size)
    centre = (prepared.vertices.min(axis=0) + prepared.vertices.max(axis=0)) / 2
    np.testing.assert_allclose(centre, 0.0, atol=1e-12)
    assert prepared.watertight and as_mesh(prepared).is_watertight


def test_subdivision_respects_the_face_cap(monkeypatch) -> None:
    box = trimesh.creation.box()
    vertices, faces = np.asarray(box.vertices), np.asarray(box.faces, dtype=np.int64)
    monkeypatch.setattr(variants, "MAX_FACES", 600)
    _, capped = subdivide_for_bending(vertices, faces)
    assert 12 < len(capped) <= 600
    monkeypatch.setattr(variants, "MAX_FACES", 12)
    same_vertices, same_faces = subdivide_for_bending(vertices, faces)
    assert same_vertices is vertices and same_faces is faces  # a mesh already at the cap is left alone


# ---------------------------------------------------------------------------------------------------------
# datagen objects variants / show
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture
def app() -> typer.Typer:
    """The ``objects`` commands as `datagen.cli.main` registers them."""
    from datagen.cli.main import objects_app

    return objects_app


@pytest.fixture
def objects_file(tmp_path: Path) -> Path:
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "tetra.obj").write_text(TETRA)
    path = tmp_path / "lists" / "objects.txt"
    path.parent.mkdir()
    path.write_text("# mine\n../meshes/tetra.obj size=0.1\nbuiltin:capsule\n'../meshes/tetra.obj' name='my tetra'\n")
    return path


def test_variants_listing_round_trips(runner: CliRunner, app: typer.Typer, objects_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "elsewhere" / "deeper" / "variants.txt"
    result = runner.invoke(app, ["variants", str(objects_file), "--count", "3", "--seed", "9", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"wrote {out}: 3 objects, each followed by 3 variants" in result.stdout
    original, listed = read_objects_file(objects_file), read_objects_file(out)
    assert listed.errors == []
    assert len(listed.objects) == 3 * 4
    bases = listed.objects[::4]
    assert [spec.object_id for spec in bases] == [spec.object_id for spec in original.objects]
    assert [spec.name for spec in bases] == ["tetra", "capsule", "my tetra"]
    seeds = draw_variant_seeds(3, 9)
    assert seeds == sorted(seeds) and len(set(seeds)) == 3
    for index, base in enumerate(bases):
        group = listed.objects[4 * index + 1 : 4 * index + 4]
        assert [spec.options for spec in group] == [replace(base.options, variant=seed) for seed in seeds]
        assert [spec.name for spec in group] == [f"{base.name}-v{seed}" for seed in seeds]
        assert {spec.source for spec in group} == {base.source}
    assert "../../meshes/tetra.obj" in out.read_text()  # relative to the new file's folder


def test_variants_listing_is_reproducible(runner: CliRunner, app: typer.Typer, objects_file: Path) -> None:
    folder = objects_file.parent
    outputs = []
    for seed in ("4", "4", "5"):
        out = folder / "variants.txt"
        assert runner.invoke(app, ["variants", str(objects_file), "-n", "2", "-s", seed, "-o", str(out)]).exit_code == 0
        outputs.append(out.read_bytes())
    assert outputs[0] == outputs[1]
    assert outputs[0] != outputs[2]


def test_objects_show_prints_each_variants_parameters(runner: CliRunner, app: typer.Typer, tmp_path: Path) -> None:
    path = tmp_path / "objects.txt"
    path.write_text("builtin:capsule\nbuiltin:capsule variant=3\n")
    result = runner.invoke(app, ["show", str(path)])
    assert result.exit_code == 0, result.output
    spec = read_objects_file(path).objects[1]
    assert f"line 2 capsule-v3: {describe_variant(spec)}" in result.stdout
    assert "2 objects ready, 0 with errors" in result.stdout


@pytest.mark.parametrize(
    ("case", "needles"),
    [
        ("missing-file", ("nothing.txt", "not found")),
        ("count-zero", ("--count 0", "1 to 1000")),
        ("count-too-large", ("--count 1001",)),
        ("negative-seed", ("--seed -1", "non-negative")),
        ("out-is-a-folder", ("is a folder", "--out")),
        ("out-is-the-input", ("objects file being varied",)),
        ("bad-line", ("objects.txt:2", "unknown key 'colour'", "fix or delete")),
        ("already-a-variant", ("objects.txt:1", "already a variant", "base objects only")),
    ],
)
def test_variants_user_errors_are_one_line(
    runner: CliRunner, app: typer.Typer, objects_file: Path, tmp_path: Path, case: str, needles: tuple[str, ...]
) -> None:
    source, count, seed, out = objects_file, "2", "0", tmp_path / "out.txt"
    if case == "missing-file":
        source = tmp_path / "nothing.txt"
    elif case.startswith("count"):
        count = "0" if case == "count-zero" else "1001"
    elif case == "negative-seed":
        seed = "-1"
    elif case == "out-is-a-folder":
        out = tmp_path
    elif case == "out-is-the-input":
        out = objects_file
    elif case == "bad-line":
        objects_file.write_text("builtin:capsule\nbuiltin:cone colour=red\n")
    else:
        objects_file.write_text("builtin:capsule variant=2\n")
    before = objects_file.read_bytes()
    result = runner.invoke(app, ["variants", str(source), "-n", count, "-s", seed, "-o", str(out)])
    assert result.exit_code == common.EXIT_USER_ERROR, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("error: ")
    for needle in needles:
        assert needle in line, (needle, line)
    assert objects_file.read_bytes() == before
    assert not (tmp_path / "out.txt").exists()


def test_a_job_carries_the_variant_to_its_workers(tmp_path: Path) -> None:
    """The job spec a driver stores and a worker reads keeps the variant: the worker prepares the very
    variant whose object id the task bears."""
    from datagen.engine.job_plan import object_ref, object_spec
    from datagen.pipeline.objects.prepare import prepare_object
    from schemas.config import GenerationConfig
    from schemas.jobs import ObjectRef

    listing = tmp_path / "objects.txt"
    listing.write_text("builtin:capsule variant=3\n")
    (spec,) = read_objects_file(listing).objects
    ref = ObjectRef.model_validate_json(object_ref(spec).model_dump_json())
    assert ref.variant == 3
    worker_side = object_spec(ref, spec.generator)
    assert worker_side.options == spec.options and worker_side.object_id == spec.object_id
    config = GenerationConfig(refiner="none")
    assert np.array_equal(prepare_object(worker_side, config).vertices, prepare_object(spec, config).vertices)
