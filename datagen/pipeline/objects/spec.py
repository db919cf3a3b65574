"""What one line of an objects file names: the object, its options and its identity (docs/pipeline.md section 0)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

Units = Literal["auto", "m", "mm"]
UpAxis = Literal["z", "y"]

BUILTIN_PREFIX = "builtin:"


@dataclass(frozen=True)
class ObjectOptions:
    """Options that change the prepared mesh, and so enter the object id."""

    units: Units = "auto"
    up: UpAxis = "z"
    size: float | None = None
    """Largest bounding-box extent in metres after preparation; None scales into ``size_range``."""
    variant: int | None = None
    """Seed of a shape variant (`datagen.pipeline.objects.variants`); None is the object as it is."""

    def canonical(self) -> str:
        """Sorted-key JSON; ``variant`` enters only when set, so objects without one keep their ids."""
        data: dict[str, Any] = {"units": self.units, "up": self.up, "size": self.size}
        if self.variant is not None:
            data["variant"] = self.variant
        return json.dumps(data, sort_keys=True, separators=(",", ":"))


@dataclass(frozen=True)
class ObjectSpec:
    """One resolved object of an objects file."""

    source: str
    """Absolute mesh path, or ``builtin:NAME``."""
    name: str
    options: ObjectOptions
    object_id: str
    """sha256 hex of the mesh bytes (or the built-in's generator identity) and the canonical options."""
    origin: str = ""
    """Where it was listed: ``FILE:LINE`` (empty when made in code)."""
    line: int = 0
    generator: dict[str, Any] = field(default_factory=dict)
    """For built-ins: generator name, parameters and version (what the id is made of)."""
    named: bool = False
    """Whether the name was given with ``name=`` (else it is the file stem or built-in name)."""
    category: str | None = None
    """A label from ``category=`` (ShapeNet's synset id, ModelNet's class folder); it groups objects
    and never enters the object id, so labelling a listing changes no object."""

    @property
    def is_builtin(self) -> bool:
        return self.source.startswith(BUILTIN_PREFIX)

    @property
    def id_prefix(self) -> int:
        """The first 16 hex digits of the object id as an integer (used in seeds and task ids)."""
        return int(self.object_id[:16], 16)

    def task_id(self, rotation: int) -> str:
        return f"{self.object_id[:16]}-r{rotation}"


def file_object_id(mesh_bytes: bytes, options: ObjectOptions) -> str:
    return options_object_id(hashlib.sha256(mesh_bytes), options)


def content_digest(path: Path) -> hashlib._Hash:
    """The sha256 of a file's bytes, read a block at a time (a large mesh is never held whole);
    raises what opening or reading the file raises."""
    with path.open("rb") as handle:
        return hashlib.file_digest(handle, "sha256")


def options_object_id(content: hashlib._Hash, options: ObjectOptions) -> str:
    """The object id from the sha256 of the mesh's bytes (`content`, consumed) and the options:
    the same as `file_object_id` of the same bytes."""
    content.update(b"\0" + options.canonical().encode())
    return content.hexdigest()


def mesh_file_spec(path: Path, options: ObjectOptions) -> ObjectSpec:
    """The spec of a mesh file made in code (benchmarks, tests), named by its stem; an objects file
    adds its line, a ``name=`` and path rules (`datagen.pipeline.objects.objects_file`)."""
    return ObjectSpec(
        source=str(path), name=path.stem, options=options, object_id=options_object_id(content_digest(path), options)
    )


def builtin_object_id(generator: dict[str, Any], options: ObjectOptions) -> str:
    identity = json.dumps(generator, sort_keys=True, separators=(",", ":"))
    digest = hashlib.sha256(b"builtin\0" + identity.encode())
    digest.update(b"\0" + options.canonical().encode())
    return digest.hexdigest()
