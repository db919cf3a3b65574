"""Split objects into training, validation and test sets that cannot leak (``datagen objects split``).

A planner judged on objects it trained on says nothing about the next object. So the split is by
mesh, never by sample or task: every line naming the same mesh bytes (a mesh and its ``variant=``
copies, or two paths to one file's bytes) lands in the same set, and meshes listed in a held-out
file (evaluation-only sets such as the six watertight meshes) land in none.

Within each stratum (an object's ``category=``, else the name of its mesh's folder: ``ycb``, ``kit``)
the meshes are ordered by sha256 of the seed and the mesh's own digest, and the first share goes to
test, the next to validation, the rest to training. The order depends on the bytes alone, never on
paths, listing order or the machine, so the same meshes and seed give the same split anywhere.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from datagen.errors import InvalidArgument
from datagen.pipeline.objects.objects_file import ObjectsListing, object_line
from datagen.pipeline.objects.spec import ObjectSpec, content_digest

SPLITS = ("train", "val", "test")
"""The sets a split writes, each to ``<name>.txt``."""


@dataclass(frozen=True)
class SplitShares:
    """The shares of meshes per stratum that go to test and to validation (training takes the rest)."""

    test: float = 0.2
    val: float = 0.1

    def check(self) -> None:
        for name, value in (("test", self.test), ("val", self.val)):
            if not 0.0 <= value < 1.0:
                raise InvalidArgument(f"--{name} {value}: give a share in [0, 1), e.g. --{name} 0.2")
        if self.test + self.val >= 1.0:
            raise InvalidArgument(
                f"--test {self.test} and --val {self.val} leave nothing to train on; keep their sum below 1"
            )

    def counts(self, groups: int) -> tuple[int, int]:
        """(test, validation) meshes of a stratum of ``groups`` meshes, rounded; a stratum of one mesh trains."""
        test = round(self.test * groups)
        val = round(self.val * groups)
        while test + val >= groups and (test or val):
            if val >= test and val:
                val -= 1
            else:
                test -= 1
        return test, val


@dataclass(frozen=True)
class ObjectSplit:
    """The objects of each set, in listing order, and those left out because a held-out file names their mesh."""

    sets: dict[str, tuple[ObjectSpec, ...]]
    held: tuple[ObjectSpec, ...]
    strata: dict[str, dict[str, int]]
    """Per stratum, the meshes (not lines) in each set."""


def stratum_of(spec: ObjectSpec) -> str:
    """An object's stratum: its category, else its mesh's folder name (``builtin`` for built-ins)."""
    if spec.category:
        return spec.category
    return "builtin" if spec.is_builtin else Path(spec.source).parent.name


def mesh_digest(spec: ObjectSpec) -> str:
    """What makes two lines one mesh: the file's bytes (a built-in: its generator identity, the object id
    without options, as variants of one built-in share it)."""
    if spec.is_builtin:
        return hashlib.sha256(repr(sorted(spec.generator.items())).encode()).hexdigest()
    return content_digest(Path(spec.source)).hexdigest()


def split_objects(
    listings: Sequence[ObjectsListing],
    shares: SplitShares,
    seed: int,
    held_out: Sequence[ObjectsListing] = (),
) -> ObjectSplit:
    """Split the objects of ``listings`` by mesh (see the module); ``held_out`` names meshes kept out of every set."""
    shares.check()
    held_digests = {mesh_digest(spec) for listing in held_out for spec in listing.objects}
    objects = [spec for listing in listings for spec in listing.objects]
    digests = {spec.object_id: mesh_digest(spec) for spec in objects}
    held = tuple(spec for spec in objects if digests[spec.object_id] in held_digests)
    kept = [spec for spec in objects if digests[spec.object_id] not in held_digests]
    # A mesh's stratum is its first line's, so variants listed under another category stay with it.
    stratum_by_mesh: dict[str, str] = {}
    for spec in kept:
        stratum_by_mesh.setdefault(digests[spec.object_id], stratum_of(spec))
    meshes_by_stratum: dict[str, list[str]] = defaultdict(list)
    for digest, stratum in stratum_by_mesh.items():
        meshes_by_stratum[stratum].append(digest)
    set_of_mesh: dict[str, str] = {}
    strata: dict[str, dict[str, int]] = {}
    for stratum in sorted(meshes_by_stratum):
        order = sorted(meshes_by_stratum[stratum], key=lambda digest: _draw(seed, digest))
        test, val = shares.counts(len(order))
        for position, digest in enumerate(order):
            set_of_mesh[digest] = "test" if position < test else "val" if position < test + val else "train"
        strata[stratum] = {"train": len(order) - test - val, "val": val, "test": test}
    sets = {name: tuple(spec for spec in kept if set_of_mesh[digests[spec.object_id]] == name) for name in SPLITS}
    return ObjectSplit(sets=sets, held=held, strata=strata)


def _draw(seed: int, digest: str) -> str:
    return hashlib.sha256(f"{seed}\0{digest}".encode()).hexdigest()


def split_listing(objects: Sequence[ObjectSpec], folder: Path, header: str) -> str:
    """The text of one set's objects file, its paths relative to ``folder``."""
    lines = [f"# {header}", *(object_line(spec, folder) for spec in objects)]
    return "\n".join(lines) + "\n"
