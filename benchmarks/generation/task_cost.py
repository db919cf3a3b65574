"""Benchmark: the cost model of one task, step by step, against what the same work costs at best.

    python -m benchmarks.generation.task_cost                         # the built-ins below + every shared mesh
    python -m benchmarks.generation.task_cost --subset                # the built-ins + a representative subset
    python -m benchmarks.generation.task_cost --objects builtin:capsule ../shared/meshes/cow.obj
    python -m benchmarks.generation.task_cost --configs before.toml after.toml  # two configs, one invocation
    python -m benchmarks.generation.task_cost --original --subset     # before/after issue 24's refinement speed-ups
    python -m benchmarks.generation.task_cost --render before.json after.json   # two saved runs, compared
    python -m benchmarks.generation.task_cost --subset --paths worker shared     # the refiner in the task and shared
    python -m benchmarks.generation.task_cost --subset --device cuda --paths worker shared --refiner-batch 16

For every object it runs one task (rotation 0) in this process exactly as a worker does
(`datagen.engine.worker.execute_task`: prepare, `run_task` with its `StepClock`, shard payload, write
to a scratch dataset) and reports each step of `schemas.index.TASK_STEPS` in CPU-seconds (process CPU
time, single-threaded BLAS and torch as in a worker), its share of the task, and a FLOOR: what the
same work costs by the fastest known means on this machine, measured on the same inputs:

- prepare: loading the mesh alone (trimesh's parser, or the built-in's generator).
- ground_truth: drawing the same random numbers (the multinomial face counts and 2 uniforms per sample).
- imaging: Embree's raw cast of the same ray batches (`EmbreeScene.run(..., output=0)`, no
  post-processing: no float64 refinement, no keys).
- refine_views / refine_cases: the POCO network's FLOPs (`torch.utils.flop_counter.FlopCounterMode`
  on the same inputs) at this machine's float32 matmul rate on one thread, plus scipy's cKDTree
  (workers=1) on the same kNN queries (the encoder's tables and the decoder's query neighbours).
- cases / coverage: one `np.unique` over the same concatenated key sets (their masks' core).
- labels: HiGHS alone on each case's reduced instance (its undominated rows, forced views taken),
  one MIP for the minimum cover: no tie-break, no listing of the minimum covers.
- write: one write (and fsync) of the same number of bytes to one file.

The table (step, CPU-s, share, floor, ratio) is printed and written to benchmarks/generation/results/task-cost.md
with the machine's state (load, cores, measured GFLOP/s). ``--configs`` runs every config on the same
objects in one invocation and adds a comparison table (a before/after of a refiner change: two configs,
or `measure_task` with two refiners from Python). Every run also saves its raw results as JSON (beside
the report, or ``--save-json``); ``--render A.json B.json`` reports saved runs as one comparison, e.g.
the same objects before and after a change of the code. ``--original`` measures each config twice,
first with the POCO refiner's original execution (``PocoRefiner(fast=False)``: the code before issue
24's speed-ups, same outputs) and then as a worker runs it, task by task in turns so both see the
same machine. Floors are the best of ``--floor-repeats``
runs (one when a run takes over `LONG_FLOOR` seconds).

``--paths`` measures each config on each path a refiner's network can take (issue 41): ``worker`` (in
the task's process, as every worker without ``--shared-refiner``) and ``shared`` (a node's shared
refiner host, here in a second process fed through a pipe, as a Ray actor is: the task's steps keep
its own CPU, and ``refiner_host`` / ``refiner_queue`` say what the host spent and what the task waited
on it). ``--device cuda`` puts the network on the GPU on either path; ``--refiner-batch`` is the host's
jobs per encoder call. On the shared path the network's FLOPs and neighbour searches run in the host,
so the refine steps have no floor there.
"""

from __future__ import annotations

import os

from benchmarks import common
from benchmarks.common import REPO_ROOT, add_report_options, check_report, limit_threads

limit_threads()

import argparse  # noqa: E402
import contextlib  # noqa: E402
import dataclasses  # noqa: E402
import importlib.metadata  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterator, Sequence  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402

from datagen.config_io import load_config  # noqa: E402
from datagen.engine.shard_payload import task_payload  # noqa: E402
from datagen.pipeline import raycast  # noqa: E402
from datagen.pipeline.keys import key_centres, unpack_keys  # noqa: E402
from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import load_mesh, prepare_object  # noqa: E402
from datagen.pipeline.objects.spec import ObjectSpec  # noqa: E402
from datagen.pipeline.refine import make_refiner  # noqa: E402
from datagen.pipeline.refine.base import Refiner  # noqa: E402
from datagen.pipeline.refine.poco.network_jobs import NetworkJob, NetworkReply, RemoteNetwork  # noqa: E402
from datagen.pipeline.refine.poco.refiner import PocoRefiner  # noqa: E402
from datagen.pipeline.setcover import cover_model, highs_solver, minimal_masks, popcount  # noqa: E402
from datagen.pipeline.step_timing import StepClock  # noqa: E402
from datagen.pipeline.task import TaskResult, run_task  # noqa: E402
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from datagen.shapes import builtins  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402
from schemas.index import TASK_STEPS  # noqa: E402
from storage import open_location, write_task  # noqa: E402

SHARED_MESHES = Path(os.environ.get("DATAGEN_SHARED_MESHES", common.SHARED_MESHES))
MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb"}
RESULTS = Path(__file__).resolve().parent / "results" / "task-cost.md"
BUILTINS = ("capsule", "mug", "torus_knot_3_5")
"""A few built-ins: a simple solid, one with a handle (occlusion), the hardest labels."""
SUBSET = ("stanford-bunny.obj", "cow.obj", "fandisk.obj", "horse.ply", "teapot.obj", "ADIS16480.STL")
"""Representative shared meshes (``--subset``): scanned, thin parts, CAD, open, many small features."""
FLOOR_NOTES = {
    "prepare": "trimesh's parse (or the built-in's generator) alone; the rest is merging, cleaning, normalising",
    "ground_truth": "the random draws alone; the rest is per-sample keying and the first sample per key",
    "imaging": "Embree's cast alone; the rest is ray set-up, float64 refinement, keys, same-key test",
    "refine_views": "network FLOPs at the matmul rate + cKDTree; the rest is gathers, softmax, band and "
    "free-space queries, sampling",
    "cases": "one sort of the visible keys; the rest is the greedy trajectories",
    "refine_cases": "as refine_views, on the multi-view cases",
    "coverage": "one sort of the refined keys; the rest is the masks",
    "labels": "one HiGHS MIP per reduced case; the pipeline adds the tie-break and lists every minimum cover",
    "next_view": "one sort of the visible keys (the gains' masks) and each ray's end cell; the rest is the ray "
    "walk through the grid and the per-case counts",
    "write": "one write + fsync of the same bytes; the rest is Zarr's chunking/compression and Parquet",
}


# ---------------------------------------------------------------------------------------------------------
# recording what a task does (the inputs the floors are measured on)
# ---------------------------------------------------------------------------------------------------------


class RecordingClock(StepClock):
    """A `StepClock` that knows which step is running (so recorded inputs are attributed to it)."""

    def __init__(self) -> None:
        super().__init__()
        self.current = ""

    @contextlib.contextmanager
    def step(self, name: str) -> Iterator[None]:
        previous, self.current = self.current, name
        try:
            with super().step(name):
                yield
        finally:
            self.current = previous


@dataclass
class KnnCall:
    source: npt.NDArray[np.float64]
    """(N, 3)"""
    target: npt.NDArray[np.float64]
    """(M, 3)"""
    k: int


@dataclass
class NetworkCall:
    kind: str
    """'encode' or 'decode'."""
    size: int
    """Input points (encode) or queries (decode)."""


@dataclass
class Recording:
    """What the hooks saw, by step."""

    rays: dict[str, list[tuple[Any, npt.NDArray[np.float32], npt.NDArray[np.float32]]]] = field(default_factory=dict)
    """step -> (scene, origins32, directions32) of every Embree cast."""
    knn: dict[str, list[KnnCall]] = field(default_factory=dict)
    network: dict[str, list[NetworkCall]] = field(default_factory=dict)
    seconds: dict[str, dict[str, float]] = field(default_factory=dict)
    """step -> part ('knn', 'network') -> process CPU seconds the pipeline spent in it."""
    model: Any = None
    first_encode: tuple[tuple[Any, ...], dict[str, Any]] | None = None
    first_decode: tuple[tuple[Any, ...], dict[str, Any]] | None = None
    highs_limited: int = 0
    """Reduced instances on which the labels floor's HiGHS stopped at its time limit."""


@contextlib.contextmanager
def recording(clock: RecordingClock) -> Iterator[Recording]:
    """Hooks on Embree's cast, the POCO kNN and the network's encode/decode while inside; they copy
    the (small) inputs the floors need and attribute them to ``clock``'s current step."""
    found = Recording()
    patches: list[tuple[Any, str, Any]] = []

    def timed_call(part: str, function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        started = time.process_time()
        try:
            return function(*args, **kwargs)
        finally:
            parts = found.seconds.setdefault(clock.current, {})
            parts[part] = parts.get(part, 0.0) + time.process_time() - started

    original_cast = raycast.RayCaster.cast

    def cast(self: raycast.RayCaster, origin: Any, directions: Any, max_range: float, directions32: Any = None) -> Any:
        rays = np.ascontiguousarray(directions, dtype=np.float32)
        origins = np.broadcast_to(np.asarray(origin, dtype=np.float32), rays.shape).copy()
        found.rays.setdefault(clock.current, []).append((self._scene, origins, rays))
        return original_cast(self, origin, directions, max_range, directions32)

    patches.append((raycast.RayCaster, "cast", cast))
    spatial = sys.modules.get("datagen.pipeline.refine.poco.spatial")
    network = sys.modules.get("datagen.pipeline.refine.poco.network")
    if spatial is not None and hasattr(spatial, "knn"):
        original_knn = spatial.knn

        def knn(source: Any, target: Any, k: int, **kwargs: Any) -> Any:
            if getattr(source, "ndim", 0) != 3:  # unbatched: it calls this hook again with a batch of one
                return original_knn(source, target, k, **kwargs)
            for b in range(source.shape[0]):
                found.knn.setdefault(clock.current, []).append(
                    KnnCall(
                        source[b].detach().cpu().double().T.numpy().copy(),
                        target[b].detach().cpu().double().T.numpy().copy(),
                        int(k),
                    )
                )
            return timed_call("knn", original_knn, source, target, k, **kwargs)

        patches.append((spatial, "knn", knn))
    if network is not None and hasattr(network, "PocoModel"):
        model_class = network.PocoModel
        original_encode, original_decode = model_class.encode, model_class.decode

        # encode(points, features, tables) and decode(latents, points, queries, knn, ...): where a call
        # does not look like that (the refiner changed), it is timed but not counted.
        def encode(self: Any, *args: Any, **kwargs: Any) -> Any:
            found.model = self
            with contextlib.suppress(IndexError, AttributeError, TypeError):
                found.network.setdefault(clock.current, []).append(NetworkCall("encode", int(args[0].shape[-1])))
                if found.first_encode is None:
                    found.first_encode = (_detached(args), dict(kwargs))
            return timed_call("network", original_encode, self, *args, **kwargs)

        def decoder_hook(original: Callable[..., Any], replayable: Callable[..., Any]) -> Callable[..., Any]:
            """A decoder entry point (queries its third argument) timed as network; ``replayable``
            turns its arguments into a `decode` call for the FLOP count."""

            def decode(self: Any, *args: Any, **kwargs: Any) -> Any:
                if decoding:  # decode_inference falling back to decode: counted once, by the outer call
                    return original(self, *args, **kwargs)
                found.model = self
                with contextlib.suppress(IndexError, AttributeError, TypeError):
                    found.network.setdefault(clock.current, []).append(NetworkCall("decode", int(args[2].shape[-1])))
                    if found.first_decode is None and args[2].shape[-1] > 1:
                        found.first_decode = replayable(args, kwargs)
                decoding.append(True)
                try:
                    return timed_call("network", original, self, *args, **kwargs)
                finally:
                    decoding.pop()

            return decode

        decoding: list[bool] = []

        patches += [
            (model_class, "encode", encode),
            (model_class, "decode", decoder_hook(original_decode, lambda a, k: (_detached(a), dict(k)))),
        ]
        if hasattr(model_class, "decode_inference"):
            # The fast execution's decoder, decode_inference(latents, points, queries, knn, chunk):
            # the same values as decode, so its FLOPs are counted by replaying decode on its inputs.
            inference = decoder_hook(model_class.decode_inference, lambda a, _: (_detached(a[:4]), {}))
            patches.append((model_class, "decode_inference", inference))
    # The rest of a refinement, where the poco refiner still has these: its queries (band minus
    # observed minus sensor-empty keys) and the encoder's quantized sampling.
    refiner_module = sys.modules.get("datagen.pipeline.refine.poco.refiner")
    for owner, name, part in ((refiner_module, "query_keys", "queries"), (spatial, "quantized_sampling", "sampling")):
        if owner is not None and callable(getattr(owner, name, None)):
            patches.append((owner, name, _timed_part(timed_call, part, getattr(owner, name))))
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
    try:
        for owner, name, replacement in patches:
            setattr(owner, name, replacement)
        yield found
    finally:
        for owner, name, original in saved:
            setattr(owner, name, original)


def _timed_part(timed_call: Callable[..., Any], part: str, function: Callable[..., Any]) -> Callable[..., Any]:
    def timed(*args: Any, **kwargs: Any) -> Any:
        return timed_call(part, function, *args, **kwargs)

    return timed


def _detached(args: Sequence[Any]) -> tuple[Any, ...]:
    def copy(value: Any) -> Any:
        if hasattr(value, "detach"):
            return value.detach().clone()
        if isinstance(value, dict):
            return {k: copy(v) for k, v in value.items()}
        return value

    return tuple(copy(a) for a in args)


# ---------------------------------------------------------------------------------------------------------
# floors: each a function of the same inputs, returning CPU-seconds (best of ``repeats``)
# ---------------------------------------------------------------------------------------------------------


LONG_FLOOR = 2.0
"""CPU-seconds after which a floor is not repeated (a long run is steady, and HiGHS's MIPs on the
hardest built-in take minutes)."""


def best_cpu(action: Callable[[], object], repeats: int = 3) -> float:
    """The least process CPU time of ``repeats`` runs of ``action`` (one run when it takes `LONG_FLOOR`)."""
    best = float("inf")
    for _ in range(max(1, repeats)):
        started = time.process_time()
        action()
        best = min(best, time.process_time() - started)
        if best >= LONG_FLOOR:
            break
    return best


def matmul_gflops(size: int = 2048, repeats: int = 5) -> float:
    """float32 GFLOP/s of one (size x size) @ (size x size) torch matmul on one thread (the best run)."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        generator = torch.Generator().manual_seed(0)
        a = torch.rand((size, size), generator=generator)
        b = torch.rand((size, size), generator=generator)
        torch.mm(a, b)  # warm-up
        seconds = best_cpu(lambda: torch.mm(a, b), repeats)
    finally:
        torch.set_num_threads(previous)
    return 2.0 * size**3 / max(seconds, 1e-9) / 1e9


def embree_floor(
    batches: Sequence[tuple[Any, npt.NDArray[np.float32], npt.NDArray[np.float32]]], repeats: int = 3
) -> float:
    """Embree's raw first-hit cast (``output=0``: the hit triangle only) of the same ray batches."""

    def cast_all() -> None:
        for scene, origins, directions in batches:
            scene.run(origins, directions, output=0)

    return best_cpu(cast_all, repeats) if batches else 0.0


def knn_floor(calls: Sequence[KnnCall], repeats: int = 3) -> float:
    """scipy's cKDTree (build and query, workers=1) on the same kNN queries."""
    from scipy.spatial import cKDTree

    def query_all() -> None:
        for call in calls:
            k = min(call.k, call.source.shape[0])
            if call.target.shape[0] and k:
                cKDTree(call.source).query(call.target, k=k, workers=1)

    return best_cpu(query_all, repeats) if calls else 0.0


def count_flops(function: Callable[[], object]) -> int:
    """FLOPs torch's `FlopCounterMode` counts for one call (matmuls and convolutions), without gradients."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        function()
    return int(counter.get_total_flops())


def network_flops(found: Recording) -> dict[str, int]:
    """FLOPs of every recorded encode and decode call, by step.

    The first encode and decode calls are replayed under `FlopCounterMode`; an encode's FLOPs scale
    with its points (the preset fixes them), a decode's are a + b * queries (per-point terms once,
    then the same work per query), so the first decode replayed at two query counts gives a and b.
    """
    if found.model is None or found.first_encode is None:
        return {}
    model = found.model
    args, kwargs = found.first_encode
    encode_points = int(args[0].shape[-1])
    encode = count_flops(lambda: model.encode(*args, **kwargs))
    per_query = fixed = 0.0
    if found.first_decode is not None:
        args, kwargs = found.first_decode
        m = int(args[2].shape[-1])
        half = max(1, m // 2)

        def decode(count: int) -> int:
            sliced = (args[0], args[1], args[2][..., :count], args[3][:, :count], *args[4:])
            return count_flops(lambda: model.decode(*sliced, **kwargs))

        full, part = decode(m), decode(half)
        per_query = (full - part) / max(1, m - half)
        fixed = max(0.0, full - per_query * m)
    totals: dict[str, int] = {}
    for step, calls in found.network.items():
        total = 0.0
        for call in calls:
            if call.kind == "encode":
                total += encode * call.size / max(1, encode_points)
            else:
                total += fixed + per_query * call.size
        totals[step] = round(total)
    return totals


def ground_truth_floor(
    vertices: npt.NDArray[np.float64], faces: npt.NDArray[np.int64], config: GenerationConfig, repeats: int = 3
) -> float:
    """The random draws of P_gt's sampling alone: face counts (multinomial by area) and 2 uniforms per sample."""
    triangles = vertices[faces]
    areas = 0.5 * np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    total = float(areas.sum())
    count = max(1, int(np.ceil(total / config.voxel_size**2 * config.gt_density)))
    weights = areas / total

    def draw() -> None:
        rng = np.random.default_rng(0)
        rng.multinomial(count, weights)
        rng.random((2, count))

    return best_cpu(draw, repeats)


def unique_floor(key_sets: Sequence[npt.NDArray[np.int64]], repeats: int = 3) -> float:
    """One `np.unique` of the concatenated key sets."""
    everything = np.concatenate(list(key_sets)) if key_sets else np.empty(0, dtype=np.int64)
    return best_cpu(lambda: np.unique(everything), repeats)


def next_view_floor(result: TaskResult, config: GenerationConfig, repeats: int = 3) -> float:
    """One `np.unique` of the visible key sets (the gains' view masks) and the grid cell of every visible
    key centre (where each ray ends): what the next-view labels cannot do without."""
    everything = np.concatenate(list(result.sets.visible)) if result.sets.visible else np.empty(0, dtype=np.int64)
    centres = key_centres(unpack_keys(everything), config.voxel_size, config.grid_offset)
    cell = result.grids.frame.cell if result.grids is not None else config.voxel_size
    return best_cpu(lambda: (np.unique(everything), np.floor(centres / cell).astype(np.int64)), repeats)


def reduced_instances(minimal: npt.NDArray[np.uint64], cases: Sequence[int]) -> list[npt.NDArray[np.uint64]]:
    """Each case's reduced rows: the undominated masks that miss it, rows hit by forced views removed."""
    instances = []
    for case in cases:
        rows = minimal_masks(minimal[(minimal & np.uint64(case)) == 0])
        if rows.size == 0:
            continue
        forced = 0
        for single in rows[popcount(rows) == 1].tolist():
            forced |= int(single)
        if forced:
            rows = rows[(rows & np.uint64(forced)) == 0]
        if rows.size:
            instances.append(rows)
    return instances


HIGHS_FLOOR_LIMIT = 1.0
"""Seconds HiGHS may spend on one reduced instance in the labels floor. Past it the floor is a lower
bound of HiGHS's time (already more than the pipeline's search takes: on the hardest built-in
HiGHS's branch and bound takes seconds per case where the search takes a fraction of one)."""


def highs_floor(
    instances: Sequence[npt.NDArray[np.uint64]], time_limit: float = HIGHS_FLOOR_LIMIT, repeats: int = 3
) -> tuple[float, int]:
    """HiGHS alone (pass the model, solve) on each reduced instance: one minimum-cover MIP each.
    Returns the CPU-seconds and how many instances stopped at ``time_limit``."""
    import highspy

    models = []
    for rows in instances:
        union = int(np.bitwise_or.reduce(rows))
        candidates = [v for v in range(64) if union >> v & 1]
        models.append(cover_model(rows, candidates, [1.0] * len(candidates)))
    limited = [0]

    def solve_all() -> None:
        limited[0] = 0
        for lp in models:
            solver = highs_solver(1, time_limit)
            solver.passModel(lp)
            solver.run()
            limited[0] += solver.getModelStatus() == highspy.HighsModelStatus.kTimeLimit

    seconds = best_cpu(solve_all, repeats) if models else 0.0
    return seconds, limited[0]


def write_floor(size: int, folder: Path, repeats: int = 3) -> float:
    """One write and fsync of ``size`` bytes to one new file in ``folder``."""
    data = np.random.default_rng(0).integers(0, 256, size=size, dtype=np.uint8).tobytes()
    target = folder / "floor.bin"

    def write() -> None:
        with open(target, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        target.unlink()

    return best_cpu(write, repeats)


def forget_builtins() -> None:
    """Drop the built-in meshes this process built (`datagen.shapes.builtins` builds each once)."""
    cached = getattr(builtins, "_build", None)
    if cached is not None and hasattr(cached, "cache_clear"):
        cached.cache_clear()


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


# ---------------------------------------------------------------------------------------------------------
# one task
# ---------------------------------------------------------------------------------------------------------


@dataclass
class TaskCost:
    """One task's steps: CPU and wall seconds, and the floor of each (CPU-seconds; None: no floor)."""

    object_name: str
    faces: int
    samples: int
    cpu: dict[str, float]
    wall: dict[str, float]
    floor: dict[str, float | None]
    total_cpu: float
    details: dict[str, dict[str, float]] = field(default_factory=dict)
    """step -> what its floor was measured on and, for the refine steps, where its time went:
    ``rays``; ``knn_cpu``/``network_cpu`` (the pipeline's own), ``knn_floor``, ``gflop``,
    ``flop_floor``; ``instances``; ``bytes``."""


def object_specs(sources: Sequence[str]) -> list[ObjectSpec]:
    """ObjectSpecs of mesh paths and ``builtin:NAME`` lines (through an objects file, as a job reads them)."""
    with tempfile.TemporaryDirectory() as folder:
        listing = Path(folder) / "objects.txt"
        listing.write_text(
            "\n".join(str(Path(s).resolve()) if not s.startswith("builtin:") else s for s in sources) + "\n"
        )
        found = read_objects_file(listing)
        if found.errors:
            raise SystemExit("\n".join(str(e) for e in found.errors))
        return found.objects


def measure_task(
    spec: ObjectSpec,
    config: GenerationConfig,
    *,
    rotation: int = 0,
    refiner: Refiner | None = None,
    gflops: float | None = None,
    floor_repeats: int = 3,
) -> TaskCost:
    """One task of ``spec`` as a worker runs it (fresh preparation, scratch dataset), every step's
    CPU and wall seconds, and the floors. ``refiner`` defaults to the config's (its loading is not
    timed: a worker loads it once); ``gflops`` to a fresh `matmul_gflops`."""
    refiner = make_refiner(config) if refiner is None else refiner
    view_space = build_view_space(config.view_space)
    clock = RecordingClock()
    with tempfile.TemporaryDirectory() as scratch, recording(clock) as found:
        with single_threaded_blas(), fixed_torch_threads():
            forget_builtins()  # a worker builds a built-in once per process: count that build
            with clock.step("prepare"):
                prepared = prepare_object(spec, config)
            before = refiner.network.steps() if isinstance(refiner, PocoRefiner) else {}
            result = run_task(prepared, rotation, config, view_space, refiner, clock=clock)
            after = refiner.network.steps() if isinstance(refiner, PocoRefiner) else {}
        for name, (cpu, wall) in after.items():  # a shared host's part, as `execute_task` adds it
            cpu_before, wall_before = before.get(name, (0.0, 0.0))
            clock.add(name, cpu - cpu_before, wall - wall_before)
        with clock.step("write"):
            payload = task_payload(result, config)
            write_task(open_location(scratch), payload, "bench")
        written = folder_bytes(Path(scratch))
        timings = clock.timings()
        vertices = prepared.task_vertices(rotation, config.rotations)
        floors = _floors(spec, vertices, prepared.faces, config, result, found, floor_repeats)
        floors["write"] = write_floor(written, Path(scratch), floor_repeats)
    details: dict[str, dict[str, float]] = {
        "imaging": {"rays": float(sum(len(rays) for _, _, rays in found.rays.get("imaging", [])))},
        "labels": {
            "instances": float(len(reduced_instances(result.cover_rows, result.cases))),
            "highs_limited": float(found.highs_limited),
        },
        "write": {"bytes": float(written)},
    }
    try:
        flops = network_flops(found)
    except Exception as error:  # a refiner whose network no longer replays this way: no FLOP floor
        print(f"warning: FLOPs not counted ({type(error).__name__}: {error})", file=sys.stderr)
        flops = {}
    rate = (gflops if gflops is not None else matmul_gflops()) * 1e9 if flops else 0.0
    for step in ("refine_views", "refine_cases"):
        knn_seconds = knn_floor(found.knn.get(step, []), floor_repeats)
        flop_seconds = flops.get(step, 0) / rate if rate else 0.0
        floors[step] = knn_seconds + flop_seconds  # 0 without a network: no floor to compare with
        spent = found.seconds.get(step, {})
        details[step] = {
            "knn_cpu": spent.get("knn", 0.0),
            "network_cpu": spent.get("network", 0.0),
            "queries_cpu": spent.get("queries", 0.0),
            "sampling_cpu": spent.get("sampling", 0.0),
            "knn_floor": knn_seconds,
            "gflop": flops.get(step, 0) / 1e9,
            "flop_floor": flop_seconds,
        }
    return TaskCost(
        object_name=spec.name,
        faces=int(prepared.faces.shape[0]),
        samples=len(result.samples),
        cpu={s: t.cpu for s, t in timings.steps.items()},
        wall={s: t.wall for s, t in timings.steps.items()},
        floor=floors,
        total_cpu=timings.total.cpu,
        details=details,
    )


def _floors(
    spec: ObjectSpec,
    vertices: npt.NDArray[np.float64],
    faces: npt.NDArray[np.int64],
    config: GenerationConfig,
    result: TaskResult,
    found: Recording,
    repeats: int = 3,
) -> dict[str, float | None]:
    floors: dict[str, float | None] = {}
    floors["prepare"] = best_cpu(lambda: (forget_builtins(), load_mesh(spec)), repeats)
    floors["ground_truth"] = ground_truth_floor(vertices, faces, config, repeats)
    floors["imaging"] = embree_floor(found.rays.get("imaging", []), repeats)
    floors["cases"] = unique_floor(result.sets.visible, repeats)
    floors["coverage"] = unique_floor(result.sets.refined, repeats)
    instances = reduced_instances(result.cover_rows, result.cases)
    floors["labels"], found.highs_limited = highs_floor(instances, repeats=repeats)
    floors["next_view"] = next_view_floor(result, config, repeats)
    return floors


# ---------------------------------------------------------------------------------------------------------
# tables
# ---------------------------------------------------------------------------------------------------------


@dataclass
class StepRow:
    step: str
    cpu: float
    wall: float
    share: float
    floor: float | None
    ratio: float | None


def step_rows(costs: Sequence[TaskCost]) -> list[StepRow]:
    """Per step, summed over the tasks: CPU-s, wall s, share of the steps' CPU, floor and ratio; the
    steps of `TASK_STEPS` first, then any others (a shared host's ``refiner_host``, ``refiner_queue``)."""
    steps = [s for s in TASK_STEPS if any(s in c.cpu for c in costs)]
    steps += sorted({s for c in costs for s in c.cpu} - set(steps))
    total = sum(sum(c.cpu.values()) for c in costs)
    rows = []
    for step in steps:
        cpu = sum(c.cpu.get(step, 0.0) for c in costs)
        floors = [c.floor.get(step) for c in costs]
        floor = None if any(f is None for f in floors) else float(sum(f for f in floors if f is not None))
        ratio = cpu / floor if floor else None
        rows.append(
            StepRow(step, cpu, sum(c.wall.get(step, 0.0) for c in costs), cpu / total if total else 0.0, floor, ratio)
        )
    return rows


def _seconds(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.3g}" if value >= 0.001 else f"{value:.1e}"


def table_lines(rows: Sequence[StepRow]) -> list[str]:
    """The step table as Markdown."""
    lines = ["| step | CPU-s | share | wall s | floor CPU-s | ratio to floor |", "|---|---:|---:|---:|---:|---:|"]
    for row in rows:
        ratio = "-" if row.ratio is None else f"{row.ratio:.1f}x"
        lines.append(
            f"| {row.step} | {_seconds(row.cpu)} | {row.share:.1%} | {_seconds(row.wall)} | "
            f"{_seconds(row.floor)} | {ratio} |"
        )
    cpu = sum(r.cpu for r in rows)
    # The pipeline's own way is a known means too: a step faster than its floor counts at its own time.
    floor = sum(min(r.floor, r.cpu) if r.floor else r.cpu for r in rows)
    lines.append(
        f"| **all steps** | {_seconds(cpu)} | 100% | {_seconds(sum(r.wall for r in rows))} | "
        f"{_seconds(floor)} | {cpu / floor:.1f}x |"
        if floor
        else ""
    )
    return [line for line in lines if line]


def object_lines(costs: Sequence[TaskCost]) -> list[str]:
    """One row per object: faces, samples, CPU-s, the three costliest steps."""
    lines = [
        "| object | faces | samples | task CPU-s | steps CPU-s | costliest steps (CPU-s) |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for c in costs:
        top = sorted(c.cpu.items(), key=lambda item: -item[1])[:3]
        described = ", ".join(f"{s} {v:.2f}" for s, v in top)
        lines.append(
            f"| {c.object_name} | {c.faces} | {c.samples} | {c.total_cpu:.2f} | {sum(c.cpu.values()):.2f} | "
            f"{described} |"
        )
    return lines


def refine_lines(costs: Sequence[TaskCost]) -> list[str]:
    """Where the refine steps' CPU went (summed over the tasks): the pipeline's own kNN and network
    time against their floors, the queries (band, sensor-empty keys) and the encoder's sampling, and
    the rest (inputs, tensors, thresholds)."""
    lines = [
        "| step | CPU-s | kNN CPU-s | kNN floor | network CPU-s | GFLOP | FLOP floor | queries CPU-s | "
        "sampling CPU-s | rest CPU-s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for step in ("refine_views", "refine_cases"):
        if not any(step in c.details for c in costs):
            continue

        def total(name: str, step: str = step) -> float:
            return sum(c.details.get(step, {}).get(name, 0.0) for c in costs)

        cpu = sum(c.cpu.get(step, 0.0) for c in costs)
        knn, network = total("knn_cpu"), total("network_cpu")
        queries, sampling = total("queries_cpu"), total("sampling_cpu")
        lines.append(
            f"| {step} | {_seconds(cpu)} | {_seconds(knn)} | {_seconds(total('knn_floor'))} | {_seconds(network)} | "
            f"{total('gflop'):.1f} | {_seconds(total('flop_floor'))} | {_seconds(queries)} | {_seconds(sampling)} | "
            f"{_seconds(cpu - knn - network - queries - sampling)} |"
        )
    return lines


def input_lines(costs: Sequence[TaskCost]) -> list[str]:
    """What the floors were measured on, summed over the tasks."""

    def total(step: str, name: str) -> float:
        return sum(c.details.get(step, {}).get(name, 0.0) for c in costs)

    return [
        f"- imaging: {total('imaging', 'rays'):,.0f} rays cast in all",
        f"- labels: {total('labels', 'instances'):,.0f} reduced instances (cases whose label is not forced or empty); "
        f"HiGHS stopped at its {HIGHS_FLOOR_LIMIT:g} s limit on {total('labels', 'highs_limited'):,.0f} of them "
        "(the floor is then a lower bound of HiGHS's time)",
        f"- write: {total('write', 'bytes') / 2**20:.2f} MiB written in all (shard groups and index fragments)",
    ]


def comparison_lines(labels: Sequence[str], results: Sequence[Sequence[TaskCost]]) -> list[str]:
    """CPU-s per step of every config, and each config's ratio to the first."""
    per = [{r.step: r.cpu for r in step_rows(costs)} for costs in results]
    header = (
        "| step | "
        + " | ".join(f"{label} CPU-s" for label in labels)
        + " | "
        + " | ".join(f"{label} / {labels[0]}" for label in labels[1:])
        + " |"
    )
    lines = [header, "|---|" + "---:|" * (2 * len(labels) - 1)]
    steps = [s for s in TASK_STEPS if any(s in p for p in per)]
    for step in [*steps, "all steps"]:
        values = [sum(p.values()) if step == "all steps" else p.get(step, 0.0) for p in per]
        ratios = [f"{v / values[0]:.2f}x" if values[0] else "-" for v in values[1:]]
        lines.append(
            f"| {step} | "
            + " | ".join(_seconds(v) for v in values)
            + (" | " + " | ".join(ratios) if ratios else "")
            + " |"
        )
    return lines


def slow_steps(rows: Sequence[StepRow], factor: float = 3.0) -> list[str]:
    """Steps above ``factor`` times their floor, each with what the floor leaves out."""
    return [
        f"- **{r.step}** {r.ratio:.1f}x its floor: {FLOOR_NOTES.get(r.step, '')}"
        for r in rows
        if r.ratio is not None and r.ratio > factor
    ]


# ---------------------------------------------------------------------------------------------------------
# the machine
# ---------------------------------------------------------------------------------------------------------


def loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def machine_busy_seconds() -> float:
    """Busy CPU seconds of the whole machine since boot (/proc/stat), 0 where it cannot be read."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    except OSError:
        return 0.0
    user, nice, system, _idle, _iowait, irq, softirq, steal = (fields + [0] * 8)[:8]
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_state() -> str:
    """The checkout's commit, and whether its tracked files differ from it."""
    import subprocess

    def git(*args: str) -> str:
        done = subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, check=False)
        return done.stdout.strip()

    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    return f"{commit} (with uncommitted changes)" if git("status", "--porcelain", "--untracked-files=no") else commit


def versions() -> str:
    import scipy
    import trimesh

    found = [
        f"python {platform.python_version()}",
        f"numpy {np.__version__}",
        f"scipy {scipy.__version__}",
        f"trimesh {trimesh.__version__}",
    ]
    with contextlib.suppress(ImportError):
        import torch

        found.append(f"torch {torch.__version__}")
    found.append(f"highspy {importlib.metadata.version('highspy')}")
    return ", ".join(found)


# ---------------------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------------------


def default_sources(subset: bool) -> list[str]:
    meshes = (
        sorted(p for p in SHARED_MESHES.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
        if SHARED_MESHES.is_dir()
        else []
    )
    if subset:
        meshes = [p for p in meshes if p.name in SUBSET]
    return [f"builtin:{name}" for name in BUILTINS] + [str(p) for p in meshes]


@dataclass
class Run:
    """One invocation's results and the machine's state while it ran (saved with ``--save-json``)."""

    labels: list[str]
    configs: list[str]
    """Each label's config file ("" for the default config)."""
    results: list[list[TaskCost]]
    gflops: float
    started: str
    load_before: str
    load_after: str
    others: float
    """Cores other processes used on average while it ran."""
    wall: float
    machine: str
    """CPUs, versions and the datagen commit."""

    def to_json(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self)}

    @staticmethod
    def from_json(data: dict[str, Any]) -> Run:
        fields = {**data, "results": [[TaskCost(**cost) for cost in costs] for costs in data["results"]]}
        return Run(**fields)


def machine_line() -> str:
    return f"{os.cpu_count()} CPUs ({cpu_model()}); {versions()}; datagen at {git_state()}"


def merged(runs: Sequence[tuple[str, Run]]) -> Run:
    """Several saved runs as one, each config labelled with its file's name when there are several."""
    first = runs[0][1]
    if len(runs) == 1:
        return first
    labels = [f"{name}:{label}" if label == "default" else label for name, run in runs for label in run.labels]
    if len(set(labels)) < len(labels):
        labels = [f"{name}:{label}" for name, run in runs for label in run.labels]
    return dataclasses.replace(
        first,
        labels=labels,
        configs=[c for _, run in runs for c in run.configs],
        results=[costs for _, run in runs for costs in run.results],
    )


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument(
        "--objects", nargs="*", help="mesh paths and builtin:NAME (default: the built-ins and every shared mesh)"
    )
    parser.add_argument(
        "--subset", action="store_true", help=f"only the representative shared meshes ({', '.join(SUBSET)})"
    )
    parser.add_argument(
        "--configs", nargs="*", help="generation configs (TOML) to compare; default: the default config"
    )
    parser.add_argument(
        "--original",
        action="store_true",
        help="also measure each config with the POCO refiner's original execution (before issue 24), in turns",
    )
    parser.add_argument(
        "--paths",
        nargs="+",
        choices=PATHS,
        default=["worker"],
        help="where the refiner's network runs: in the task (worker) and/or a shared host (default: worker)",
    )
    parser.add_argument("--device", default="cpu", help="the refiner network's device: cpu or cuda (default cpu)")
    parser.add_argument("--refiner-batch", type=int, default=1, help="the shared host's jobs per encoder call")
    parser.add_argument("--rotation", type=int, default=0, help="the task's rotation (default 0)")
    parser.add_argument("--floor-repeats", type=int, default=3, help="runs per floor; the best counts (default 3)")
    parser.add_argument("--no-warm-up", action="store_true", help="skip the untimed warm-up task")
    add_report_options(parser, RESULTS, "Markdown report")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument(
        "--save-json", type=Path, help="save the raw results here (for --render; default: beside --out, as .json)"
    )
    parser.add_argument(
        "--render",
        nargs="+",
        type=Path,
        help="measure nothing: report saved runs (--save-json files), several as one comparison (before/after)",
    )
    return parser.parse_args(argv)


PATHS = ("worker", "shared")


def _serve_host(connection: Any, config_json: str, device: str, encoder_batch: int) -> None:
    """A shared refiner host in its own process (`datagen.engine.refiner_host.RefinerHost`, the
    body of the engine's actor), answering lists of jobs from a pipe until it reads None."""
    from datagen.engine.refiner_host import RefinerHost

    limit_threads()
    host = RefinerHost(config_json, device, encoder_batch)
    while (jobs := connection.recv()) is not None:
        try:
            connection.send(host.run(jobs))
        except Exception as error:  # the caller raises it
            connection.send(error)


@contextlib.contextmanager
def host_process(config: GenerationConfig, device: str, encoder_batch: int) -> Iterator[RemoteNetwork]:
    """A refiner host in a second process and a task-side network that calls it (one call at a time)."""
    context = multiprocessing.get_context("spawn")
    ours, theirs = context.Pipe()
    process = context.Process(target=_serve_host, args=(theirs, config.model_dump_json(), device, encoder_batch))
    process.start()
    lock = threading.Lock()

    def call(jobs: list[NetworkJob]) -> NetworkReply:
        with lock:
            ours.send(jobs)
            reply = ours.recv()
        if isinstance(reply, BaseException):
            raise reply
        return reply

    try:
        yield RemoteNetwork(call)
    finally:
        ours.send(None)
        process.join(timeout=30)
        if process.is_alive():
            process.kill()


def on_path(refiner: Refiner, network: RemoteNetwork) -> Refiner:
    """The same POCO refiner with its network on a shared host; any other refiner as it is."""
    if not isinstance(refiner, PocoRefiner):
        return refiner
    return PocoRefiner(
        refiner.config, refiner.model, refiner.weights_id, refiner.threshold, refiner.finetune_steps, network=network
    )


def original_execution(refiner: Refiner) -> Refiner:
    """The same POCO refiner running its original execution (``fast=False``: the code before issue
    24's speed-ups, bit-identical outputs); any other refiner as it is."""
    if not isinstance(refiner, PocoRefiner):
        return refiner
    return PocoRefiner(
        refiner.config,
        refiner.model,
        refiner.weights_id,
        refiner.threshold,
        refiner.finetune_steps,
        refiner.device,
        fast=False,
    )


def measure(args: argparse.Namespace) -> Run:
    sources = args.objects or default_sources(args.subset)
    specs = object_specs(sources)
    config_paths: list[Path | None] = [Path(p) for p in args.configs] if args.configs else [None]
    labels = [p.stem if p is not None else "default" for p in config_paths]
    started = datetime.now(UTC).isoformat(timespec="seconds")
    load_before = loadavg()
    busy_before, own_before, wall_before = machine_busy_seconds(), time.process_time(), time.perf_counter()
    gflops = matmul_gflops()
    print(
        f"{len(specs)} objects x {len(config_paths)} configs; float32 matmul on 1 thread: {gflops:.1f} GFLOP/s; "
        f"load {load_before}",
        flush=True,
    )
    variants: list[tuple[str, str, GenerationConfig, Refiner]] = []
    hosts = contextlib.ExitStack()
    for label, path in zip(labels, config_paths, strict=True):
        config = load_config(path)
        refiner = make_refiner(config, args.device)
        if args.original:
            variants.append((f"{label}-original", str(path or ""), config, original_execution(refiner)))
        if "worker" in args.paths:
            named = label if args.paths == ["worker"] and args.device == "cpu" else f"{label}-worker-{args.device}"
            variants.append((named, str(path or ""), config, refiner))
        if "shared" in args.paths:
            network = hosts.enter_context(host_process(config, args.device, args.refiner_batch))
            named = f"{label}-shared-{args.device}-batch{args.refiner_batch}"
            variants.append((named, str(path or ""), config, on_path(refiner, network)))
    if not args.no_warm_up:  # imports, torch's first kernels: not part of a task in a warm worker
        for _, _, config, refiner in variants:
            measure_task(object_specs(["builtin:capsule"])[0], config, refiner=refiner, gflops=gflops, floor_repeats=1)
    results: list[list[TaskCost]] = [[] for _ in variants]
    for spec in specs:  # object by object, every variant in turn: a change of load hits them alike
        for (label, _, config, refiner), costs in zip(variants, results, strict=True):
            cost = measure_task(
                spec, config, rotation=args.rotation, refiner=refiner, gflops=gflops, floor_repeats=args.floor_repeats
            )
            costs.append(cost)
            top = max(cost.cpu.items(), key=lambda item: item[1])
            print(
                f"[{label}] {spec.name}: {sum(cost.cpu.values()):.2f} CPU-s in steps ({top[0]} {top[1]:.2f}), "
                f"load {loadavg()}",
                flush=True,
            )
    hosts.close()
    wall = time.perf_counter() - wall_before
    others = (machine_busy_seconds() - busy_before - (time.process_time() - own_before)) / wall if wall else 0.0
    labels = [label for label, _, _, _ in variants]
    configs = [config for _, config, _, _ in variants]
    return Run(labels, configs, results, gflops, started, load_before, loadavg(), others, wall, machine_line())


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    if not args.no_write:
        check_report(argparse.ArgumentParser(prog="task_cost"), args.out, args.replace)
    if args.render:
        run = merged([(path.stem, Run.from_json(json.loads(path.read_text()))) for path in args.render])
    else:
        run = measure(args)
        saved = args.save_json or (None if args.no_write else args.out.with_suffix(".json"))
        if saved is not None:
            saved.parent.mkdir(parents=True, exist_ok=True)
            saved.write_text(json.dumps(run.to_json(), indent=1) + "\n")
    report = render(run)
    print("\n".join(report))
    if not args.no_write:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(report) + "\n")
        print(f"\nwritten to {args.out}")
    return 0


def render(run: Run) -> list[str]:
    lines = [
        "# Cost model of one task: each step against its floor",
        "",
        "Written by `python -m benchmarks.generation.task_cost` (see its docstring for what each floor measures).",
        "",
        "## Machine state",
        "",
        f"- {run.machine}",
        f"- float32 matmul on 1 thread (torch, 2048^2): **{run.gflops:.1f} GFLOP/s** (the POCO FLOP floor's rate)",
        f"- started {run.started}; load average {run.load_before} before, {run.load_after} after; other processes "
        f"used {run.others:.2f} cores on average during the {run.wall:.0f} s run (CPU-seconds below are this "
        "process's own)",
        "- one task per object, rotation 0, in one process as a worker runs it (single-threaded BLAS and torch; "
        "fresh preparation, which a worker does once per object and reuses for its other rotations)",
        "",
    ]
    for label, config, costs in zip(run.labels, run.configs, run.results, strict=True):
        rows = step_rows(costs)
        lines += [
            f"## {label}: {len(costs)} tasks" + (f" (config {config})" if config else " (default config)"),
            "",
            "CPU-seconds summed over the tasks; share of the steps' CPU; floor: the same work by the fastest "
            "known means.",
            "",
            *table_lines(rows),
            "",
            "The all-steps floor counts a step at its own CPU time where that is below its floor (labels: the "
            "pipeline's exact search beats HiGHS's branch and bound) or where it has none (a refiner without a "
            "network).",
            "",
            "Steps above 3x their floor, and what the floor leaves out:",
            "",
            *(slow_steps(rows) or ["- none"]),
            "",
            "Refinement, where its time goes (the pipeline's kNN and network forward, timed inside it):",
            "",
            *refine_lines(costs),
            "",
            "Inputs of the floors:",
            "",
            *input_lines(costs),
            "",
            "Per object:",
            "",
            *object_lines(costs),
            "",
        ]
    if len(run.results) > 1:
        lines += ["## Comparison", "", *comparison_lines(run.labels, run.results), ""]
    return lines


if __name__ == "__main__":
    sys.exit(main())
