"""A package's public names, imported when first used (PEP 562), so that importing one light submodule
(``schemas.errors``, ``storage.dataset.problems``) does not import the whole package: a command that only
lists jobs starts in a fraction of a second instead of loading pyarrow, zarr and pydantic first."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_names(package: str, homes: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``: each public name of ``homes`` (name -> the submodule
    that defines it) imported from its submodule on first access, then kept in the package."""

    def __getattr__(name: str) -> Any:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        setattr(importlib.import_module(package), name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(homes)

    return __getattr__, __dir__
