"""Objects files of many lines (benchmarks/scale measures 1k-50k): the meshes are hashed a block at
a time and lines are split without shlex where they can be, with the very results of reading each
whole file: the same object ids, names, errors and order, and the job planned from them in file
order, its tasks made on demand."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from datagen.engine.job_plan import plan_job
from datagen.pipeline.objects import objects_file
from datagen.pipeline.objects.objects_file import ObjectLineError, read_objects_file
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec, file_object_id, mesh_file_spec
from schemas.config import GenerationConfig

TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


@pytest.fixture
def listing(tmp_path: Path) -> Path:
    """300 distinct meshes, with a missing file, a folder and a quoted path among them."""
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    lines = []
    for index in range(300):
        (meshes / f"m{index:03d}.obj").write_text(f"# mesh {index}\n{TETRA}")
        lines.append(f"meshes/m{index:03d}.obj" + (" size=0.1" if index % 3 == 0 else ""))
    (meshes / "with space.obj").write_text("# spaced\n" + TETRA)
    lines[10] = "meshes/missing.obj"
    lines[20] = "meshes"
    lines[30] = "'meshes/with space.obj' name=spaced # a comment"
    path = tmp_path / "objects.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_each_line_resolves_as_when_read_whole_and_in_turn(listing: Path) -> None:
    entries = read_objects_file(listing).entries
    assert len(entries) == 300 and [e.line for e in entries] == list(range(1, 301))
    for entry in entries:
        if entry.line in (11, 21):
            assert isinstance(entry, ObjectLineError)
            continue
        assert isinstance(entry, ObjectSpec)
        path = Path(entry.source)
        assert entry.object_id == file_object_id(path.read_bytes(), entry.options)
        assert entry.origin == f"{listing}:{entry.line}"
    missing, folder = entries[10], entries[20]
    assert isinstance(missing, ObjectLineError) and missing.message.startswith("mesh file not found: ")
    assert isinstance(folder, ObjectLineError) and "is a folder" in folder.message
    spaced = entries[30]
    assert isinstance(spaced, ObjectSpec) and spaced.name == "spaced" and spaced.source.endswith("with space.obj")


def test_a_large_mesh_is_hashed_a_block_at_a_time_to_the_same_id(tmp_path: Path) -> None:
    mesh = tmp_path / "large.obj"
    mesh.write_text(TETRA + "".join(f"# padding line {i}\n" for i in range(200_000)))  # ~4 MB
    options = ObjectOptions(size=0.2)
    assert mesh_file_spec(mesh, options).object_id == file_object_id(mesh.read_bytes(), options)


@pytest.mark.parametrize(
    "line",
    [
        "a.obj",
        "  a.obj \t name=x  size=0.1 ",
        "a.obj name=x # comment",
        "'a b.obj' name=x",
        '"a b.obj"',
        "a\\ b.obj",
        "a.obj\xa0name=x",
        "a.obj\x0cname=x",
        "#only a comment",
        "   ",
        "",
    ],
)
def test_lines_split_as_shlex_splits_them(line: str) -> None:
    assert objects_file._tokens(line) == shlex.split(line, comments=True)


def test_plan_of_many_lines_keeps_file_order_and_rotations(listing: Path) -> None:
    plan = plan_job(listing, GenerationConfig(refiner="none", rotations=8), out="/out", job_id="j")
    objects = read_objects_file(listing).objects
    assert len(plan.tasks) == len(objects) * 8
    assert [t.task_id for t in plan.tasks] == [o.task_id(r) for o in objects for r in range(8)]
    assert [t.object.object_id for t in plan.tasks[:9]] == [objects[0].object_id] * 8 + [objects[1].object_id]
    assert plan.spec.line_errors == [str(e) for e in read_objects_file(listing).errors]
    assert "tasks" not in plan.spec.model_dump()
    assert plan.tasks[-1] == plan.tasks[len(plan.tasks) - 1] and plan.tasks[2:4] == list(plan.tasks)[2:4]
    with pytest.raises(IndexError):
        plan.tasks[len(plan.tasks)]


def test_the_ledger_rows_of_a_plan_are_its_task_specs_as_json(listing: Path) -> None:
    plan = plan_job(listing, GenerationConfig(refiner="none", rotations=3), out="/out", job_id="j")
    assert list(plan.tasks.rows()) == [(t.task_id, t.model_dump(mode="json")) for t in plan.tasks]
