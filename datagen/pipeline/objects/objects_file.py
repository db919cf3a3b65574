"""Parse objects files: one object per line, ``PATH [key=value ...]``.

Keys: ``name``, ``units`` (auto|m|mm), ``up`` (z|y), ``size`` (metres), ``variant`` (a seed: a
deformed copy, see `datagen.pipeline.objects.variants`), ``category`` (a label, e.g. ShapeNet's synset
id; not part of the object id). ``#`` starts a comment; blank lines are
skipped; relative paths resolve against the objects file's folder; ``builtin:NAME`` names a built-in
shape. A bad line does not stop the others: the listing keeps it as an `ObjectLineError` naming the
file, the line and the fix, so a job can record it and go on. `variants_listing` writes the text of an
objects file that adds seeded variants to every object of another.
"""

from __future__ import annotations

import math
import os
import re
import shlex
from dataclasses import dataclass, replace
from pathlib import Path

from datagen.errors import ObjectsFileError, OutputError
from datagen.pipeline.objects.spec import (
    BUILTIN_PREFIX,
    ObjectOptions,
    ObjectSpec,
    builtin_object_id,
    content_digest,
    options_object_id,
)
from datagen.pipeline.objects.variants import draw_variant_seeds
from datagen.shapes import builtins

ALLOWED_KEYS = ("name", "units", "up", "size", "variant", "category")
LINE_SYNTAX = (
    "'PATH [name=..] [units=auto|m|mm] [up=z|y] [size=METRES] [variant=SEED] [category=..]', or 'builtin:NAME'"
)
_DIGITS = re.compile(r"[0-9]+")
_SHELL_SPECIAL = re.compile(r"['\"\\#]")
"""What makes `shlex.split` differ from splitting at blanks: quotes, escapes, comments."""
_BLANKS = re.compile(r"[ \t\r\n]+")
"""The characters `shlex` splits at in POSIX mode."""


@dataclass(frozen=True)
class ObjectLineError:
    """A line of an objects file that names no usable object, and why."""

    origin: str
    line: int
    text: str
    message: str

    def __str__(self) -> str:
        return f"{self.origin}:{self.line}: {self.message}"


ObjectEntry = ObjectSpec | ObjectLineError


@dataclass(frozen=True)
class ObjectsListing:
    """Every non-blank, non-comment line of an objects file, in file order."""

    path: Path
    entries: tuple[ObjectEntry, ...]

    @property
    def objects(self) -> list[ObjectSpec]:
        return [entry for entry in self.entries if isinstance(entry, ObjectSpec)]

    @property
    def errors(self) -> list[ObjectLineError]:
        return [entry for entry in self.entries if isinstance(entry, ObjectLineError)]


def read_objects_file(path: str | Path) -> ObjectsListing:
    """Resolve every line of an objects file; raise only when the file itself is unusable."""
    path = Path(path).absolute()
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ObjectsFileError(f"{path}: objects file not found; pass the path of an existing file") from None
    except UnicodeDecodeError:
        raise ObjectsFileError(
            f"{path}: not a text file; an objects file lists one 'PATH [key=value ...]' per line"
        ) from None
    except OSError as exc:
        raise ObjectsFileError(f"{path}: cannot read objects file ({exc.strerror})") from None
    entries: list[ObjectEntry] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        try:
            tokens = _tokens(raw)
        except ValueError as exc:
            entries.append(
                ObjectLineError(
                    origin=str(path),
                    line=number,
                    text=raw.strip(),
                    message=f"cannot split the line ({exc}); close the quotes around the path",
                )
            )
            continue
        if tokens:
            entries.append(_parse_line(path, number, raw.strip(), tokens))
    if not entries:
        raise ObjectsFileError(f"{path}: lists no objects; add one line per mesh, {LINE_SYNTAX}")
    return ObjectsListing(path=path, entries=tuple(_flag_duplicates(entries)))


def _tokens(raw: str) -> list[str]:
    """``shlex.split(raw, comments=True)``; a line without quotes, escapes or ``#`` (nearly every
    line of a long listing) is split at blanks directly, with the same result, 20x faster."""
    if _SHELL_SPECIAL.search(raw):
        return shlex.split(raw, comments=True)
    return [token for token in _BLANKS.split(raw) if token]


def _parse_line(path: Path, number: int, raw: str, tokens: list[str]) -> ObjectEntry:
    origin = str(path)

    def fail(message: str) -> ObjectLineError:
        return ObjectLineError(origin=origin, line=number, text=raw, message=message)

    target, pairs = tokens[0], tokens[1:]
    if "=" in target and target.partition("=")[0] in ALLOWED_KEYS:
        return fail("the line must start with a mesh path or builtin:NAME, then key=value options")
    options: dict[str, str] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key or not value:
            return fail(f"malformed option {pair!r}; options are key=value with keys {', '.join(ALLOWED_KEYS)}")
        if key not in ALLOWED_KEYS:
            return fail(f"unknown key {key!r}; allowed keys: {', '.join(ALLOWED_KEYS)}")
        if key in options:
            return fail(f"key {key!r} given twice; keep one")
        options[key] = value
    try:
        object_options = _object_options(options)
    except ValueError as exc:
        return fail(str(exc))
    if target.startswith(BUILTIN_PREFIX):
        spec = _builtin_spec(target, options.get("name"), object_options, origin, number)
        return replace(spec, category=options.get("category")) if isinstance(spec, ObjectSpec) else spec
    mesh_path = Path(target).expanduser()
    if not mesh_path.is_absolute():
        mesh_path = path.parent / mesh_path
    mesh_path = mesh_path.resolve()
    try:
        # A block at a time: a large mesh is never held whole. In turn, not by a pool of threads:
        # on 50,000 synthetic meshes (67 KB, page cache, 2 cores) 8 threads took 8.2 s against
        # 6.0 s (they wait on each other for the interpreter); on 400 files of 5 MB they gained 10 %.
        content = content_digest(mesh_path)
    except FileNotFoundError:
        return fail(f"mesh file not found: {mesh_path}; fix the path (relative paths start at the objects file)")
    except IsADirectoryError:
        return fail(f"{mesh_path} is a folder; name a mesh file (OBJ, PLY, STL, OFF, GLB...)")
    except OSError as exc:
        return fail(f"cannot read {mesh_path} ({exc.strerror})")
    return ObjectSpec(
        source=str(mesh_path),
        name=options.get("name") or default_name(mesh_path.stem, object_options),
        options=object_options,
        object_id=options_object_id(content, object_options),
        origin=f"{origin}:{number}",
        line=number,
        named="name" in options,
        category=options.get("category"),
    )


def _object_options(options: dict[str, str]) -> ObjectOptions:
    units = options.get("units", "auto")
    if units not in ("auto", "m", "mm"):
        raise ValueError(f"units={units!r} is not allowed; use units=auto, units=m or units=mm")
    up = options.get("up", "z")
    if up not in ("z", "y"):
        raise ValueError(f"up={up!r} is not allowed; use up=z or up=y")
    size: float | None = None
    if "size" in options:
        try:
            size = float(options["size"])
        except ValueError:
            raise ValueError(f"size={options['size']!r} is not a number; give metres, e.g. size=0.12") from None
        if not math.isfinite(size) or size <= 0:
            raise ValueError(f"size={options['size']} must be a positive number of metres, e.g. size=0.12")
    return ObjectOptions(units=units, up=up, size=size, variant=_variant(options))  # type: ignore[arg-type]


def _variant(options: dict[str, str]) -> int | None:
    if "variant" not in options:
        return None
    if not _DIGITS.fullmatch(options["variant"]):
        raise ValueError(
            f"variant={options['variant']!r} is not allowed; give a non-negative integer seed, e.g. variant=3 "
            "(leave it out for the object as it is)"
        )
    return int(options["variant"])


def default_name(stem: str, options: ObjectOptions) -> str:
    """A line's name without ``name=``: the file stem (or built-in name), plus ``-v<SEED>`` for a variant."""
    return stem if options.variant is None else f"{stem}-v{options.variant}"


def _builtin_spec(target: str, name: str | None, options: ObjectOptions, origin: str, number: int) -> ObjectEntry:
    shape = target[len(BUILTIN_PREFIX) :]
    try:
        identity = builtins.builtin_generator_identity(shape)
    except KeyError:
        known = ", ".join(builtins.builtin_names())
        return ObjectLineError(
            origin=origin,
            line=number,
            text=target,
            message=f"unknown built-in {shape!r}; built-ins: {known} (see 'datagen objects builtins')",
        )
    return ObjectSpec(
        source=target,
        name=name or default_name(shape, options),
        options=options,
        object_id=builtin_object_id(identity, options),
        origin=f"{origin}:{number}",
        line=number,
        generator=identity,
        named=name is not None,
    )


def _flag_duplicates(entries: list[ObjectEntry]) -> list[ObjectEntry]:
    """The same object twice (same id) is an error naming both lines; so is a name given twice
    with ``name=``. A default name (file stem) that collides gets the object id's first 8 hex
    digits appended, since folders of meshes often share stems (ShapeNet's model_normalized)."""
    explicit = {e.name for e in entries if isinstance(e, ObjectSpec) and e.named}
    first_by_id: dict[str, ObjectSpec] = {}
    first_by_name: dict[str, ObjectSpec] = {}
    result: list[ObjectEntry] = []
    for entry in entries:
        if isinstance(entry, ObjectSpec):
            earlier = first_by_id.get(entry.object_id)
            if earlier is not None:
                result.append(
                    _line_error(
                        entry,
                        f"the same object as line {earlier.line} (same mesh and options); "
                        f"delete one of lines {earlier.line} and {entry.line}",
                    )
                )
                continue
            if entry.named and entry.name in first_by_name:
                earlier = first_by_name[entry.name]
                result.append(
                    _line_error(
                        entry,
                        f"name {entry.name!r} is already used by line {earlier.line}; give one of them "
                        "another name with name=...",
                    )
                )
                continue
            if not entry.named and (entry.name in first_by_name or entry.name in explicit):
                entry = replace(entry, name=f"{entry.name}-{entry.object_id[:8]}")
            first_by_id[entry.object_id] = entry
            first_by_name[entry.name] = entry
        result.append(entry)
    return result


def _line_error(entry: ObjectSpec, message: str) -> ObjectLineError:
    return ObjectLineError(origin=entry.origin.rsplit(":", 1)[0], line=entry.line, text=entry.source, message=message)


def variants_listing(listing: ObjectsListing, count: int, seed: int, out: Path) -> str:
    """The text of an objects file at ``out``: each object of ``listing``, then ``count`` variants of it
    (the same seeds, from `draw_variant_seeds`, for every object), paths relative to ``out``'s folder."""
    seeds = draw_variant_seeds(count, seed)
    _check_can_vary(listing, out)
    folder = Path(out).absolute().parent.resolve()
    source = relative_path(listing.path, folder)
    lines = [f"# {count} variants of each object of {source}, seed {seed} (datagen objects variants)"]
    for spec in listing.objects:
        lines.append(object_line(spec, folder))
        lines.extend(object_line(spec, folder, variant) for variant in seeds)
    return "\n".join(lines) + "\n"


def object_line(spec: ObjectSpec, folder: Path, variant: int | None = None) -> str:
    """The objects-file line of ``spec`` (with ``variant`` set, when given) for a file in ``folder``."""
    options = spec.options if variant is None else replace(spec.options, variant=variant)
    tokens = [spec.source if spec.is_builtin else relative_path(Path(spec.source), folder)]
    if spec.named:
        tokens.append(f"name={spec.name if variant is None else default_name(spec.name, options)}")
    if options.units != "auto":
        tokens.append(f"units={options.units}")
    if options.up != "z":
        tokens.append(f"up={options.up}")
    if options.size is not None:
        tokens.append(f"size={options.size!r}")
    if options.variant is not None:
        tokens.append(f"variant={options.variant}")
    if spec.category is not None:
        tokens.append(f"category={spec.category}")
    return " ".join(shlex.quote(token) for token in tokens)


def _check_can_vary(listing: ObjectsListing, out: Path) -> None:
    """Refuse what would make a wrong variants file: bad lines, lines already variants, writing over the input."""
    if listing.errors:
        first, more = listing.errors[0], len(listing.errors) - 1
        also = f" (and {more} more bad lines)" if more else ""
        raise ObjectsFileError(f"{first}{also}; fix or delete the bad lines before making variants")
    for spec in listing.objects:
        if spec.options.variant is not None:
            raise ObjectsFileError(
                f"{spec.origin}: is already a variant (variant={spec.options.variant}); list the base objects only"
            )
    if Path(out).absolute().resolve() == listing.path.resolve():
        raise OutputError(f"{out}: is the objects file being varied; write the variants to another file")


def relative_path(path: Path, folder: Path) -> str:
    """``path`` relative to ``folder``; absolute when the two share no folder below the root (``/tmp/x``
    and ``/data/meshes``), where a relative path would only break when either moves."""
    resolved = path.resolve()
    try:
        common = Path(os.path.commonpath([resolved, folder]))
    except ValueError:  # different Windows drives
        return resolved.as_posix()
    if common == Path(common.anchor):
        return resolved.as_posix()
    return Path(os.path.relpath(resolved, folder)).as_posix()
