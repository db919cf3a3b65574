"""benchmarks/generation/recipe_time.py's pieces: the 40-object file it times and the report it prints
(the timed jobs themselves are whole `datagen submit` runs, measured by hand:
benchmarks/generation/results/recipe-time.md)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest
from support.benchmarks import load_benchmark


@pytest.fixture(scope="module")
def recipe_time() -> ModuleType:
    return load_benchmark("generation.recipe_time")


def test_the_first_recipes_objects(recipe_time: ModuleType, tmp_path: Path) -> None:
    objects = recipe_time.recipe_objects(tmp_path)
    lines = [line for line in objects.read_text().splitlines() if line and not line.startswith("#")]
    meshes = [m for m in recipe_time.RECIPE_MESHES if (recipe_time.SHARED_MESHES / m.split()[0]).is_file()]
    assert len(lines) == 22 + recipe_time.SYNTHETIC + len(meshes)
    assert sum(line.startswith("builtin:") for line in lines) == 22
    synthetic = [line for line in lines if "/synth/" in line]
    assert len(synthetic) == recipe_time.SYNTHETIC and all(Path(line.split()[0]).is_file() for line in synthetic)


def test_report_compares_each_job_with_the_first(recipe_time: ModuleType) -> None:
    before = recipe_time.JobTime("v1", 1800.0, 320, 18_000, {"refine_views": 2000.0, "write": 50.0}, 2.0)
    after = recipe_time.JobTime("v2", 1200.0, 320, 18_000, {"refine_views": 1200.0, "write": 50.0}, 2.1)
    lines = recipe_time.report([before, after])
    assert "| v1 | 320 | 18,000 | 30 min 00.0 s | 1.00x |" in lines[2]
    assert "| v2 | 320 | 18,000 | 20 min 00.0 s | 1.50x | 1,250 | 3.91 |" in lines[3]
    assert "| refine_views | 2,000.0 | 1,200.0 |" in lines and "| write | 50.0 | 50.0 |" in lines
