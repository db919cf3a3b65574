"""Every committed result of `benchmarks/` and `studies/` is named after the script that writes it.

A results file lives in a ``results/`` folder beside its script and is named like it, hyphens for
underscores: ``refine_speed.py`` writes ``refine-speed.md``; a second report of one script adds a
suffix (``task-cost-paths.md``); the record of a run of one of `scripts/` is named after that script
(``cluster-faults.md``). An input (an objects file) is no result: it lives in `examples/` or beside
the script that reads it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULT_SUFFIXES = {".md", ".png", ".json", ".csv"}


def results_files() -> list[Path]:
    found = [path for top in ("benchmarks", "studies") for path in (ROOT / top).rglob("results/*") if path.is_file()]
    return sorted(found)


def script_names(folder: Path) -> set[str]:
    """The hyphenated names of the scripts in ``folder`` and in `scripts/`."""
    scripts = [*folder.glob("*.py"), *folder.glob("*.sh"), *(ROOT / "scripts").glob("*.sh")]
    return {path.stem.replace("_", "-") for path in scripts if path.stem != "__init__"}


def named_after(stem: str, names: set[str]) -> bool:
    return any(stem == name or stem.startswith(name + "-") for name in names)


def test_there_are_results_to_check() -> None:
    assert len(results_files()) > 30


@pytest.mark.parametrize("path", results_files(), ids=lambda path: str(path.relative_to(ROOT)))
def test_a_result_is_named_after_its_script(path: Path) -> None:
    assert path.suffix in RESULT_SUFFIXES, f"{path.relative_to(ROOT)}: an input or stray file in results/"
    names = script_names(path.parent.parent)
    stem = path.name.split(".")[0]
    assert named_after(stem, names), f"{path.relative_to(ROOT)} is named after no script of {sorted(names)}"


def test_the_rule_refuses_a_stray_name() -> None:
    assert named_after("task-cost-paths", {"task-cost"})
    assert not named_after("task-costly", {"task-cost"})
    assert not named_after("learning-curve-ceiling", {"curve-ceiling", "fit-curve"})
