"""Shared test fixtures: the real meshes of ../shared/meshes (skipped cleanly when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from support.meshes import SHARED_MESHES, shared_mesh_paths

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


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
