"""The objects side of the scale benchmark: objects files of thousands of lines, made and measured.

Inputs, made once under the work folder and shared by every source tree measured:

- ``synth-L/``: ``datagen objects synth --count L`` (L seeded watertight meshes, binary PLY, about
  67 KB each, and ``objects.txt``); making it is a measured row too. Mesh ``i`` of a seed does not
  depend on the count, so the engine's objects files are the first lines of the largest set.
- ``tree-L/``: a ShapeNetCore-shaped tree for ``datagen objects scan``:
  ``SYNSET/MODEL/models/model_normalized.obj`` over 55 synsets of 8 digits, with ShapeNet's companion
  ``.mtl`` and ``.json`` beside each model. The meshes are tiny distinct OBJ cubes (a comment names the
  model): scan reads headers only, so their size does not matter to it.

Measured per source tree and line count, each in a fresh process (`benchmarks.scale.measure`):
``objects scan`` of the tree, ``objects show`` of the synth listing (it prepares every mesh), and
``submit --detach`` of the synth listing with the default config (8 rotations: 8 tasks a line),
which plans the job (reads and hashes every mesh file for its object id) and enqueues it.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path

from benchmarks.scale.measure import Cache, Measurement, run_measured

SYNSETS = 55
"""ShapeNetCore v2's category count."""
ROTATIONS = 8
"""The default config's rotations: tasks per objects-file line."""

_CUBE = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
_CUBE_FACES = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]


def synth_folder(work: Path, lines: int) -> Path:
    return work / f"synth-{lines}"


def ensure_synth(work: Path, lines: int, cache: Cache, env: Mapping[str, str], datagen: list[str]) -> Path:
    """``datagen objects synth --count LINES`` into the work folder, measured once (any source tree:
    synthesis is not what is compared); the folder."""
    folder = synth_folder(work, lines)
    key = f"synth|{lines}"
    if cache.get(key) is not None and (folder / "objects.txt").exists():
        return folder
    if folder.exists():
        shutil.rmtree(folder)
    logs = work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    measured = run_measured(
        [*datagen, "objects", "synth", "--count", str(lines), "--seed", "0", "--out", str(folder)],
        cwd=work,
        env=env,
        stdout=logs / f"synth-{lines}.log",
    )
    if measured.rc != 0:
        raise RuntimeError(f"objects synth --count {lines} failed: see {logs / f'synth-{lines}.log'}")
    cache.put(key, measured.to_json())
    return folder


def first_lines(listing: Path, count: int, out: Path) -> Path:
    """An objects file of the first ``count`` object lines of ``listing``, paths made absolute."""
    folder = listing.parent
    lines = []
    for raw in listing.read_text().splitlines():
        if raw.strip() and not raw.lstrip().startswith("#"):
            path, _, options = raw.partition(" ")
            lines.append(f"{folder / path} {options}".strip())
            if len(lines) == count:
                break
    if len(lines) < count:
        raise RuntimeError(f"{listing} has {len(lines)} lines, {count} wanted")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    return out


def make_tree(root: Path, models: int) -> Path:
    """A ShapeNetCore-shaped tree of ``models`` distinct tiny OBJ meshes (made once: a marker beside
    it says it is whole)."""
    done = root.with_name(root.name + ".complete")
    if done.exists():
        return root
    if root.exists():
        shutil.rmtree(root)
    for index in range(models):
        synset = f"{2_000_000 + 1_000 * (index % SYNSETS):08d}"
        model = hashlib.md5(f"model-{index}".encode()).hexdigest()
        folder = root / synset / model / "models"
        folder.mkdir(parents=True)
        vertices = "".join(f"v {x} {y} {z}\n" for x, y, z in _CUBE)
        faces = "".join("f " + " ".join(str(i) for i in face) + "\n" for face in _CUBE_FACES)
        mesh = f"# model {synset}/{model}\nmtllib model_normalized.mtl\n{vertices}{faces}"
        (folder / "model_normalized.obj").write_text(mesh)
        (folder / "model_normalized.mtl").write_text("newmtl material_0\nKd 0.5 0.5 0.5\n")
        (folder / "model_normalized.json").write_text(json.dumps({"id": model}) + "\n")
    done.write_text("")
    return root


def objects_cases(
    work: Path,
    label: str,
    source: Path,
    lines: int,
    cache: Cache,
    env: Mapping[str, str],
    datagen: list[str],
    say: Callable[[str], None],
) -> dict[str, Measurement]:
    """Every objects-side row at ``lines`` lines for one source tree (cached as a whole)."""
    key = f"objects|{label}|{lines}"
    cached = cache.get(key)
    if cached is not None:
        return {name: Measurement.from_json(m) for name, m in cached.items()}
    listing = synth_folder(work, lines) / "objects.txt"
    tree = make_tree(work / f"tree-{lines}", lines)
    base = work / label / f"objects-{lines}"
    if base.exists():
        shutil.rmtree(base)
    base.mkdir(parents=True)
    home = base / "home"
    rows: dict[str, Measurement] = {}

    def measure(name: str, *args: str) -> Measurement:
        say(f"{label} {lines} lines: {name}")
        measured = run_measured([*datagen, *args], cwd=source, env=env, stdout=base / f"{name.split()[0]}.log")
        if measured.rc != 0:
            raise RuntimeError(f"{name} failed ({measured.rc}): see {base / name.split()[0]}.log")
        rows[name] = measured
        return measured

    measure("scan", "objects", "scan", str(tree), "--out", str(base / "scanned.txt"))
    measure("show", "objects", "show", str(listing))
    measure("submit", "submit", "--objects", str(listing), "--home", str(home), "--detach")
    cache.put(key, {name: m.to_json() for name, m in rows.items()})
    shutil.rmtree(home)  # the ledger of 400k tasks is large and not needed again
    return rows


def source_env(source: Path, base: Mapping[str, str]) -> dict[str, str]:
    """The environment that runs ``source``'s code: it comes first on PYTHONPATH (the editable
    install's finder comes after the path), one thread per BLAS pool."""
    env = dict(base)
    env["PYTHONPATH"] = os.pathsep.join([str(source), *filter(None, [base.get("PYTHONPATH", "")])])
    env.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env.pop("RAY_ADDRESS", None)
    return env
