"""benchmarks/generation/task_cost.py's pieces on tiny inputs: every floor helper computes (no timed assertions),
FLOPs are counted exactly, the decoder's FLOP model is linear in the queries, the hooks restore what
they patch, and one whole task (refiner none) is measured with a floor for each step."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import trimesh
from support.benchmarks import load_benchmark

from datagen.pipeline import raycast
from datagen.pipeline.setcover import minimal_masks
from schemas.config import GenerationConfig
from schemas.index import TASK_STEPS


@pytest.fixture(scope="module")
def task_cost() -> ModuleType:
    return load_benchmark("generation.task_cost")


def test_cpu_and_matmul_rate(task_cost: ModuleType) -> None:
    assert task_cost.best_cpu(lambda: sum(range(100)), repeats=2) >= 0.0
    assert task_cost.matmul_gflops(size=64, repeats=1) > 0.0


def test_embree_floor_casts_the_same_batches(task_cost: ModuleType) -> None:
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    caster = raycast.RayCaster(box.vertices, box.faces)
    directions = np.tile(np.array([[0.0, 0.0, -1.0]], dtype=np.float32), (16, 1))
    origins = np.tile(np.array([[0.0, 0.0, 1.0]], dtype=np.float32), (16, 1))
    assert (caster._scene.run(origins, directions, output=0) >= 0).all()  # every ray hits the box
    assert task_cost.embree_floor([(caster._scene, origins, directions)], repeats=1) >= 0.0
    assert task_cost.embree_floor([]) == 0.0


def test_knn_floor(task_cost: ModuleType) -> None:
    rng = np.random.default_rng(0)
    calls = [
        task_cost.KnnCall(rng.random((20, 3)), rng.random((7, 3)), 16),
        task_cost.KnnCall(rng.random((3, 3)), rng.random((5, 3)), 16),
    ]
    assert task_cost.knn_floor(calls, repeats=1) >= 0.0  # k above the source size is clamped
    assert task_cost.knn_floor([]) == 0.0


def test_flops_are_counted_exactly(task_cost: ModuleType) -> None:
    import torch

    layer = torch.nn.Linear(8, 4, bias=False)
    assert task_cost.count_flops(lambda: layer(torch.ones(5, 8))) == 2 * 5 * 8 * 4


class TinyModel:
    """Stands for a POCO model: encode is one matmul over the points, decode a fixed part plus one
    matmul per query."""

    def __init__(self) -> None:
        import torch

        self.weight = torch.ones(6, 3)

    def encode(self, points: Any, features: Any, tables: Any) -> Any:
        return self.weight @ points[0]

    def decode(self, latents: Any, points: Any, queries: Any, knn: Any, chunk_size: int = 4) -> Any:
        fixed = self.weight @ points[0]  # per-point terms, once
        return fixed.sum() + (self.weight @ queries[0]).sum(dim=0)


def test_network_flops_model_the_decoder_as_linear_in_queries(task_cost: ModuleType) -> None:
    import torch

    model = TinyModel()
    points, queries = torch.ones(1, 3, 10), torch.ones(1, 3, 9)
    found = task_cost.Recording()
    found.model = model
    found.first_encode = ((points, points, {}), {})
    found.first_decode = ((None, points, queries, torch.zeros(1, 9, 2, dtype=torch.int64)), {"chunk_size": 4})
    found.network = {
        "refine_views": [task_cost.NetworkCall("encode", 10), task_cost.NetworkCall("decode", 9)],
        "refine_cases": [task_cost.NetworkCall("encode", 10), task_cost.NetworkCall("decode", 100)],
    }
    flops = task_cost.network_flops(found)
    per_point = 2 * 6 * 3
    assert flops["refine_views"] == 10 * per_point + (10 + 9) * per_point
    assert flops["refine_cases"] == 10 * per_point + (10 + 100) * per_point
    assert task_cost.network_flops(task_cost.Recording()) == {}


def test_cpu_floors_of_the_small_steps(task_cost: ModuleType, tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    config = GenerationConfig()
    assert task_cost.ground_truth_floor(np.asarray(box.vertices), np.asarray(box.faces), config, repeats=1) >= 0.0
    keys = [np.array([1, 5, 9], dtype=np.int64), np.array([2, 5], dtype=np.int64)]
    assert task_cost.unique_floor(keys, repeats=1) >= 0.0
    assert task_cost.write_floor(4096, tmp_path, repeats=2) >= 0.0
    assert list(tmp_path.iterdir()) == []


def test_reduced_instances_and_highs(task_cost: ModuleType) -> None:
    masks = minimal_masks(np.array([0b0011, 0b0110, 0b1100, 0b1000, 0b0111], dtype=np.uint64))
    assert masks.tolist() == [0b0011, 0b0110, 0b1000]
    # case {0}: rows 0b0110 and 0b1000 miss it; view 3 is forced, which leaves 0b0110. Case {0..3}
    # misses no row, and case {1, 2} only 0b1000, which forcing view 3 settles: neither has an instance.
    instances = task_cost.reduced_instances(masks, [0b0001, 0b1111, 0b0110])
    assert [r.tolist() for r in instances] == [[0b0110]]
    seconds, limited = task_cost.highs_floor(instances, repeats=1)
    assert seconds >= 0.0 and limited == 0
    assert task_cost.highs_floor([]) == (0.0, 0)


def test_hooks_restore_what_they_patch(task_cost: ModuleType) -> None:
    cast = raycast.RayCaster.cast
    with task_cost.recording(task_cost.RecordingClock()):
        assert raycast.RayCaster.cast is not cast
    assert raycast.RayCaster.cast is cast


def test_one_task_measured_with_a_floor_for_each_step(task_cost: ModuleType, tmp_path: Path) -> None:
    config = GenerationConfig(refiner="none")
    (spec,) = task_cost.object_specs(["builtin:capsule"])
    cost = task_cost.measure_task(spec, config, gflops=100.0, floor_repeats=1)
    assert list(cost.cpu) == list(TASK_STEPS) and cost.samples > 0
    assert sum(cost.cpu.values()) <= cost.total_cpu + 0.05
    for step in TASK_STEPS:
        if step.startswith("refine_"):
            assert cost.floor[step] == 0.0  # no network, no kNN: nothing to floor
        else:
            assert cost.floor[step] is not None and cost.floor[step] >= 0.0, step
    assert cost.details["imaging"]["rays"] > 0 and cost.details["write"]["bytes"] > 0
    rows = task_cost.step_rows([cost, cost])
    assert sum(r.share for r in rows) == pytest.approx(1.0)
    table = task_cost.table_lines(rows)
    assert table[0].startswith("| step | CPU-s | share") and len(table) == 2 + len(TASK_STEPS) + 1
    comparison = task_cost.comparison_lines(["a", "b"], [[cost], [cost]])
    assert comparison[-1].endswith("| 1.00x |")
    run = task_cost.Run(["default"], [""], [[cost]], 100.0, "now", "0 0 0", "0 0 0", 0.0, 1.0, "a machine")
    assert task_cost.Run.from_json(json.loads(json.dumps(run.to_json()))) == run  # --save-json, --render
    report = "\n".join(task_cost.render(task_cost.merged([("before", run), ("after", run)])))
    assert "## before:default: 1 tasks" in report and "## after:default: 1 tasks" in report
    assert "## Comparison" in report and "| write |" in report


@pytest.mark.slow
def test_the_shared_path_moves_the_network_to_the_host(task_cost: ModuleType) -> None:
    """``--paths shared``: the same task through a host in a second process: the same samples, the
    network's CPU in ``refiner_host`` instead of the refine steps, the task's wait in ``refiner_queue``."""
    from datagen.pipeline.refine import make_refiner

    config = GenerationConfig()
    (spec,) = task_cost.object_specs(["builtin:capsule"])
    refiner = make_refiner(config)
    worker = task_cost.measure_task(spec, config, refiner=refiner, gflops=100.0, floor_repeats=1)
    with task_cost.host_process(config, "cpu", 1) as network:
        shared = task_cost.measure_task(
            spec, config, refiner=task_cost.on_path(refiner, network), gflops=100.0, floor_repeats=1
        )
    assert shared.samples == worker.samples > 0
    assert shared.cpu["refiner_host"] > 0 and "refiner_queue" in shared.wall
    own = shared.cpu["refine_views"] + shared.cpu["refine_cases"]
    assert own < worker.cpu["refine_views"] + worker.cpu["refine_cases"]  # the network ran elsewhere
    rows = task_cost.step_rows([shared])
    assert [r.step for r in rows][-2:] == ["refiner_host", "refiner_queue"]
    assert next(r for r in rows if r.step == "refiner_host").floor is None


def test_original_execution_is_the_same_poco_refiner_unoptimised(task_cost: ModuleType) -> None:
    from datagen.pipeline.refine import make_refiner

    fast = make_refiner(GenerationConfig())
    original = task_cost.original_execution(fast)
    assert fast.fast and not original.fast and original.depth_buffers is None  # --original's "before"
    assert original.model is fast.model and original.weights_id == fast.weights_id
    assert original.threshold == fast.threshold and original.config == fast.config
    carve = make_refiner(GenerationConfig(refiner="carve"))
    assert task_cost.original_execution(carve) is carve  # nothing to switch off


@pytest.mark.parametrize(
    ("fast", "layout"), [(False, None), (True, None), (True, "last")], ids=["original", "fast", "fast-via-decode"]
)
def test_both_executions_record_the_same_network_work(task_cost: ModuleType, fast: bool, layout: str | None) -> None:
    """The fast execution decodes through `decode_inference`: the hooks time it as network and count
    its FLOPs by replaying `decode`, so the two executions' floors are the same. Where it falls back
    to `decode` itself (the channels-last layout) the call is still counted once."""
    import torch

    from datagen.pipeline.refine.poco.network import PocoModel

    torch.manual_seed(0)  # the weights of a throwaway model; nothing here is compared across runs
    model = PocoModel("tiny").eval()
    model.projection.fast_layout = layout
    points = torch.rand(1, 3, 256, generator=torch.Generator().manual_seed(1))
    queries = torch.rand(1, 3, 40, generator=torch.Generator().manual_seed(2))
    found = _recorded(task_cost, model, points, queries, fast)
    calls = [(call.kind, call.size) for call in found.network["refine_views"]]
    assert calls == [("encode", 256), ("decode", 40)]
    assert found.seconds["refine_views"]["network"] > 0.0
    flops = task_cost.network_flops(found)["refine_views"]
    assert flops > 0
    # The same recording made by the other execution counts the same FLOPs.
    assert flops == task_cost.network_flops(_recorded(task_cost, model, points, queries, not fast))["refine_views"]


def _recorded(task_cost: ModuleType, model: Any, points: Any, queries: Any, fast: bool) -> Any:
    """The hooks' recording of one encode and decode, by the fast or the original execution."""
    import torch

    clock = task_cost.RecordingClock()
    with task_cost.recording(clock) as found, clock.step("refine_views"), torch.no_grad():
        tables = model.tables(points, torch.Generator().manual_seed(3))
        knn = model.query_knn(points, queries)
        latents = model.encode(points, model.features(points), tables)
        if fast:
            model.decode_inference(latents, points, queries, knn, 16)
        else:
            model.decode(latents, points, queries, knn, chunk_size=16)
    return found
