"""Fixtures shared by the storage tests: one finalised dataset of every task per layout version."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from support import storage as fx


def _layout(version: int) -> Callable[[pytest.TempPathFactory], Path]:
    """A module-scoped fixture ``version_<version>``: the storage tests' tasks in that layout, finalised
    (built once per test module that asks for it; a test that damages it works on a copy)."""

    @pytest.fixture(scope="module", name=f"version_{version}")
    def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
        return fx.finalised_dataset(tmp_path_factory, version)

    return built


version_1, version_2, version_3, version_4, version_5 = (_layout(v) for v in (1, 2, 3, 4, 5))
