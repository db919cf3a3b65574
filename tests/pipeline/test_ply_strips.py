"""PLY files with triangle strips load with the same triangles, orientation included, as their
triangle-list twins; a broken strip file is one clear error line
(datagen/pipeline/objects/ply_strips.py, datagen/pipeline/objects/prepare.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from datagen.errors import ObjectError
from datagen.pipeline.objects.ply_strips import strip_triangles
from datagen.pipeline.objects.prepare import load_mesh, prepare_object
from datagen.pipeline.objects.spec import ObjectOptions, mesh_file_spec
from schemas.config import GenerationConfig

ENCODINGS = ("ascii", "binary_little_endian", "binary_big_endian")


def mesh_of(kind: str) -> trimesh.Trimesh:
    if kind == "box":
        return trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    return trimesh.creation.icosphere(subdivisions=2, radius=0.05)


def strips_of(faces: np.ndarray) -> list[list[int]]:
    """Two rows of strips for ``faces``: one long strip of face pairs (each pair a 4-index strip, joined
    by repeated indices, so the degenerate triangles between them must be dropped), and the faces left
    unpaired, one 3-index strip each, separated by -1."""
    directed = {}
    for index, face in enumerate(faces.tolist()):
        for k in range(3):
            directed[(face[k], face[(k + 1) % 3])] = index
    used: set[int] = set()
    pairs: list[list[int]] = []
    singles: list[int] = []
    for index, face in enumerate(faces.tolist()):
        if index in used:
            continue
        used.add(index)
        for k in range(3):
            a, b, c = face[k], face[(k + 1) % 3], face[(k + 2) % 3]
            other = directed.get((c, b))
            if other is not None and other not in used:
                (d,) = set(faces[other].tolist()) - {b, c}
                used.add(other)
                pairs.append([a, b, c, d])  # triangles (a, b, c) and, odd, (c, b, d)
                break
        else:
            singles += [*face, -1]
    long_strip = pairs[0]
    for strip in pairs[1:]:
        long_strip = [*long_strip, long_strip[-1], strip[0], *strip]
    return [long_strip, singles[:-1]] if singles else [long_strip]


def write_strip_ply(path: Path, vertices: np.ndarray, rows: list[list[int]], encoding: str) -> None:
    header = (
        f"ply\nformat {encoding} 1.0\ncomment triangle strips, -1 between strips\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element tristrips {len(rows)}\nproperty list int int vertex_indices\nend_header\n"
    )
    if encoding == "ascii":
        body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in vertices.astype(np.float32).tolist())
        body += "".join(f"{len(row)} {' '.join(map(str, row))}\n" for row in rows)
        path.write_text(header + body)
        return
    order = "<" if encoding == "binary_little_endian" else ">"
    data = vertices.astype(f"{order}f4").tobytes()
    for row in rows:
        data += np.array([len(row), *row], dtype=f"{order}i4").tobytes()
    path.write_bytes(header.encode() + data)


def canonical(faces: np.ndarray) -> np.ndarray:
    """Each triangle rotated to start at its smallest index (orientation kept), rows sorted."""
    faces = np.asarray(faces, dtype=np.int64)
    shift = faces.argmin(axis=1)
    rotated = np.stack([faces[np.arange(len(faces)), (shift + k) % 3] for k in range(3)], axis=1)
    return rotated[np.lexsort(rotated.T[::-1])]


def normals_by_triangle(mesh: trimesh.Trimesh) -> np.ndarray:
    """Face normals in the order of `canonical` triangles."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    shift = faces.argmin(axis=1)
    rotated = np.stack([faces[np.arange(len(faces)), (shift + k) % 3] for k in range(3)], axis=1)
    return np.asarray(mesh.face_normals)[np.lexsort(rotated.T[::-1])]


def test_strip_triangles_alternate_winding_and_drop_degenerates() -> None:
    strips = np.array([0, 1, 2, 3, 4, -1, 5, 6, 7, 7, -1, 8, 9])
    assert strip_triangles(strips).tolist() == [[0, 1, 2], [2, 1, 3], [2, 3, 4], [5, 6, 7]]


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("kind", ["box", "icosphere"])
def test_strip_ply_loads_the_faces_of_its_triangle_list_twin(tmp_path: Path, kind: str, encoding: str) -> None:
    mesh = mesh_of(kind)
    listed = tmp_path / "list.ply"
    listed.write_bytes(mesh.export(file_type="ply", encoding="ascii" if encoding == "ascii" else "binary"))
    stripped = tmp_path / "strips.ply"
    rows = strips_of(np.asarray(mesh.faces))
    write_strip_ply(stripped, np.asarray(mesh.vertices), rows, encoding)
    assert len(rows[0]) > 4  # a real strip, with degenerate joins

    options = ObjectOptions()
    twin = load_mesh(mesh_file_spec(listed, options))
    loaded = load_mesh(mesh_file_spec(stripped, options))
    assert len(twin.faces) == len(mesh.faces)
    assert np.array_equal(canonical(loaded.faces), canonical(twin.faces))
    assert np.allclose(loaded.vertices, twin.vertices, atol=1e-6)
    assert loaded.volume == pytest.approx(twin.volume, rel=1e-6)
    assert loaded.volume > 0  # outward orientation kept
    assert np.allclose(normals_by_triangle(loaded), normals_by_triangle(twin), atol=1e-6)

    config = GenerationConfig()
    a, b = (
        prepare_object(mesh_file_spec(stripped, options), config),
        prepare_object(mesh_file_spec(listed, options), config),
    )
    assert a.watertight and b.watertight
    assert np.array_equal(canonical(a.faces), canonical(b.faces))


def test_strip_ply_beside_a_face_element_keeps_both(tmp_path: Path) -> None:
    path = tmp_path / "mixed.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\n"
        "element tristrips 1\nproperty list int int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 1 2 3\n9 0 2 1 -1 0 1 3 -1 -1\n"
    )
    loaded = load_mesh(mesh_file_spec(path, ObjectOptions()))
    assert canonical(loaded.faces).tolist() == [[0, 1, 3], [0, 2, 1], [1, 2, 3]]


@pytest.mark.parametrize(
    ("case", "needle"),
    [
        ("index-out-of-range", "vertex index 9 is outside 0..3"),
        ("truncated-binary", "the file ends inside element 'tristrips'"),
        ("not-a-number", "not a number"),
        ("bad-format", "format 'binary_middle_endian'"),
    ],
)
def test_a_malformed_strip_ply_is_one_clear_error(tmp_path: Path, case: str, needle: str) -> None:
    path = tmp_path / f"{case}.ply"
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    if case == "truncated-binary":
        write_strip_ply(path, vertices, [[0, 2, 1, 3]], "binary_little_endian")
        path.write_bytes(path.read_bytes()[:-4])
    elif case == "bad-format":
        write_strip_ply(path, vertices, [[0, 2, 1, 3]], "ascii")
        path.write_text(path.read_text().replace("format ascii", "format binary_middle_endian"))
    else:
        write_strip_ply(path, vertices, [[0, 2, 1, 9 if case == "index-out-of-range" else 3]], "ascii")
        if case == "not-a-number":
            path.write_text(path.read_text().replace("4 0 2 1 3", "4 0 2 x 3"))
    with pytest.raises(ObjectError) as caught:
        load_mesh(mesh_file_spec(path, ObjectOptions()))
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: malformed triangle-strip PLY (")
    assert needle in message
    assert "re-export" in message
