"""A small real dataset shared by the osvp tests, written once per session in a subprocess, and the
same tasks in schema version 1 (no minimum covers), as an older datagen wrote them."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

HERE = Path(__file__).resolve().parent


@pytest.fixture(autouse=True)
def one_torch_thread() -> Iterator[None]:
    """Each test trains tiny networks: one thread is fastest, and on a busy machine torch's default
    (one per core) runs ten times slower. The caller's thread count is restored after the test."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def datasets(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """(version-2 dataset, version-1 dataset) of the same tasks."""
    folder = tmp_path_factory.mktemp("osvp-data")
    out, v1_out = folder / "dataset", folder / "dataset-v1"
    done = subprocess.run(
        [sys.executable, str(HERE / "make_dataset.py"), str(out), str(v1_out)],
        capture_output=True,
        text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    if done.returncode != 0:
        if "No module named 'datagen'" in done.stderr:
            pytest.skip("datagen is not installed: the osvp tests build their dataset with it (pip install -e .)")
        raise RuntimeError(f"building the test dataset failed:\n{done.stderr}")
    return str(out), str(v1_out)


@pytest.fixture(scope="session")
def dataset_url(datasets: tuple[str, str]) -> str:
    return datasets[0]


@pytest.fixture(scope="session")
def v1_dataset_url(datasets: tuple[str, str]) -> str:
    return datasets[1]
