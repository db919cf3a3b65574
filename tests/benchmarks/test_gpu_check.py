"""benchmarks/generation/gpu_check.py without a GPU: run on the CPU against itself (one small built-in, a
small config) every comparison comes out identical and the JSON has every field; the comparison counts
made-up differences; a device run that raises is recorded and the status says so; asking for CUDA where
there is none is one line and a non-zero status."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch
from support.benchmarks import load_benchmark

from datagen.config_io import load_config
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine import RefineRequest
from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas
from datagen.pipeline.viewspace import build_view_space

pytestmark = pytest.mark.skipif(not BUILTIN_WEIGHTS.is_file(), reason="no shipped POCO weights")

SMALL_CONFIG = 'voxel_size = 0.004\nalpha = 3\n[view_space]\nsource = "generated"\ncount = 8\n'
"""8 views and 4 mm keys: a task refines in about a second, where the default config takes 5-15 s."""
COMPARISON_FIELDS = {
    "singles",
    "singles_identical",
    "cases",
    "cases_identical",
    "differing_keys",
    "union_keys",
    "share_max",
    "share_mean",
    "max_prob_diff",
    "same_queries",
    "same_cases",
    "samples",
    "labels_differing",
    "failures_equal",
    "refinements",
    "refined_identical",
    "labels_identical",
}
REFINEMENT_FIELDS = {"mask", "kept_reference", "kept", "differing", "union", "max_prob_diff", "same_queries", "share"}
SUMMARY_FIELDS = {
    "tasks",
    "errors",
    "refined_identical_tasks",
    "labels_identical_tasks",
    "differing_keys",
    "union_keys",
    "share_max",
    "max_prob_diff",
    "labels_differing",
    "samples",
    "task_seconds",
    "refine_seconds",
    "reference_task_seconds",
    "reference_refine_seconds",
}
ENVIRONMENT_FIELDS = {
    "python",
    "platform",
    "cpu",
    "cpu_count",
    "numpy",
    "torch",
    "torch_cuda",
    "cudnn",
    "device",
    "device_name",
    "device_capability",
    "cuda_driver",
    "torch_threads_in_tasks",
    "packages",
    "tf32_default",
}


@pytest.fixture(scope="module")
def gpu_check() -> ModuleType:
    return load_benchmark("generation.gpu_check")


@pytest.fixture(scope="module")
def gpu_compare() -> ModuleType:
    return load_benchmark("generation.gpu_compare")


@pytest.fixture
def inputs(tmp_path: Path) -> list[str]:
    """``--objects`` (one small built-in) and ``--config`` (the small config) arguments."""
    (tmp_path / "objects.txt").write_text("builtin:capsule\n")
    (tmp_path / "small.toml").write_text(SMALL_CONFIG)
    return ["--objects", str(tmp_path / "objects.txt"), "--config", str(tmp_path / "small.toml")]


def test_cpu_against_itself_is_identical_and_the_json_complete(
    gpu_check: ModuleType, inputs: list[str], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    assert gpu_check.main(["--device", "cpu", *inputs, "--repeat", "--no-tf32", "--out", str(out)]) == 0
    result = json.loads((out / "gpu-check.json").read_text())
    labels = ["cpu", "cpu again", "cpu fp32"]
    assert [v["label"] for v in result["variants"]] == labels
    assert result["variants"][2]["tf32"] is False
    assert result["complete"] is True
    assert set(result["environment"]) == ENVIRONMENT_FIELDS
    assert result["environment"]["device"] == "cpu"
    assert result["environment"]["torch"] == torch.__version__
    assert set(result["warm_up_seconds"]) == {"cpu reference", *labels}
    assert result["refiner"]["name"] == "poco"
    assert len(result["refiner"]["weights_id"]) == 64
    (task,) = result["tasks"]
    assert (task["object"], task["rotation"], task["errors"]) == ("capsule", 0, {})
    assert task["samples"] > 0
    assert set(task["runs"]) == {"cpu reference", *labels}
    for run in task["runs"].values():
        assert 0 < run["refine_seconds"] <= run["task_seconds"]
        assert {"refine_views", "refine_cases", "labels"} <= set(run["steps"])
    for label in labels:
        compared = task["comparisons"][label]
        assert set(compared) == COMPARISON_FIELDS
        assert compared["singles"] == 8  # every view of the small config, then the multi-view cases
        assert len(compared["refinements"]) == task["refinements"] == compared["singles"] + compared["cases"]
        assert all(set(r) == REFINEMENT_FIELDS for r in compared["refinements"])
        assert compared["refined_identical"] and compared["labels_identical"]
        assert compared["singles_identical"] == 8 and compared["cases_identical"] == compared["cases"] > 0
        assert compared["differing_keys"] == 0 and compared["union_keys"] > 0
        assert compared["max_prob_diff"] == 0.0 and compared["same_queries"] and compared["same_cases"]
        assert compared["samples"] == task["samples"] and compared["labels_differing"] == 0
        summary = result["summary"][label]
        assert set(summary) == SUMMARY_FIELDS
        assert (summary["tasks"], summary["errors"], summary["refined_identical_tasks"]) == (1, 0, 1)
        assert summary["labels_identical_tasks"] == 1 and summary["share_max"] == 0.0
    report = (out / "gpu-check.md").read_text()
    assert "| capsule | 0 | cpu again | 8/8 |" in report
    assert report.count("| cpu fp32 |") == 2  # its task row and its summary row


def test_recorded_refinements_are_the_refiners_own(gpu_check: ModuleType, inputs: list[str]) -> None:
    config = load_config(Path(inputs[3]))
    (spec,) = read_objects_file(Path(inputs[1])).objects
    scan = scan_task(prepare_object(spec, config), 0, config, build_view_space(config.view_space))
    requests = [RefineRequest(o, config.seed, spec.object_id, 0) for o in scan.observations[:2]]
    base = gpu_check.base_refiner(config, "cpu")
    recording = gpu_check.RecordingRefiner(base)
    with single_threaded_blas(), fixed_torch_threads():
        kept = recording.refine(requests)
        plain = base.refine(requests)
    assert [r.mask for r in recording.records] == [1, 2]
    for mine, theirs, record in zip(kept, plain, recording.records, strict=True):
        assert mine.size > 0
        assert np.array_equal(mine, record.kept) and np.array_equal(mine, theirs)
        assert np.array_equal(record.kept, record.queries[record.prob > base.threshold])


def test_comparison_counts_differences(gpu_compare: ModuleType) -> None:
    keys = np.arange(10, dtype=np.int64)
    prob = np.linspace(0.0, 0.9, 10).astype(np.float32)

    def refinement(mask: int, p: np.ndarray) -> object:
        return gpu_compare.Refinement(mask, keys, p, keys[p > 0.5])

    nudged = prob.copy()
    nudged[5] = 0.51  # 0.5 before: one key crosses the threshold
    reference = gpu_compare.TaskRun([refinement(1, prob), refinement(3, prob)], {1: (2, "optimal")}, {}, (1, 3), 2, 1)
    other = gpu_compare.TaskRun([refinement(1, prob), refinement(3, nudged)], {1: (4, "optimal")}, {}, (1, 3), 1, 1)
    compared = gpu_compare.compare_runs(reference, other)
    assert (compared.singles, compared.singles_identical, compared.cases, compared.cases_identical) == (1, 1, 1, 0)
    assert (compared.differing_keys, compared.union_keys) == (1, 4 + 5)
    assert compared.share_max == pytest.approx(1 / 5) and compared.share_mean == pytest.approx(1 / 10)
    assert compared.max_prob_diff == pytest.approx(0.01, abs=1e-6)
    assert not compared.refined_identical and not compared.labels_identical and compared.labels_differing == 1
    with pytest.raises(ValueError, match="out of step"):
        gpu_compare.compare_runs(reference, gpu_compare.TaskRun(other.refinements[::-1], {}, {}, (), 1, 1))


def test_a_device_run_that_raises_is_reported(
    gpu_check: ModuleType, inputs: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = gpu_check.run_variant

    def broken(prepared: object, rotation: int, config: object, view_space: object, variant: object) -> object:
        if variant.label != gpu_check.REFERENCE:  # type: ignore[attr-defined]
            raise RuntimeError("no kernel image is available")
        return real(prepared, rotation, config, view_space, variant)

    monkeypatch.setattr(gpu_check, "run_variant", broken)
    out = tmp_path / "out"
    assert gpu_check.main(["--device", "cpu", *inputs, "--out", str(out)]) == 1
    (task,) = json.loads((out / "gpu-check.json").read_text())["tasks"]
    assert task["errors"] == {"cpu": "RuntimeError: no kernel image is available"}
    assert task["comparisons"] == {}
    assert "**error**: RuntimeError: no kernel image is available" in (out / "gpu-check.md").read_text()


def test_a_spent_budget_starts_no_task_and_says_so(gpu_check: ModuleType, inputs: list[str], tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert gpu_check.main(["--device", "cpu", *inputs, "--budget", "0", "--out", str(out)]) == 0
    result = json.loads((out / "gpu-check.json").read_text())
    assert (result["tasks"], result["complete"]) == ([], False)
    assert "stopped early" in (out / "gpu-check.md").read_text()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_a_gpu_is_one_line(gpu_check: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    assert gpu_check.main(["--device", "cuda"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1 and "sees no CUDA device" in captured.err
