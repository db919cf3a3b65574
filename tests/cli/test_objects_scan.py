"""``datagen objects scan``: a tree of 10,000 files (ShapeNet and ModelNet layouts, plain folders and
broken files) becomes an objects file that reads back, every mesh once with its name and category,
every skipped file named with its reason; ``objects show`` piped keeps each error on one line
(datagen/pipeline/objects/scan.py, datagen/cli/inputs.py)."""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path

import pytest
import trimesh
from typer.testing import CliRunner

from datagen.cli.main import app
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from schemas.config import GenerationConfig

SYNSETS = [f"0{2691156 + 1000 * k}" for k in range(9)]
MODELS_PER_SYNSET = 1000
MODELNET = {"chair": (400, 100), "airplane": (400, 100)}
"""ModelNet classes: (train, test) files."""


def meshes() -> dict[str, bytes]:
    box = trimesh.creation.box(extents=(0.1, 0.08, 0.06))
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    return {
        "obj": box.export(file_type="obj").encode(),
        "off": sphere.export(file_type="off").encode(),
        "ply": box.export(file_type="ply"),
        "stl": sphere.export(file_type="stl"),
        "glb": box.export(file_type="glb"),
    }


def build_tree(root: Path) -> tuple[dict[str, tuple[str, str | None]], dict[str, str]]:
    """The tree, and what a scan must find: relative path -> (name, category) of each mesh, and
    relative path -> reason of each skipped file. Copies differ by a comment, so each is its own object."""
    base = meshes()
    expected: dict[str, tuple[str, str | None]] = {}
    for synset in SYNSETS:
        for m in range(MODELS_PER_SYNSET):
            model = hashlib.sha1(f"{synset}{m}".encode()).hexdigest()[:16]
            folder = root / synset / model / "models"
            folder.mkdir(parents=True)
            (folder / "model_normalized.obj").write_bytes(base["obj"] + f"# model {model}\n".encode())
            if m % 100 == 0:
                (folder / "model_normalized.mtl").write_text("newmtl a\n")
                (folder / "model_normalized.json").write_text("{}\n")
            expected[f"{synset}/{model}/models/model_normalized.obj"] = (f"{synset}-{model}", synset)
    for category, counts in MODELNET.items():
        number = 0
        for split, count in zip(("train", "test"), counts, strict=True):
            folder = root / "ModelNet40" / category / split
            folder.mkdir(parents=True)
            for _ in range(count):
                number += 1
                stem = f"{category}_{number:04d}"
                (folder / f"{stem}.off").write_bytes(base["off"] + f"# {stem}\n".encode())
                expected[f"ModelNet40/{category}/{split}/{stem}.off"] = (
                    f"ModelNet40-{category}-{split}-{stem}",
                    category,
                )
    plain = root / "plain"
    (plain / "nested").mkdir(parents=True)
    for suffix in ("ply", "stl", "glb"):
        (plain / f"box.{suffix}").write_bytes(base[suffix])
    (plain / "nested" / "sphere.off").write_bytes(base["off"])
    for suffix in ("ply", "stl", "glb"):
        relative = f"plain/box.{suffix}"
        expected[relative] = (f"plain-box-{hashlib.sha256(relative.encode()).hexdigest()[:8]}", None)
    expected["plain/nested/sphere.off"] = ("plain-nested-sphere", None)

    broken = root / "broken"
    (broken / "folder.obj").mkdir(parents=True)
    (broken / "empty.obj").write_bytes(b"")
    (broken / "garbage.ply").write_bytes(os.urandom(300))
    (broken / "garbage.stl").write_bytes(b"\x01\x02" * 77)
    (broken / "garbage.off").write_text("not an off file\n")
    (broken / "garbage.glb").write_bytes(b"GLTF" + bytes(40))
    (broken / "no-vertices.obj").write_text("# only comments\nmtllib x.mtl\n" * 10)
    (broken / "points.xyz").write_text("0 0 0\n")
    (broken / "no-suffix").write_text("v 0 0 0\n")
    reasons = {
        "broken/folder.obj": "a folder named like a mesh",
        "broken/empty.obj": "empty file",
        "broken/garbage.ply": "not a PLY mesh",
        "broken/garbage.stl": "not an STL mesh",
        "broken/garbage.off": "not an OFF mesh",
        "broken/garbage.glb": "not a GLB mesh",
        "broken/no-vertices.obj": "not an OBJ mesh",
        "broken/points.xyz": "unsupported suffix '.xyz'",
        "broken/no-suffix": "unsupported suffix '(none)'",
    }
    if os.geteuid() != 0:  # root reads any file
        locked = broken / "locked.obj"
        locked.write_bytes(base["obj"])
        locked.chmod(0)
        reasons["broken/locked.obj"] = "unreadable (Permission denied)"
    return expected, reasons


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, tuple[str, str | None]], dict[str, str]]:
    root = tmp_path_factory.mktemp("meshes")
    expected, reasons = build_tree(root)
    files = sum(len(names) for _, _, names in os.walk(root))
    assert files >= 10_000
    return root, expected, reasons


def skipped_rows(text: str) -> dict[str, str]:
    """The tab-separated skipped summary: path -> reason (the warning lines after it left out)."""
    lines = text.splitlines()
    start = lines.index("skipped\twhy")
    return dict(line.split("\t") for line in lines[start + 1 :] if not line.startswith("warning: "))


def test_scan_lists_a_10000_file_tree(tree, tmp_path: Path) -> None:
    root, expected, reasons = tree
    out = tmp_path / "lists" / "objects.txt"
    started = time.perf_counter()
    result = CliRunner().invoke(app, ["objects", "scan", str(root), "--out", str(out)])
    seconds = time.perf_counter() - started
    print(f"objects scan of {len(expected)} meshes, {len(reasons)} broken files: {seconds:.2f} s")
    assert result.exit_code == 0, result.output
    assert f"wrote {out}: {len(expected)} meshes in {len(SYNSETS) + len(MODELNET)} categories" in result.stdout
    assert f"skipped {len(reasons)} files" in result.stdout
    assert f"left out {2 * len(SYNSETS) * MODELS_PER_SYNSET // 100} materials" in result.stdout

    skipped = skipped_rows(result.stdout)
    assert sorted(skipped) == sorted(str(root / relative) for relative in reasons)
    for relative, reason in reasons.items():
        assert reason in skipped[str(root / relative)], (relative, skipped[str(root / relative)])

    started = time.perf_counter()
    listing = read_objects_file(out)
    print(f"read_objects_file of {len(listing.entries)} lines: {time.perf_counter() - started:.2f} s")
    assert listing.errors == []
    found = {Path(spec.source).relative_to(root.resolve()).as_posix(): spec for spec in listing.objects}
    assert len(found) == len(listing.objects) == len(expected)
    assert {path: (spec.name, spec.category) for path, spec in found.items()} == expected
    assert [spec.source for spec in listing.objects] == sorted(
        (spec.source for spec in listing.objects), key=lambda source: Path(source).parts
    )
    first_path = out.read_text().splitlines()[1].split()[0]
    assert not first_path.startswith("/") and (out.parent / first_path).is_file()  # relative to the file

    config = GenerationConfig()
    for path in (
        f"{SYNSETS[3]}/{next(p for p in found if p.startswith(SYNSETS[3])).split('/', 1)[1]}",
        "ModelNet40/chair/test/chair_0401.off",
        "plain/box.glb",
        "plain/box.ply",
        "plain/box.stl",
    ):
        prepared = prepare_object(found[path], config)
        assert prepared.watertight and len(prepared.faces) > 0


def test_scan_is_deterministic_and_prints_to_stdout_without_out(tree) -> None:
    root, expected, reasons = tree
    first = CliRunner().invoke(app, ["objects", "scan", str(root)])
    second = CliRunner().invoke(app, ["objects", "scan", str(root)])
    assert first.exit_code == 0, first.output
    assert first.stdout == second.stdout and first.stderr == second.stderr
    lines = [line for line in first.stdout.splitlines() if not line.startswith("#")]
    assert len(lines) == len(expected)
    assert all(line.startswith(str(root) + "/") for line in lines)  # absolute: no file to be relative to
    assert f"listed {len(expected)} meshes" in first.stderr
    assert sorted(skipped_rows(first.stderr)) == sorted(str(root / relative) for relative in reasons)


def test_scan_of_a_folder_without_meshes_is_one_error(tmp_path: Path) -> None:
    (tmp_path / "notes.xyz").write_text("x\n")
    result = CliRunner().invoke(app, ["objects", "scan", str(tmp_path)])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1
    assert result.stderr.startswith(f"error: {tmp_path}: holds no mesh files (1 skipped)")
    missing = CliRunner().invoke(app, ["objects", "scan", str(tmp_path / "absent")])
    assert missing.exit_code == 2 and "does not exist" in missing.stderr


def test_objects_show_piped_keeps_an_error_on_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from datagen.cli import common

    monkeypatch.setattr(common.console, "_width", 40)  # a narrow console used to wrap a cell to 9 characters
    path = tmp_path / "objects.txt"
    path.write_text("a/mesh/that/is/not/there/at/all.obj\n")
    result = CliRunner().invoke(app, ["objects", "show", str(path)])
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert lines[0] == "line\tname\tobject id\tfaces\twatertight\tunits\tscale\tsize m"
    missing = (tmp_path / "a/mesh/that/is/not/there/at/all.obj").resolve()
    assert lines[1] == (
        f"1\t-\tmesh file not found: {missing}; fix the path (relative paths start at the objects file)\t\t\t\t\t"
    )
    assert lines[2] == "0 objects ready, 1 with errors"


FLAT_SQUARE = b"v 0 0 0\nv 0.1 0 0\nv 0.1 0.1 0\nv 0 0.1 0\nf 1 2 3\nf 1 3 4\n"
BROKEN_OFF = b"OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 x\n3 0 1 2\n3 0 2 3\n"


@pytest.fixture
def odd_folder(tmp_path: Path) -> Path:
    """A mesh, its byte-identical copy, an OFF that passes the header check but will not load, a flat sheet."""
    folder = tmp_path / "odd"
    folder.mkdir()
    box = trimesh.creation.box(extents=(0.1, 0.08, 0.06)).export(file_type="obj").encode()
    (folder / "a.obj").write_bytes(box)
    (folder / "b.obj").write_bytes(box)
    (folder / "broken.off").write_bytes(BROKEN_OFF)
    (folder / "flat.obj").write_bytes(FLAT_SQUARE)
    return folder


def test_scan_leaves_out_byte_identical_copies(odd_folder: Path) -> None:
    result = CliRunner().invoke(app, ["objects", "scan", str(odd_folder)])
    assert result.exit_code == 0, result.output
    listed = [line.split()[0] for line in result.stdout.splitlines() if not line.startswith("#")]
    assert listed == [str(odd_folder / name) for name in ("a.obj", "broken.off", "flat.obj")]
    assert skipped_rows(result.stderr) == {str(odd_folder / "b.obj"): "the same bytes as a.obj, which is listed"}


def test_scan_check_loads_each_mesh_and_names_the_broken_one_in_a_plain_line(odd_folder: Path) -> None:
    result = CliRunner().invoke(app, ["objects", "scan", str(odd_folder), "--check"])
    assert result.exit_code == 0, result.output
    listed = [line.split()[0] for line in result.stdout.splitlines() if not line.startswith("#")]
    assert listed == [str(odd_folder / name) for name in ("a.obj", "flat.obj")]
    skipped = skipped_rows(result.stderr)
    assert sorted(skipped) == [str(odd_folder / "b.obj"), str(odd_folder / "broken.off")]
    reason = skipped[str(odd_folder / "broken.off")]
    assert reason.startswith("not a readable mesh (") and "Traceback" not in result.stderr
    assert reason.endswith("give an OBJ, PLY, STL, OFF or GLB file with faces")
    (warning,) = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert warning.startswith(f"warning: {odd_folder / 'flat.obj'}: flat (thinnest extent")  # listed, but named


def test_objects_show_warns_of_a_flat_mesh(odd_folder: Path, tmp_path: Path) -> None:
    listing = tmp_path / "objects.txt"
    listing.write_text(f"{odd_folder / 'a.obj'}\n{odd_folder / 'flat.obj'}\n")
    result = CliRunner().invoke(app, ["objects", "show", str(listing)])
    assert result.exit_code == 0, result.output
    (warning,) = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert warning.startswith(f"warning: {listing}:2: flat: flat (thinnest extent 0.00% of its size)")
    assert "labels are degenerate" in warning
    config = GenerationConfig()
    specs = read_objects_file(listing).objects
    box, sheet = (prepare_object(spec, config) for spec in specs)
    assert box.thinness == pytest.approx(0.06 / 0.1 * 0.8, rel=0.5) and box.flat_warning() is None
    assert sheet.thinness == 0.0


def test_scan_help_no_longer_says_submit_does_not_exist() -> None:
    """`datagen scan --help` said "until ``datagen submit`` exists" long after it did (issue 42)."""
    result = CliRunner().invoke(app, ["scan", "--help"])
    assert result.exit_code == 0
    text = " ".join(result.stdout.split())
    assert "until" not in text and "exists" not in text
    assert "before a `datagen submit`" in text or "before a datagen submit" in text


def test_scan_check_warns_of_a_flat_mesh_keeps_the_originals_name_and_names_a_truncated_file(
    tmp_path: Path, runner
) -> None:
    """Issue 52, finding 10: `objects scan --check` warns of a flat mesh as `objects show` does; of two
    byte-identical files it lists the original (``cow.off``, not ``cow-copy.off``, which sorts first);
    and a truncated OFF is named as such, not by numpy's reshape message."""
    box = trimesh.creation.box(extents=(0.1, 0.08, 0.06)).export(file_type="off")
    (tmp_path / "cow.off").write_text(box)
    (tmp_path / "cow-copy.off").write_text(box)
    (tmp_path / "broken.off").write_text(box[: len(box) // 2])
    (tmp_path / "sheet.obj").write_text(trimesh.creation.box(extents=(0.1, 0.1, 0.0005)).export(file_type="obj"))
    result = runner.invoke(app, ["objects", "scan", str(tmp_path), "--check", "--out", str(tmp_path / "objects.txt")])
    assert result.exit_code == 0, result.output
    listed = [spec.name for spec in read_objects_file(tmp_path / "objects.txt").objects]
    assert listed == ["cow", "sheet"]
    assert f"{tmp_path / 'cow-copy.off'}\tthe same bytes as cow.off, which is listed" in result.output
    (broken,) = [line for line in result.output.splitlines() if "broken.off" in line]
    assert "truncated or damaged" in broken and "reshape" not in broken
    (warning,) = [line for line in result.output.splitlines() if line.startswith("warning:")]
    assert warning.startswith(f"warning: {tmp_path / 'sheet.obj'}: flat (thinnest extent 0.50% of its size)")
