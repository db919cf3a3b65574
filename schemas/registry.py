"""One shape for every plug-in kind: `Registry`, a named table of entries filled in code and from
installed packages' entry points.

Each kind (label objectives, sample fields, export layouts, refiners, network families, training
targets, planners) is one ``Registry`` instance in the module that defines what an entry is. A
built-in entry is registered where it is defined; a package adds one by naming it in the kind's
entry-point group (``[project.entry-points."datagen.refiners"]`` in its ``pyproject.toml``), with no
file of ours touched. The group is read the first time the registry is asked for a name it does not
hold or for its full listing, in whatever process asks: a Ray worker finds an installed plug-in as
the driver does. A name is registered once: a built-in is never shadowed by a plug-in, and of two
plug-ins of one name the first in sorted order is kept (the one `entries` lists, with its source).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Generic, TypeVar

from schemas.errors import DatagenError

T = TypeVar("T")

BUILT_IN = "built-in"
"""The source of an entry registered in code."""


class UnknownEntry(DatagenError, KeyError):
    """A name no entry of the kind has; the message lists the names there are."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class PluginError(DatagenError):
    """An installed plug-in that cannot be loaded, or that gives something that is not an entry."""


@dataclass(frozen=True)
class Registered(Generic[T]):
    """An entry with where it comes from: `BUILT_IN` or the distribution that installed it."""

    name: str
    entry: T
    source: str


def plugin_source(point: EntryPoint) -> str:
    """How a listing names where an entry point comes from: its distribution and version."""
    dist = point.dist
    return f"distribution {dist.name} {dist.version}" if dist is not None else "a plug-in"


def load_entry(point: EntryPoint) -> object:
    """The object an entry point names; a failure to import it is one `PluginError` line."""
    try:
        return point.load()
    except Exception as error:  # a third-party module may fail in any way
        raise PluginError(
            f"plug-in {point.name!r} ({point.value}, {plugin_source(point)}) cannot be loaded: "
            f"{type(error).__name__}: {error}"
        ) from None


def load_named(target: str | Callable[..., Any], what: str, error: type[Exception] = PluginError) -> Any:
    """``target`` itself when it is an object, else the attribute a ``"module:attribute"`` string
    names, imported now: how an entry names code that must not be imported before it is used (the
    generator's side of an objective or a refiner, from the reader's install)."""
    if not isinstance(target, str):
        return target
    if not target:
        raise error(f"{what} is not given")
    module, _, attribute = target.partition(":")
    try:
        return getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as failure:
        raise error(f"{what} ({target}) cannot be loaded: {failure}") from None


KINDS: list[Registry[Any]] = []
"""Every registry made, in the order their modules were imported (one per plug-in kind)."""


class Registry(Generic[T]):
    """Entries of one plug-in kind by name, in registration order (built-ins first, then plug-ins
    sorted by name).

    ``adapt`` turns an entry point into an entry; by default the entry point names the entry itself
    (an ``Objective``, a ``Layout``...) and is imported when the group is read. A kind whose plug-ins
    must stay unimported until used (planners) adapts the entry point into a lazy entry instead. A
    plug-in module may also register its entries itself when imported (decorators); then the entry
    point's object is only the module's handle.
    """

    def __init__(
        self,
        kind: str,
        group: str,
        *,
        error: type[Exception] = UnknownEntry,
        adapt: Callable[[EntryPoint], T] | None = None,
        check: Callable[[object], bool] | None = None,
    ) -> None:
        self.kind = kind
        """What one entry is, for messages: "label objective", "refiner"."""
        self.group = group
        """The entry-point group installed packages name their entries in."""
        self._error = error
        self._adapt = adapt
        self._check = check
        self._entries: dict[str, Registered[T]] = {}
        self._plugins_read = False
        KINDS.append(self)

    # -- filling ----------------------------------------------------------------------------------

    def register(self, name: str, entry: T, *, source: str = BUILT_IN) -> T:
        """Add ``entry`` under ``name``; a name is registered once (`ValueError` otherwise)."""
        if not name or not isinstance(name, str):
            raise ValueError(f"{name!r} cannot name a {self.kind}")
        if name in self._entries:
            raise ValueError(f"{self.kind} {name!r} is registered twice")
        self._entries[name] = Registered(name, entry, source)
        return entry

    def unregister(self, name: str) -> None:
        """Remove ``name`` (a test's toy, after the test); an unknown name is left alone."""
        self._entries.pop(name, None)

    def __delitem__(self, name: str) -> None:
        self.unregister(name)

    def pop(self, name: str) -> T:
        """Remove ``name`` and give its entry (a test's toy, after the test)."""
        found = self._entries.pop(name)
        return found.entry

    @contextmanager
    def replaced(self, name: str, entry: T) -> Iterator[T]:
        """``entry`` stands in for the registered ``name`` inside the block (a test's stand-in)."""
        before = self._entries[name]
        self._entries[name] = Registered(name, entry, before.source)
        try:
            yield entry
        finally:
            self._entries[name] = before

    def read_plugins(self) -> None:
        """Register every installed entry point of the group not yet registered (once a process)."""
        if self._plugins_read:
            return
        self._plugins_read = True
        points = sorted(entry_points(group=self.group), key=lambda point: (point.name, point.value))
        for point in points:
            if point.name in self._entries:
                continue  # a built-in, or the first plug-in of that name
            entry = self._adapt(point) if self._adapt is not None else load_entry(point)
            if point.name in self._entries:
                continue  # importing it registered it (a decorated plug-in)
            if self._check is not None and not self._check(entry):
                raise PluginError(
                    f"plug-in {point.name!r} ({point.value}, {plugin_source(point)}) gives "
                    f"{type(entry).__name__}, not a {self.kind}"
                )
            self._entries[point.name] = Registered(point.name, entry, plugin_source(point))  # type: ignore[arg-type]

    def forget_plugins(self) -> None:
        """Drop the plug-ins read so far, so that the group is read again (tests that install one)."""
        self._entries = {name: found for name, found in self._entries.items() if found.source == BUILT_IN}
        self._plugins_read = False

    # -- asking -----------------------------------------------------------------------------------

    def get(self, name: str) -> T | None:
        """The entry ``name`` (read from the installed plug-ins if it is not built in), or None."""
        found = self._entries.get(name)
        if found is None:
            self.read_plugins()
            found = self._entries.get(name)
        return None if found is None else found.entry

    def __getitem__(self, name: str) -> T:
        found = self.get(name)
        if found is None:
            raise self._error(f"unknown {self.kind} {name!r}; choose one of {', '.join(self.names())}")
        return found

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and self.get(name) is not None

    def entries(self, plugins: bool = True) -> list[Registered[T]]:
        """Every entry with its source, built-ins first (``plugins``: the installed ones too)."""
        if not plugins:
            return [found for found in self._entries.values() if found.source == BUILT_IN]
        self.read_plugins()
        return list(self._entries.values())

    def names(self, plugins: bool = True) -> tuple[str, ...]:
        """Every name, in registration order."""
        return tuple(found.name for found in self.entries(plugins))

    def items(self, plugins: bool = True) -> list[tuple[str, T]]:
        return [(found.name, found.entry) for found in self.entries(plugins)]

    def values(self, plugins: bool = True) -> list[T]:
        return [found.entry for found in self.entries(plugins)]

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {self.group!r}: {', '.join(self._entries)})"
