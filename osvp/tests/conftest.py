"""A small real dataset shared by the osvp tests, written once per session in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="session")
def dataset_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    out = tmp_path_factory.mktemp("osvp-data") / "dataset"
    done = subprocess.run(
        [sys.executable, str(HERE / "make_dataset.py"), str(out)],
        capture_output=True,
        text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    if done.returncode != 0:
        if "No module named 'datagen'" in done.stderr:
            pytest.skip("datagen is not installed: the osvp tests build their dataset with it (pip install -e .)")
        raise RuntimeError(f"building the test dataset failed:\n{done.stderr}")
    return str(out)
