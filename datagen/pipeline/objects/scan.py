"""List a tree of mesh files as an objects file without loading a mesh (``datagen objects scan``).

Object sets for training hold tens of thousands of meshes (ShapeNetCore, ModelNet), so a listing
reads at most the first kilobytes of each file: enough to tell a mesh by its header from an empty,
truncated or mislabelled file. Each listed mesh gets a name from its path (unique, the same on every
run) and, where the layout has one, a category: ShapeNet's synset id or ModelNet's class folder.
Whatever is not listed is kept with the reason, so the caller can name every skipped file.

Files with the same bytes would make the same samples twice: the first by path is listed and the
others left out, named (only files that share a size are read whole and hashed). With a ``check``
(``objects scan --check``) each mesh is also loaded, and one that will not load is left out with
the loader's one line.
"""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from datagen.errors import ObjectsFileError
from datagen.pipeline.objects.objects_file import relative_path
from datagen.pipeline.objects.spec import content_digest

SNIFF_BYTES = 4096
"""Bytes read from every file: holds the header of PLY, OFF, STL and GLB files."""
OBJ_SNIFF_BYTES = 65536
"""How far an OBJ file may go (comments, ``mtllib``) before its first ``v`` line."""

COMPANION_SUFFIXES = frozenset(
    {".mtl", ".json", ".binvox", ".png", ".jpg", ".jpeg", ".bmp", ".tga", ".tif", ".tiff", ".gif", ".txt", ".md"}
)
"""Files that travel with meshes (materials, textures, voxels, metadata, readmes): counted, not listed
one by one, since ShapeNet holds several of them per model."""

_SYNSET = re.compile(r"[0-9]{8}")
_OBJ_VERTEX = re.compile(rb"(?:^|[\r\n])[ \t]*v[ \t]")
_OFF_HEADER = re.compile(rb"[A-Za-z]{0,4}OFF")
_MODELNET_SPLITS = ("train", "test")


@dataclass(frozen=True)
class ScannedMesh:
    """One listed mesh: its path, a name unique in the listing and its category, if the layout has one."""

    path: Path
    name: str
    category: str | None


@dataclass(frozen=True)
class SkippedFile:
    """A file (or folder named like a mesh) left out of the listing, and why."""

    path: Path
    reason: str

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"


@dataclass(frozen=True)
class ScanResult:
    """A tree's meshes and skipped files, both sorted by path."""

    root: Path
    meshes: tuple[ScannedMesh, ...]
    skipped: tuple[SkippedFile, ...]
    companions: int
    """Materials, textures and other files that come with meshes, left out without a line each."""
    warnings: tuple[SkippedFile, ...] = ()
    """Listed meshes a check warns about (a flat mesh: every view sees nearly all of it), with why."""

    @property
    def categories(self) -> list[str]:
        return sorted({mesh.category for mesh in self.meshes if mesh.category is not None})


def _sniff_obj(head: bytes, path: Path) -> str | None:
    if _OBJ_VERTEX.search(head):
        return None
    if len(head) == SNIFF_BYTES:
        with path.open("rb") as handle:
            head = handle.read(OBJ_SNIFF_BYTES)
        if _OBJ_VERTEX.search(head):
            return None
    return f"not an OBJ mesh: no 'v' vertex line in its first {min(len(head), OBJ_SNIFF_BYTES)} bytes"


def _sniff_ply(head: bytes, path: Path) -> str | None:
    lines = head.split(b"\n", 2)
    if lines[0].strip() != b"ply" or len(lines) < 2 or not lines[1].startswith(b"format "):
        return "not a PLY mesh: it does not start with the 'ply' and 'format' header lines"
    return None


def _sniff_off(head: bytes, path: Path) -> str | None:
    for line in head.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith(b"#"):
            continue
        if _OFF_HEADER.match(stripped):
            return None
        break
    return "not an OFF mesh: its first line is not an OFF header"


def _sniff_stl(head: bytes, path: Path) -> str | None:
    size = path.stat().st_size
    if size >= 84:
        (triangles,) = struct.unpack_from("<I", head, 80)
        if size == 84 + 50 * triangles:
            return None if triangles else "binary STL with no triangles"
    if head.lstrip().startswith(b"solid") and b"facet" in head:
        return None
    return "not an STL mesh: neither binary (84 + 50 x triangles bytes) nor ASCII ('solid' ... 'facet')"


def _sniff_glb(head: bytes, path: Path) -> str | None:
    if len(head) >= 12 and head[:4] == b"glTF" and struct.unpack_from("<I", head, 4)[0] == 2:
        return None
    return "not a GLB mesh: no 'glTF' version 2 header"


SNIFFERS: dict[str, Callable[[bytes, Path], str | None]] = {
    ".glb": _sniff_glb,
    ".obj": _sniff_obj,
    ".off": _sniff_off,
    ".ply": _sniff_ply,
    ".stl": _sniff_stl,
}
"""Mesh suffixes the loader reads (`datagen.pipeline.objects.prepare.load_mesh`), each with a header
check that returns why a file is not such a mesh, or None."""


@dataclass(frozen=True)
class Verdict:
    """What a mesh check says of one file: why it is left out, or a warning for a mesh that is listed."""

    refused: str | None = None
    warning: str | None = None


MeshCheck = Callable[[Path], Verdict]
"""Loads a mesh file; the reason it cannot be used (one line), or None."""


def scan_meshes(root: str | Path, check: MeshCheck | None = None) -> ScanResult:
    """Every mesh file under ``root`` (sorted by relative path) with a name and category; what was not
    listed, with the reason: unreadable headers, byte-identical copies of a listed file, and with
    ``check`` the meshes it refuses. Raises `ObjectsFileError` when ``root`` is not a readable folder."""
    root = Path(root).absolute()
    if not root.is_dir():
        what = "does not exist" if not root.exists() else "is not a folder"
        raise ObjectsFileError(f"{root}: {what}; give the folder that holds the meshes (e.g. ShapeNetCore.v2)")
    files, skipped = _walk(root)
    meshes: list[tuple[Path, str | None]] = []
    companions = 0
    for relative in files:
        suffix = relative.suffix.lower()
        path = root / relative
        if suffix in COMPANION_SUFFIXES or relative.name.startswith("."):
            companions += 1
            continue
        sniffer = SNIFFERS.get(suffix)
        if sniffer is None:
            known = ", ".join(sorted(SNIFFERS))
            skipped.append(SkippedFile(path, f"unsupported suffix {suffix or '(none)'!r}; meshes are {known}"))
            continue
        reason = _sniff(path, sniffer)
        if reason is not None:
            skipped.append(SkippedFile(path, reason))
            continue
        meshes.append((relative, _category(relative)))
    copies = _byte_copies(root, [relative for relative, _ in meshes])
    for relative, original in sorted(copies.items()):
        skipped.append(SkippedFile(root / relative, f"the same bytes as {original.as_posix()}, which is listed"))
    meshes = [(relative, category) for relative, category in meshes if relative not in copies]
    warned: list[SkippedFile] = []
    if check is not None:
        verdicts = {relative: check(root / relative) for relative, _ in meshes}
        skipped += [SkippedFile(root / r, v.refused) for r, v in verdicts.items() if v.refused]
        warned += [SkippedFile(root / r, v.warning) for r, v in verdicts.items() if v.warning and not v.refused]
        meshes = [(relative, category) for relative, category in meshes if not verdicts[relative].refused]
    names = _unique_names([relative for relative, _ in meshes])
    listed = tuple(
        ScannedMesh(path=root / relative, name=name, category=category)
        for (relative, category), name in zip(meshes, names, strict=True)
    )
    return ScanResult(
        root=root,
        meshes=listed,
        skipped=tuple(sorted(skipped, key=lambda s: s.path)),
        companions=companions,
        warnings=tuple(sorted(warned, key=lambda s: s.path)),
    )


def _byte_copies(root: Path, files: list[Path]) -> dict[Path, Path]:
    """Each file whose bytes equal another's -> the one listed instead: the original, taken to be the
    one of the shortest name (``cow.obj`` over ``cow-copy.obj``, which sorts first), then by path. Only
    files sharing a size are hashed, so a tree of distinct meshes is read no further than its headers."""
    by_size: dict[int, list[Path]] = {}
    for relative in files:
        try:
            by_size.setdefault((root / relative).stat().st_size, []).append(relative)
        except OSError:
            continue
    copies: dict[Path, Path] = {}
    for group in by_size.values():
        if len(group) < 2:
            continue
        first: dict[str, Path] = {}
        for relative in sorted(group, key=lambda path: (len(path.stem), path.as_posix())):
            digest = _sha256(root / relative)
            if digest is None:
                continue
            if digest in first:
                copies[relative] = first[digest]
            else:
                first[digest] = relative
    return copies


def _sha256(path: Path) -> str | None:
    """The file's sha256 (`spec.content_digest`, as object ids are made), None where it cannot be read."""
    try:
        return content_digest(path).hexdigest()
    except OSError:
        return None


def _walk(root: Path) -> tuple[list[Path], list[SkippedFile]]:
    """Relative paths of the files under ``root``, sorted; folders named like meshes and unreadable
    folders as skipped entries. Links to folders are not followed (no loops)."""
    files: list[Path] = []
    skipped: list[SkippedFile] = []
    pending = [Path()]
    while pending:
        relative = pending.pop()
        try:
            with os.scandir(root / relative) as entries:
                children = sorted(entries, key=lambda entry: entry.name)
        except OSError as exc:
            skipped.append(SkippedFile(root / relative, f"cannot read the folder ({exc.strerror})"))
            continue
        for entry in children:
            child = relative / entry.name
            if entry.is_dir(follow_symlinks=False):
                if entry.name.startswith("."):
                    continue
                if Path(entry.name).suffix.lower() in SNIFFERS:
                    skipped.append(SkippedFile(root / child, "a folder named like a mesh; its files are listed"))
                pending.append(child)
            elif entry.is_file():
                files.append(child)
            elif entry.is_symlink():
                skipped.append(SkippedFile(root / child, "a broken link or a link to a folder"))
    files.sort(key=lambda path: path.parts)
    return files, skipped


def _sniff(path: Path, sniffer: Callable[[bytes, Path], str | None]) -> str | None:
    try:
        with path.open("rb") as handle:
            head = handle.read(SNIFF_BYTES)
        if not head:
            return "empty file"
        return sniffer(head, path)
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"


def _category(relative: Path) -> str | None:
    """ShapeNet's synset (``SYNSET/MODEL/models/model_normalized.*``, or v1's ``SYNSET/MODEL/model.*``)
    or ModelNet's class (``CLASS/{train,test}/NAME.off``); None for other layouts."""
    parts = relative.parts
    if len(parts) >= 4 and parts[-2] == "models" and _SYNSET.fullmatch(parts[-4]):
        return parts[-4]
    if len(parts) >= 3 and relative.stem == "model" and _SYNSET.fullmatch(parts[-3]):
        return parts[-3]
    if len(parts) >= 3 and parts[-2] in _MODELNET_SPLITS:
        return parts[-3]
    return None


def _base_name(relative: Path) -> str:
    """The relative path without suffix, folders joined by '-'; ShapeNet's ``models/model_normalized``
    (and v1's ``model``) tail is dropped, so a model is named ``SYNSET-MODEL``. No '/' in it: names
    become file names in exports and pictures."""
    parts = list(relative.with_suffix("").parts)
    if len(parts) >= 4 and parts[-2] == "models" and _SYNSET.fullmatch(parts[-4]):
        parts = parts[:-2]
    elif len(parts) >= 3 and parts[-1] == "model" and _SYNSET.fullmatch(parts[-3]):
        parts = parts[:-1]
    return "-".join(parts)


def _unique_names(paths: list[Path]) -> list[str]:
    """Base names, with the first 8 hex digits of the relative path's sha256 added to each name that
    two paths share (``chair.obj`` and ``chair.ply``): the same tree gives the same names."""
    names = [_base_name(path) for path in paths]
    counts: dict[str, int] = {}
    for name in names:
        counts[name] = counts.get(name, 0) + 1
    return [
        f"{name}-{hashlib.sha256(path.as_posix().encode()).hexdigest()[:8]}" if counts[name] > 1 else name
        for name, path in zip(names, paths, strict=True)
    ]


def scan_listing(result: ScanResult, folder: Path | None) -> str:
    """The objects file of ``result``: one ``PATH name=NAME [category=C]`` line per mesh, paths relative to
    ``folder`` (where the file is written) or absolute when it is None (printed)."""
    root = result.root.as_posix() if folder is None else relative_path(result.root, folder)
    lines = [f"# {len(result.meshes)} meshes under {root} (datagen objects scan)"]
    for mesh in result.meshes:
        target = mesh.path.as_posix() if folder is None else relative_path(mesh.path, folder)
        tokens = [target, f"name={mesh.name}"]
        if mesh.category is not None:
            tokens.append(f"category={mesh.category}")
        lines.append(" ".join(shlex.quote(token) for token in tokens))
    return "\n".join(lines) + "\n"
