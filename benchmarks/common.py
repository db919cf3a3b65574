"""What the benchmarks share: one thread per BLAS / OpenMP pool, torch's thread count, and the repository's paths.

A benchmark that times single-threaded work calls `limit_threads` before anything imports numpy:
OpenBLAS, OpenMP and MKL read their thread counts from the environment once, when the library
loads, so a later change has no effect on this process (its subprocesses still inherit it). This
module imports nothing heavy, so it can run first::

    from benchmarks.common import limit_threads

    limit_threads()

    import numpy as np  # noqa: E402

Scripts run as modules from the repository root (``python -m benchmarks.<group>.<script>``), so
``benchmarks`` and the installed packages import by name without any path of their own.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
TESTS = REPO_ROOT / "tests"
SHARED_MESHES = REPO_ROOT.parent / "shared" / "meshes"
"""The real meshes beside the repository (absent on most machines: the scripts say so)."""
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_threads(torch_threads: int | None = None) -> None:
    """One thread for every BLAS and OpenMP pool (set in the environment, so call it before numpy is
    imported) and, when given, torch's intra-op thread count (this imports torch)."""
    for variable in THREAD_VARIABLES:
        os.environ[variable] = "1"
    if torch_threads is not None:
        import torch

        torch.set_num_threads(torch_threads)


def use_test_support() -> None:
    """Make the tests' helpers (``tests/support``: the Open3D reference, the S3 servers) importable as
    ``support``; the benchmarks reuse them rather than keep a second copy."""
    if str(TESTS) not in sys.path:
        sys.path.insert(0, str(TESTS))


def interruptible_child() -> None:
    """A `subprocess.Popen` ``preexec_fn``: SIGINT back to its default in the child. A shell starts
    background commands with SIGINT ignored, and an ignored signal stays ignored across exec (Python
    then installs no KeyboardInterrupt handler), so a harness run with ``&`` could not stop its
    commands cleanly."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def add_report_options(parser: Any, default: Path | None = None, what: str = "the report (Markdown)") -> None:
    """``--out`` (default ``default``, or none: printed only) and ``--replace``: a harness writes a new
    file, and writes over an existing one (a committed result) only when told to (`check_report`)."""
    shown = ""
    if default is not None:
        shown = f" (default {default.relative_to(REPO_ROOT) if default.is_relative_to(REPO_ROOT) else default})"
    parser.add_argument("--out", type=Path, default=default, help=what + shown)
    parser.add_argument("--replace", action="store_true", help="let --out write over an existing file")


def check_report(parser: Any, out: Path | None, replace: bool) -> None:
    """Refuse (as the parser's one-line error) an ``--out`` that exists unless ``--replace``."""
    if out is not None and out.exists() and not replace:
        parser.error(f"{out} exists; give another --out, or --replace to write over it")


def check_new_folder(parser: Any, folder: Path, what: str = "--work") -> None:
    """Refuse a folder that holds anything: a harness cleans up only what it made."""
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        parser.error(f"{what} {folder} is not a new or empty folder; give a new one (nothing is deleted)")
