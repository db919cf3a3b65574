"""benchmarks/generation/gpu_recipe.py without a GPU: both jobs on the CPU (one small built-in, a small
config, one rotation; the device job through a shared refiner host) hold the same samples and every
label agrees; the agreement counts made-up
differences; a budget stops a job and what it committed is still read; it refuses to write over a
result or into a folder it did not make, and asking for CUDA where there is none is one line."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest
from support.benchmarks import load_benchmark

from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS

pytestmark = pytest.mark.skipif(not BUILTIN_WEIGHTS.is_file(), reason="no shipped POCO weights")

SMALL_CONFIG = 'rotations = 1\nvoxel_size = 0.004\nalpha = 3\n[view_space]\nsource = "generated"\ncount = 8\n'


@pytest.fixture(scope="module")
def gpu_recipe() -> ModuleType:
    return load_benchmark("generation.gpu_recipe")


@pytest.fixture
def inputs(tmp_path: Path) -> list[str]:
    (tmp_path / "objects.txt").write_text("builtin:capsule\nbuiltin:cone\nbuiltin:mug\n")
    (tmp_path / "small.toml").write_text(SMALL_CONFIG)
    return ["--objects", str(tmp_path / "objects.txt"), "--config", str(tmp_path / "small.toml")]


@pytest.mark.slow
@pytest.mark.ray
def test_both_jobs_on_the_cpu_agree_on_every_label(
    gpu_recipe: ModuleType, inputs: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "report.md"
    work = tmp_path / "work"
    argv = ["--device", "cpu", "--work", str(work), "--workers", "2", "--objects-count", "2", *inputs]
    argv += ["--shared-refiner"]  # the device job through one shared host: the same labels
    assert gpu_recipe.main([*argv, "--out", str(out)]) == 0
    text = out.read_text()
    assert "2 lines of" in text and "(a subset: time was short)" in text
    assert "one shared host, 1 jobs per encoder call" in text
    device = gpu_recipe.dataset_job("device", work / "device", 1.0, False)
    cpu = gpu_recipe.dataset_job("cpu", work / "cpu", 1.0, False)
    assert device.tasks == cpu.tasks == 2 and device.samples == cpu.samples > 0
    assert device.task_cpu > 0 and "refine_views" in device.step_cpu
    assert device.step_cpu["refiner_host"] > 0 and "refiner_host" not in cpu.step_cpu
    found = gpu_recipe.agreement(work / "device", work / "cpu")
    assert found.common == found.same_label == found.same_view_state == found.same_points == cpu.samples
    assert found.only_device == found.only_cpu == 0
    row = f"| {found.common:,} | {found.common:,} | {found.common:,} | {found.common:,} | 0 | 0 |"
    assert row in text
    with pytest.raises(SystemExit):  # the result is not written over
        gpu_recipe.main([*argv, "--out", str(out)])
    assert "exists" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # nor a folder it did not make
        gpu_recipe.main(["--device", "cpu", "--work", str(work), *inputs])
    assert "not empty" in capsys.readouterr().err


def test_the_agreement_counts_differences(gpu_recipe: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    """Made-up datasets: one label, one point count and one missing sample apart."""
    import numpy as np
    import pyarrow as pa

    class Fake:
        def __init__(self, ids: list[str], labels: list[int], points: list[int]) -> None:
            self.ids, self.data = ids, {"label": labels, "view_state": [1] * len(ids), "num_points": points}

        def column(self, name: str) -> pa.ChunkedArray:
            return pa.chunked_array([pa.array(self.ids)])

        def values(self, name: str) -> np.ndarray:
            return np.asarray(self.data[name])

    fakes = {
        "a": Fake(["s1", "s2", "s3"], [3, 5, 6], [10, 11, 12]),
        "b": Fake(["s1", "s2", "s4"], [3, 4, 6], [10, 11, 13]),
    }
    monkeypatch.setattr("storage.open_dataset", lambda url: fakes[Path(url).name])
    found = gpu_recipe.agreement(Path("a"), Path("b"))
    assert (found.common, found.same_label, found.same_view_state, found.same_points) == (2, 1, 2, 2)
    assert (found.only_device, found.only_cpu) == (1, 1)


def test_a_job_past_its_budget_is_stopped(gpu_recipe: ModuleType, tmp_path: Path) -> None:
    wall, stopped = gpu_recipe.run_job("slow", ["sleep", "30"], tmp_path, budget=0.5)
    assert stopped and wall < 20
    wall, stopped = gpu_recipe.run_job("quick", ["true"], tmp_path, budget=10)
    assert not stopped
    missing = gpu_recipe.dataset_job("none", tmp_path / "nothing", 1.0, True)
    assert (missing.tasks, missing.samples, missing.stopped) == (0, 0, True)


def test_cuda_where_there_is_none_is_one_line(
    gpu_recipe: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is here")
    assert gpu_recipe.main(["--work", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no CUDA device" in err
