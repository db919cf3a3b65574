"""Importing a benchmark or study script (``benchmarks/<group>/<script>.py``, ``studies/<group>/<script>.py``)
as the module its tests call into."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType

REPO_ROOT = Path(__file__).resolve().parents[2]


def load_benchmark(name: str, top: str = "benchmarks") -> ModuleType:
    """``<top>.<name>`` (``"generation.task_cost"``), imported by its package path as the scripts
    run (``python -m benchmarks.<name>``); the repository root joins sys.path when pytest was started
    without it (plain ``pytest`` rather than ``python -m pytest``)."""
    if str(REPO_ROOT) not in sys.path:
        sys.path.append(str(REPO_ROOT))
    return importlib.import_module(f"{top}.{name}")


def load_study(name: str) -> ModuleType:
    """``studies.<name>`` (``"planners.curve_ceiling"``), as `load_benchmark` imports a benchmark."""
    return load_benchmark(name, top="studies")
