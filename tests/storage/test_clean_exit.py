"""Every process that reads a dataset exits 0: a fresh interpreter opens a finalised dataset, takes
its length (and, in the second script, reads a sample and validates) and exits, 20 times each.

pyarrow's threaded Parquet reader left its thread pool running into interpreter shutdown, and with
pyarrow 26 many such runs aborted ("terminate called without an active exception", exit 134).
How many depends on the machine's load and the index's size: on a 40-task index (1,880 rows) a
2-core runner aborted in 12 of 20 runs before the fix (a 2-task index: 1 to 12 of 20).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from support import storage as fx

REPO_ROOT = Path(__file__).resolve().parents[2]
RUNS = 20

OPEN_AND_EXIT = """
import sys
import storage
ds = storage.open_dataset(sys.argv[1])
len(ds)
"""

READ_AND_VALIDATE = """
import sys
import storage
ds = storage.open_dataset(sys.argv[1])
assert len(ds) and len(ds[0]["points"]) and ds.failures() == []
assert storage.validate(sys.argv[1]) == []
"""


TASK_COPIES = 20
"""Copies of the two test tasks: a 40-task index, large enough for the abort to show often."""


@pytest.fixture(scope="module")
def finalised(tmp_path_factory: pytest.TempPathFactory) -> str:
    url = str(tmp_path_factory.mktemp("exit") / "ds")
    fx.build_many_tasks(url, TASK_COPIES)
    return url


def exit_codes(script: str, url: str) -> list[int]:
    """Exit codes of RUNS fresh interpreters, two at a time (a loaded machine shows the abort more)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(REPO_ROOT)}

    def run(_: int) -> int:
        done = subprocess.run(
            [sys.executable, "-c", textwrap.dedent(script), url],
            cwd=REPO_ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert "Traceback" not in done.stderr, done.stderr
        return done.returncode

    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(run, range(RUNS)))


@pytest.mark.slow
@pytest.mark.parametrize("script", [OPEN_AND_EXIT, READ_AND_VALIDATE], ids=["open-len-exit", "read-validate-exit"])
def test_a_fresh_interpreter_reading_a_dataset_exits_0(finalised: str, script: str) -> None:
    codes = exit_codes(script, finalised)
    assert codes == [0] * RUNS, f"exit codes of {RUNS} runs: {codes}"
