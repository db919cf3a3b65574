"""``datagen objects split``: a split by mesh that cannot leak (datagen/pipeline/objects/split.py).

Checked against a brute-force reading of what was written: every set's lines re-read and their mesh
files hashed, so no object and no byte-identical mesh (a variant, a copy under another path) is in two
sets; held-out meshes are in none; the same meshes and seed give the same files in any listing order;
and the committed real-object split of issue 49 is exactly what its script makes from ../shared.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest
import trimesh
from support.meshes import REPO_ROOT, SHARED_MESHES

from datagen.cli.main import app
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.split import SplitShares, split_objects

SPLIT_FOLDER = REPO_ROOT / "studies" / "planners" / "real_objects"
CORPUS = SHARED_MESHES.parent / "corpus"


def _mesh(path: Path, seed: int) -> Path:
    """A distinct small box per seed (its extents differ), written to ``path``."""
    box = trimesh.creation.box(extents=(0.05 + 0.001 * seed, 0.04, 0.03))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(box.export(file_type="obj"))
    return path


def _tree(root: Path) -> Path:
    """Three source folders of 20, 10 and 1 meshes, a copy of one mesh under another name, variants of
    another, and an objects file listing it all (plus a bad line)."""
    lines = []
    for offset, (folder, count) in enumerate((("ycb", 20), ("kit", 10), ("single", 1))):
        for k in range(count):
            _mesh(root / folder / f"m{k}.obj", seed=100 * offset + k)
            lines.append(f"{folder}/m{k}.obj name={folder}-m{k}")
    shutil.copyfile(root / "ycb" / "m3.obj", root / "kit" / "copy-of-ycb-m3.obj")
    lines.append("kit/copy-of-ycb-m3.obj name=copy units=m")  # same bytes, another object id
    lines += [f"kit/m2.obj name=kit-m2-v{v} variant={v}" for v in (1, 2, 3)]
    lines.append("kit/missing.obj name=missing")
    objects = root / "objects.txt"
    objects.write_text("\n".join(lines) + "\n")
    return objects


def _sets(folder: Path) -> dict[str, list[tuple[str, str]]]:
    """Each written set as (object id, sha256 of its mesh file's bytes) per line."""
    found = {}
    for name in ("train", "val", "test"):
        listing = read_objects_file(folder / f"{name}.txt")
        assert not listing.errors
        found[name] = [
            (spec.object_id, hashlib.sha256(Path(spec.source).read_bytes()).hexdigest()) for spec in listing.objects
        ]
    return found


def _assert_disjoint(sets: dict[str, list[tuple[str, str]]]) -> None:
    names = list(sets)
    for i, first in enumerate(names):
        for second in names[i + 1 :]:
            assert not {o for o, _ in sets[first]} & {o for o, _ in sets[second]}, (first, second)
            assert not {m for _, m in sets[first]} & {m for _, m in sets[second]}, (first, second)


def test_split_is_disjoint_by_mesh_stratified_and_names_bad_lines(tmp_path: Path, runner) -> None:
    objects = _tree(tmp_path / "meshes")
    held = tmp_path / "held.txt"
    held.write_text(f"{tmp_path / 'meshes' / 'ycb' / 'm7.obj'}\n")
    result = runner.invoke(
        app, ["objects", "split", str(objects), "--out", str(tmp_path / "split"), "--seed", "5", "--hold", str(held)]
    )
    assert result.exit_code == 0, result.output
    assert "missing.obj" in result.output  # the bad line is named, the rest split
    sets = _sets(tmp_path / "split")
    _assert_disjoint(sets)
    written = {mesh for lines in sets.values() for _, mesh in lines}
    held_mesh = hashlib.sha256((tmp_path / "meshes" / "ycb" / "m7.obj").read_bytes()).hexdigest()
    assert held_mesh not in written
    # Every good line but the held one is in exactly one set: 31 meshes + 1 copy + 3 variants - 1 held.
    assert sum(len(lines) for lines in sets.values()) == 34
    # The copy sits with its original, the variants with their mesh.
    by_mesh: dict[str, set[str]] = {}
    for name, lines in sets.items():
        for _, mesh in lines:
            by_mesh.setdefault(mesh, set()).add(name)
    assert all(len(where) == 1 for where in by_mesh.values())
    listing = read_objects_file(objects)
    ycb3 = next(s for s in listing.objects if s.name == "ycb-m3")
    copy = next(s for s in listing.objects if s.name == "copy")
    written_sets = {name: read_objects_file(tmp_path / "split" / f"{name}.txt") for name in sets}
    placed = {spec.name: name for name, listing in written_sets.items() for spec in listing.objects}
    assert placed[ycb3.name] == placed[copy.name]
    assert {placed[f"kit-m2-v{v}"] for v in (1, 2, 3)} == {placed["kit-m2"]}
    # Stratified: ycb's 19 kept meshes split 4 / 2 / 13 (rounded shares), kit's 10 as 2 / 1 / 7, the
    # lone mesh of its folder trains.
    assert "ycb\t13\t2\t4" in result.output
    assert "kit\t7\t1\t2" in result.output
    assert "single\t1\t0\t0" in result.output


def test_split_depends_on_the_meshes_and_seed_only(tmp_path: Path) -> None:
    objects = _tree(tmp_path / "meshes")
    listing = read_objects_file(objects)
    lines = objects.read_text().splitlines()
    reordered = tmp_path / "meshes" / "reordered.txt"
    reordered.write_text("\n".join(reversed(lines)) + "\n")
    first = split_objects([listing], SplitShares(), seed=3)
    again = split_objects([read_objects_file(reordered)], SplitShares(), seed=3)
    other = split_objects([listing], SplitShares(), seed=4)
    names = {k: sorted(s.name for s in v) for k, v in first.sets.items()}
    assert names == {k: sorted(s.name for s in v) for k, v in again.sets.items()}
    assert names != {k: sorted(s.name for s in v) for k, v in other.sets.items()}


@pytest.mark.parametrize(("test", "val"), [(1.0, 0.0), (0.6, 0.4), (-0.1, 0.1)])
def test_split_refuses_shares_that_leave_nothing(tmp_path: Path, runner, test: float, val: float) -> None:
    objects = _tree(tmp_path / "meshes")
    result = runner.invoke(
        app, ["objects", "split", str(objects), "--out", str(tmp_path / "s"), "--test", str(test), "--val", str(val)]
    )
    assert result.exit_code == 2
    assert result.output.count("error:") == 1


@pytest.mark.skipif(not CORPUS.is_dir(), reason=f"the real corpus is not at {CORPUS} (../shared/corpus)")
def test_committed_real_split_is_disjoint_holds_out_the_evaluation_sets_and_is_reproduced(tmp_path: Path) -> None:
    sets = _sets(SPLIT_FOLDER)
    _assert_disjoint(sets)
    held = [REPO_ROOT / "examples" / "watertight-meshes.txt"]
    held.append(REPO_ROOT / "examples" / "high-ceiling-meshes.txt")
    evaluation = {
        hashlib.sha256(Path(spec.source).read_bytes()).hexdigest()
        for path in held
        for spec in read_objects_file(path).objects
    }
    assert len(evaluation) == 12
    for name in ("train", "val", "test"):
        assert not evaluation & {mesh for _, mesh in sets[name]}, name
    # 227 scans + 30 shared meshes - the 12 evaluation meshes, each in one set.
    assert sum(len(lines) for lines in sets.values()) == 245
    # The committed files are what the committed command makes from the scans.
    listings = [read_objects_file(SPLIT_FOLDER / "corpus.txt"), read_objects_file(SPLIT_FOLDER / "meshes.txt")]
    split = split_objects(listings, SplitShares(test=0.2, val=0.1), 49, [read_objects_file(p) for p in held])
    for name, lines in sets.items():
        assert [spec.object_id for spec in split.sets[name]] == [object_id for object_id, _ in lines]
