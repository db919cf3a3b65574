"""Object preparation (docs/pipeline.md section 1): bad input gives one-line ObjectErrors naming the file and
the fix; good input is loaded, converted to metres, turned z-up, centred and sized
(datagen/pipeline/objects/prepare.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from datagen.errors import ObjectError
from datagen.pipeline.camera import max_fitting_radius
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import PreparedObject, prepare_object, yaw
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec, builtin_object_id
from datagen.shapes import builtins
from schemas.config import GenerationConfig

CONFIG = GenerationConfig()
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def obj_text(vertices: np.ndarray, faces: np.ndarray) -> str:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, dtype=float).tolist()]
    triangles = np.asarray(faces, dtype=int).reshape(-1, 3).tolist()
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in triangles]
    return "\n".join(lines) + "\n"


def box_mesh(low, high) -> trimesh.Trimesh:
    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    box = trimesh.creation.box(extents=high - low)
    box.apply_translation((low + high) / 2.0)
    return box


def write_obj(folder: Path, name: str, mesh: trimesh.Trimesh) -> Path:
    path = folder / name
    path.write_text(obj_text(mesh.vertices, mesh.faces))
    return path


def spec_for(path: Path, options: str = "") -> ObjectSpec:
    """Resolve ``path`` through a real objects file, as a job does."""
    listing_path = path.parent / f"{path.name}.objects.txt"
    listing_path.write_text(f'"{path.name}" {options}\n')
    listing = read_objects_file(listing_path)
    assert listing.errors == [], listing.errors
    (spec,) = listing.objects
    return spec


def prepare(path: Path, options: str = "", config: GenerationConfig = CONFIG) -> PreparedObject:
    return prepare_object(spec_for(path, options), config)


def object_error(spec: ObjectSpec, config: GenerationConfig = CONFIG) -> str:
    with pytest.raises(ObjectError) as info:
        prepare_object(spec, config)
    message = str(info.value)
    assert "\n" not in message, message
    return message


def extents(prepared: PreparedObject) -> np.ndarray:
    return prepared.vertices.max(axis=0) - prepared.vertices.min(axis=0)


# ---------------------------------------------------------------------------------------------------------
# Bad input: one line, naming the file, saying what to do
# ---------------------------------------------------------------------------------------------------------


def test_missing_file_deleted_after_listing(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "gone.obj", box_mesh([0, 0, 0], [0.1, 0.1, 0.1]))
    spec = spec_for(path)
    path.unlink()
    message = object_error(spec)
    assert message.startswith(f"{path.resolve()}: ")
    assert "not found" in message
    assert "fix the path in the objects file" in message
    assert spec.origin in message  # FILE:LINE of the listing


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".off", ".glb"])
@pytest.mark.parametrize("size", [16, 84, 3000])
def test_random_bytes_are_not_a_mesh(tmp_path: Path, suffix: str, size: int) -> None:
    path = tmp_path / f"noise{suffix}"
    path.write_bytes(np.random.default_rng(size).bytes(size))
    message = object_error(spec_for(path))
    assert message.startswith(f"{path.resolve()}: ")
    # either the loader fails (then the formats it takes are named) or it reads nothing (then: export faces)
    assert "give an OBJ, PLY, STL, OFF or GLB file with faces" in message or "has no faces" in message


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".off"])
def test_text_garbage_is_not_a_mesh(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"notes{suffix}"
    path.write_text("shopping list:\n  milk 2\n  eggs 12 0 1\nend\n")
    message = object_error(spec_for(path))
    assert message.startswith(f"{path.resolve()}: ")
    assert ("not a readable mesh" in message and "give an OBJ" in message) or (
        "no faces" in message and "export the surface with its triangles" in message
    )


def test_unknown_format_names_the_accepted_ones(tmp_path: Path) -> None:
    path = tmp_path / "mesh.unknownformat"
    path.write_text(obj_text(*[np.eye(3), [[0, 1, 2]]]))
    message = object_error(spec_for(path))
    assert message.startswith(f"{path.resolve()}: not a readable mesh")
    assert "OBJ, PLY, STL, OFF or GLB" in message


def test_faces_pointing_past_the_vertices(tmp_path: Path) -> None:
    path = tmp_path / "broken.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    message = object_error(spec_for(path))
    assert message.startswith(f"{path.resolve()}: not a readable mesh")


def test_ply_point_cloud_has_no_faces(tmp_path: Path) -> None:
    path = tmp_path / "points.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n0 0 0\n0.1 0 0\n0 0.1 0\n0 0 0.1\n"
    )
    assert isinstance(trimesh.load(str(path)), trimesh.PointCloud)  # the loader does read it
    message = object_error(spec_for(path))
    assert message.startswith(f"{path.resolve()}: ")
    assert "no faces" in message or "no triangle faces" in message
    assert "export the surface" in message or "surface mesh" in message


@pytest.mark.parametrize(
    "text",
    ["", "# an OBJ with nothing in it\n", "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\n"],
    ids=["empty", "comment", "no-faces"],
)
def test_empty_mesh(tmp_path: Path, text: str) -> None:
    path = tmp_path / "empty.obj"
    path.write_text(text)
    message = object_error(spec_for(path))
    assert message == f"{path.resolve()}: the mesh has no faces; export the surface with its triangles"


@pytest.mark.parametrize(
    "text",
    [
        "v 0 0 0\nv 0.05 0 0\nv 0.1 0 0\nv 0.1 0.1 0.1\nf 1 2 3\nf 1 3 2\nf 2 3 1\n",  # collinear
        "v 0 0 0\nv 0.1 0 0\nv 0.2 0 0\nv 0.3 0 0\nf 1 2 3\nf 2 3 4\nf 1 1 4\n",  # collinear, repeated index
        "v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n",  # one point
    ],
    ids=["collinear", "line", "point"],
)
def test_zero_area_mesh(tmp_path: Path, text: str) -> None:
    path = tmp_path / "flat.obj"
    path.write_text(text)
    message = object_error(spec_for(path))
    assert message.startswith(f"{path.resolve()}: ")
    assert "zero surface area" in message
    assert "cannot be imaged" in message


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_non_finite_vertices(tmp_path: Path, bad: str) -> None:
    path = tmp_path / "nan.obj"
    path.write_text(f"v {bad} 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    message = object_error(spec_for(path))
    assert message == (f"{path.resolve()}: the mesh has NaN or infinite vertex coordinates; repair or re-export it")


def test_size_that_cannot_fit_the_image(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "cube.obj", box_mesh([0, 0, 0], [0.1, 0.1, 0.1]))
    message = object_error(spec_for(path, "size=0.5"))
    assert message.startswith(f"{path.resolve()}: size 0.5 m does not fit the image")
    advice = float(message.rsplit("use size <= ", 1)[1])
    # the advice is right: that size fits, a little more does not
    limit = max_fitting_radius(CONFIG.camera, CONFIG.view_space.radius)
    assert advice * math.sqrt(3) / 2 <= limit < (advice + 0.001) * math.sqrt(3) / 2
    assert prepare(path, f"size={advice}").size == advice
    object_error(spec_for(path, f"size={advice + 0.002}"))


def test_fit_limit_follows_the_view_radius(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "cube.obj", box_mesh([0, 0, 0], [0.1, 0.1, 0.1]))
    near = CONFIG.model_copy(update={"view_space": CONFIG.view_space.model_copy(update={"radius": 0.2})})
    assert prepare(path, "size=0.15").size == 0.15
    assert "does not fit the image" in object_error(spec_for(path, "size=0.15"), near)


def test_a_bad_object_does_not_break_the_next(tmp_path: Path) -> None:
    good = write_obj(tmp_path, "good.obj", box_mesh([0, 0, 0], [0.1, 0.1, 0.1]))
    bad = tmp_path / "bad.obj"
    bad.write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    listing_path = tmp_path / "objects.txt"
    listing_path.write_text("bad.obj\ngood.obj\n")
    results = []
    for spec in read_objects_file(listing_path).objects:
        try:
            results.append(prepare_object(spec, CONFIG).spec.name)
        except ObjectError as exc:
            results.append(type(exc).__name__)
    assert results == ["ObjectError", "good"]
    assert good.exists()


# ---------------------------------------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------------------------------------


def test_units_auto_detects_millimetres(tmp_path: Path) -> None:
    # a 100 x 60 x 40 mm part, in the range after x 0.001, so no size scaling on top
    path = write_obj(tmp_path, "part.obj", box_mesh([0, 0, 0], [100, 60, 40]))
    prepared = prepare(path)
    assert prepared.units_guessed == "mm"
    assert prepared.scale == pytest.approx(0.001)
    assert prepared.size == pytest.approx(0.1)
    np.testing.assert_allclose(extents(prepared), [0.1, 0.06, 0.04], atol=1e-12)


def test_units_auto_mm_then_clamped_into_the_size_range(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "big.obj", box_mesh([0, 0, 0], [400, 100, 100]))  # 0.4 m after mm
    prepared = prepare(path)
    assert prepared.units_guessed == "mm"
    assert prepared.size == pytest.approx(0.15)
    assert prepared.scale == pytest.approx(0.001 * 0.15 / 0.4)


@pytest.mark.parametrize(
    ("low", "high", "units"),
    [
        ([0, 0, 0], [9.99, 1, 1], "m"),  # every |coordinate| < 10: metres
        ([0, 0, 0], [10.0, 1, 1], "mm"),  # the threshold itself counts
        ([-10.0, 0, 0], [-9.9, 0.05, 0.05], "mm"),  # |coordinate|, not the coordinate
        ([20, 20, 20], [20.1, 20.05, 20.05], "mm"),  # far from the origin: position, not size
        ([-0.05, -0.05, -0.05], [0.05, 0.05, 0.05], "m"),
    ],
)
def test_units_auto_threshold(tmp_path: Path, low, high, units: str) -> None:
    path = write_obj(tmp_path, "m.obj", box_mesh(low, high))
    assert prepare(path).units_guessed == units


def test_units_threshold_is_a_config_value(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "m.obj", box_mesh([0, 0, 0], [50, 1, 1]))
    assert prepare(path).units_guessed == "mm"
    assert prepare(path, config=CONFIG.model_copy(update={"mm_threshold": 100.0})).units_guessed == "m"


def test_units_m_overrides_auto(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "part.obj", box_mesh([0, 0, 0], [100, 60, 40]))
    prepared = prepare(path, "units=m")
    assert prepared.units_guessed == "m"
    assert prepared.size == pytest.approx(0.15)  # 100 m, clamped
    assert prepared.scale == pytest.approx(0.0015)


def test_units_mm_overrides_auto(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "small.obj", box_mesh([0, 0, 0], [0.08, 0.04, 0.02]))
    assert prepare(path).units_guessed == "m"
    assert prepare(path).scale == pytest.approx(1.0)
    prepared = prepare(path, "units=mm")
    assert prepared.units_guessed == "mm"
    assert prepared.size == pytest.approx(0.05)  # 0.08 mm, clamped up
    assert prepared.scale == pytest.approx(0.05 / 0.08)


# ---------------------------------------------------------------------------------------------------------
# Up axis: up=y is a rotation by +90 degrees about x, never a mirroring swap
# ---------------------------------------------------------------------------------------------------------

R_X_90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def tall_y_with_marker() -> trimesh.Trimesh:
    """A box tall along y, and a small marker triangle inside its +x +y +z corner."""
    body = box_mesh([0, 0, 0], [0.04, 0.12, 0.06])
    marker = trimesh.Trimesh(
        vertices=[[0.035, 0.115, 0.055], [0.039, 0.115, 0.055], [0.035, 0.119, 0.055]], faces=[[0, 1, 2]]
    )
    return trimesh.util.concatenate([body, marker])


def test_up_y_makes_y_tall_mesh_z_tall(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "tall.obj", tall_y_with_marker())
    as_is = prepare(path)
    np.testing.assert_allclose(extents(as_is), [0.04, 0.12, 0.06], atol=1e-12)
    turned = prepare(path, "up=y")
    np.testing.assert_allclose(extents(turned), [0.04, 0.06, 0.12], atol=1e-12)


def test_up_y_is_a_proper_rotation(tmp_path: Path) -> None:
    mesh = tall_y_with_marker()
    path = write_obj(tmp_path, "tall.obj", mesh)
    prepared = prepare(path, "up=y")
    # fit the linear map from the (centred) file vertices to the prepared ones
    source = np.asarray(mesh.vertices)
    assert len(prepared.vertices) == len(source)  # nothing merged in this mesh, order kept
    centred = source - (source.min(axis=0) + source.max(axis=0)) / 2
    transform, *_ = np.linalg.lstsq(centred, prepared.vertices, rcond=None)
    linear = transform.T / prepared.scale
    np.testing.assert_allclose(linear, R_X_90, atol=1e-9)
    assert np.linalg.det(linear) == pytest.approx(1.0)


def test_up_y_keeps_handedness_of_a_marker(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "tall.obj", tall_y_with_marker())
    prepared = prepare(path, "up=y")
    marker = prepared.vertices[-3:].mean(axis=0)
    # file +x +y(up) +z corner -> +x, +z(up), and file +z goes to -y; a y/z swap would give +y
    assert marker[0] > 0.015
    assert marker[2] > 0.05
    assert marker[1] < -0.02
    # the triangle's winding is kept too: its normal turns with the mesh (+z -> -y), not mirrored
    a, b, c = prepared.vertices[-3:]
    normal = np.cross(b - a, c - a)
    assert normal[1] < 0 and abs(normal[0]) < 1e-12 and abs(normal[2]) < 1e-12


def test_up_z_leaves_axes_alone(tmp_path: Path) -> None:
    mesh = tall_y_with_marker()
    path = write_obj(tmp_path, "tall.obj", mesh)
    a, b = prepare(path), prepare(path, "up=z")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    source = np.asarray(mesh.vertices)
    expected = (source - (source.min(axis=0) + source.max(axis=0)) / 2) * a.scale
    np.testing.assert_allclose(a.vertices, expected, atol=1e-12)


# ---------------------------------------------------------------------------------------------------------
# Frame and size
# ---------------------------------------------------------------------------------------------------------


def test_bounding_box_is_centred_at_the_origin(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "off.obj", box_mesh([3.0, -2.0, 5.0], [3.1, -1.95, 5.02]))
    prepared = prepare(path)
    low, high = prepared.vertices.min(axis=0), prepared.vertices.max(axis=0)
    np.testing.assert_allclose((low + high) / 2, 0.0, atol=1e-15)
    np.testing.assert_allclose(high - low, [0.1, 0.05, 0.02], atol=1e-12)
    assert prepared.bounding_radius == pytest.approx(math.sqrt(0.05**2 + 0.025**2 + 0.01**2))


@pytest.mark.parametrize(
    ("extent", "expected"),
    [(0.3, 0.15), (2.0, 0.15), (0.02, 0.05), (0.001, 0.05), (0.05, 0.05), (0.15, 0.15), (0.1, 0.1)],
)
def test_size_is_clamped_into_the_range(tmp_path: Path, extent: float, expected: float) -> None:
    path = write_obj(tmp_path, "box.obj", box_mesh([0, 0, 0], [extent, extent / 2, extent / 3]))
    prepared = prepare(path)
    assert prepared.size == pytest.approx(expected)
    assert extents(prepared).max() == pytest.approx(expected, rel=1e-12)
    assert prepared.scale == pytest.approx(expected / extent)
    # uniform scaling: the proportions are kept
    np.testing.assert_allclose(extents(prepared) / extents(prepared).max(), [1, 1 / 2, 1 / 3], rtol=1e-12)


def test_size_range_is_a_config_value(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "box.obj", box_mesh([0, 0, 0], [0.3, 0.1, 0.1]))
    config = CONFIG.model_copy(update={"size_range": (0.06, 0.08)})
    assert prepare(path, config=config).size == pytest.approx(0.08)


@pytest.mark.parametrize("size", [0.07, 0.03, 0.2])
def test_size_option_sets_the_largest_extent_exactly(tmp_path: Path, size: float) -> None:
    path = write_obj(tmp_path, "box.obj", box_mesh([0, 0, 0], [0.3, 0.2, 0.1]))
    prepared = prepare(path, f"size={size}")  # even outside size_range
    assert prepared.size == size
    assert extents(prepared).max() == pytest.approx(size, rel=1e-12)
    assert prepared.scale == pytest.approx(size / 0.3)


def test_size_option_applies_after_units(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "part.obj", box_mesh([0, 0, 0], [100, 60, 40]))
    prepared = prepare(path, "size=0.12")
    assert prepared.units_guessed == "mm"
    assert prepared.scale == pytest.approx(0.0012)
    np.testing.assert_allclose(extents(prepared), [0.12, 0.072, 0.048], rtol=1e-12)


def test_yaw_keeps_the_bounding_radius(tmp_path: Path) -> None:
    path = write_obj(tmp_path, "box.obj", box_mesh([0, 0, 0], [0.12, 0.05, 0.03]))
    prepared = prepare(path)
    for rotation in range(CONFIG.rotations):
        turned = prepared.task_vertices(rotation, CONFIG.rotations)
        assert np.sqrt((turned**2).sum(axis=1)).max() == pytest.approx(prepared.bounding_radius)
        np.testing.assert_array_equal(turned[:, 2], prepared.vertices[:, 2])
    np.testing.assert_allclose(yaw(np.array([[1.0, 0.0, 0.5]]), math.pi / 2), [[0.0, 1.0, 0.5]], atol=1e-15)


# ---------------------------------------------------------------------------------------------------------
# Watertightness, merging, built-ins and real meshes
# ---------------------------------------------------------------------------------------------------------


def test_watertight_closed_box(tmp_path: Path) -> None:
    assert prepare(write_obj(tmp_path, "box.obj", box_mesh([0, 0, 0], [0.1, 0.1, 0.1]))).watertight is True


def test_not_watertight_open_box(tmp_path: Path) -> None:
    box = box_mesh([0, 0, 0], [0.1, 0.1, 0.1])
    open_box = trimesh.Trimesh(vertices=box.vertices, faces=box.faces[:-2], process=False)
    assert prepare(write_obj(tmp_path, "open.obj", open_box)).watertight is False


def test_triangle_soup_is_merged_and_watertight(tmp_path: Path) -> None:
    # STL stores every triangle with its own three vertices; merging must close the box again
    box = box_mesh([0, 0, 0], [0.1, 0.08, 0.06])
    path = tmp_path / "box.stl"
    path.write_bytes(trimesh.exchange.stl.export_stl(box))
    prepared = prepare(path)
    assert prepared.watertight is True
    assert len(prepared.vertices) == 8
    assert len(prepared.faces) == 12


def test_degenerate_faces_are_dropped(tmp_path: Path) -> None:
    box = box_mesh([0, 0, 0], [0.1, 0.1, 0.1])
    faces = np.vstack([box.faces, [[0, 0, 1], [2, 2, 2]]])
    prepared = prepare(write_obj(tmp_path, "box.obj", trimesh.Trimesh(box.vertices, faces, process=False)))
    assert len(prepared.faces) == 12
    assert prepared.watertight is True


def test_objects_of_a_scene_are_merged(tmp_path: Path) -> None:
    first = box_mesh([0, 0, 0], [0.05, 0.05, 0.05])
    second = box_mesh([0.07, 0, 0], [0.1, 0.03, 0.03])
    # two named objects in one OBJ; its indices are global, so the second's faces start after 8 vertices
    text = "o first\n" + obj_text(first.vertices, first.faces)
    text += "o second\n" + obj_text(second.vertices, second.faces + len(first.vertices))
    path = tmp_path / "two.obj"
    path.write_text(text)
    prepared = prepare(path)
    assert len(prepared.faces) == 24
    np.testing.assert_allclose(extents(prepared), [0.1, 0.05, 0.05], atol=1e-12)


def test_builtin_prepares_watertight_in_range() -> None:
    name = "capsule"
    identity = builtins.builtin_generator_identity(name)
    spec = ObjectSpec(
        source=f"builtin:{name}",
        name=name,
        options=ObjectOptions(),
        object_id=builtin_object_id(identity, ObjectOptions()),
        generator=identity,
    )
    prepared = prepare_object(spec, CONFIG)
    assert prepared.watertight is True
    assert prepared.units_guessed == "m"
    assert CONFIG.size_range[0] <= prepared.size <= CONFIG.size_range[1]
    centre = (prepared.vertices.min(axis=0) + prepared.vertices.max(axis=0)) / 2
    np.testing.assert_allclose(centre, 0, atol=1e-15)


def test_example_objects_file_prepares(shared_meshes: list[Path]) -> None:
    assert (EXAMPLES / "../../shared/meshes").resolve() == shared_meshes[0].parent.resolve()
    listing = read_objects_file(EXAMPLES / "shared-meshes.txt")
    prepared = {spec.name: prepare_object(spec, CONFIG) for spec in listing.objects}
    assert prepared["cow"].watertight is True
    assert prepared["teapot"].watertight is False  # open lid seams (SOURCES.md)
    fandisk = prepared["fandisk"]
    assert fandisk.units_guessed == "m" and fandisk.size == 0.12
    for item in prepared.values():
        assert extents(item).max() == pytest.approx(item.size, rel=1e-9)
        assert 0.05 <= item.size <= 0.15
    # the y-up cow stands: its height (file y) is now z, its width (file z, +-1.7) now y
    cow = extents(prepared["cow"])
    assert cow[2] > cow[1]
