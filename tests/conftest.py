"""Shared test fixtures: the real meshes of ../shared/meshes (skipped cleanly when absent), a CLI runner."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from support.meshes import SHARED_MESHES, shared_mesh_paths
from typer.testing import CliRunner

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@pytest.fixture
def runner(monkeypatch: pytest.MonkeyPatch) -> CliRunner:
    """A CLI runner with a wide console, so table cells holding error messages are not wrapped mid-word."""
    from datagen.cli import common

    monkeypatch.setattr(common.console, "_width", 400)
    monkeypatch.setattr(common.error_console, "_width", 400)
    return CliRunner()


@pytest.fixture(scope="session")
def shared_meshes() -> list[Path]:
    paths = shared_mesh_paths()
    if not paths:
        pytest.skip(f"real meshes not found at {SHARED_MESHES} (../shared/meshes)")
    return paths


RAY_FIXTURES = {"engine_dataset"}
"""Fixtures that start a local Ray (the engine writes their dataset)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test that starts Ray, also through a fixture, so ``-m "not ray"`` leaves them out."""
    for item in items:
        if RAY_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.ray)
