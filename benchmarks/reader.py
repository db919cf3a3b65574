"""Benchmark: how fast a training job can read a dataset, next to a raw numpy memmap of the same clouds.

    python benchmarks/reader.py [--out DIR] [--rotations 3] [--processes 2] [--seconds 20] [--repeats 3]
                                [--profile]

The dataset holds every built-in of ``examples/builtin.txt`` (the default config, refiner poco, with
``rotations`` lowered from 8 to 3 to keep the build within a few minutes; printed). The build is
dominated by labelling torus_knot_3_5 (70-80 s a task on a loaded 2-core machine): 4 rotations took
about 5 minutes with 2 processes (3: an estimated 4). It is built into DIR, or
reused when DIR already holds a dataset (default: a fresh temporary folder, removed afterwards).

Measured in one run, each for about ``--seconds`` (or one pass over the dataset, whichever ends first):

- random ``ds[i]``: `storage.reader.Dataset.__getitem__` over uniformly random indices, on a freshly
  opened dataset (every key set of a sample as float32 centres, both masks);
- iter_shuffled: `Dataset.iter_shuffled` (shard-aware order, the same items as ``ds[i]``);
- DataLoader: `storage.torch.OSVPDataset` (2048 points), batch 32, 2 workers, `ShardShuffleSampler`;
  the rate over the epoch with worker start-up included, and after the first batch;
- memmap: the same samples' 2048-point float32 clouds (those the DataLoader returned) saved as one .npy,
  read back as random batches of 32 through ``np.load(mmap_mode='r')`` (sorted fancy indexing), plus
  the masks from an in-memory array;

and the ratio of each to the memmap rate. A diagnostic row repeats the DataLoader path with a sampler
mixing 1 shard at a time instead of the default 4.

The integrity checks readers make (each shard verified whole, every array and chunk file, the
first time a dataset reads from it; the finalised index checked against the commit records on
open) are measured against a baseline in the same run: the random, shuffled and DataLoader paths
run with ``Dataset._integrity_checks`` on and off (a private switch for this benchmark only),
alternately ``--repeats`` times, and the table shows the best rate of each and their ratio. The
checks' own time is shown too: ``ShardReader.verify`` per shard (and spread over its samples), and
the open-time index check. ``--profile`` adds a cProfile of a worker-equivalent loop
(``OSVPDataset.__getitem__`` in `ShardShuffleSampler` order plus default collation, one process),
with the default mix and with the diagnostic one.
Target: >= 5,000 samples/s for the DataLoader path.
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import cProfile  # noqa: E402
import datetime  # noqa: E402
import io  # noqa: E402
import multiprocessing  # noqa: E402
import pstats  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch.utils.data import DataLoader, default_collate  # noqa: E402

from datagen.engine.shard_payload import task_payload  # noqa: E402
from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.refine import make_refiner  # noqa: E402
from datagen.pipeline.task import run_task  # noqa: E402
from datagen.pipeline.thread_limits import single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402
from schemas.dataset import DATASET_FILE, DatasetInfo  # noqa: E402
from storage import (  # noqa: E402
    Dataset,
    ShardReader,
    committed_tasks,
    finalise,
    init_dataset,
    open_dataset,
    open_location,
    write_task,
)
from storage.index import coverage_disagreements, read_coverage, row_count_disagreements  # noqa: E402
from storage.reader import SHARD_CACHE  # noqa: E402
from storage.torch import OSVPDataset, ShardShuffleSampler  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
OBJECTS = REPO_ROOT / "examples" / "builtin.txt"
NUM_POINTS = 2048
BATCH = 32
WORKERS = 2
DIAGNOSTIC_MIX = 1
"""Shards mixed at a time in the diagnostic run (the default mixes 4)."""
SLOW_FIRST = ("torus_knot_3_5", "torus_knot", "vase", "table", "mug")
"""Built-ins whose tasks take longest (labelling the torus knots: 10-60 s a task); started first."""


# ---------------------------------------------------------------------------------------------------------
# the dataset
# ---------------------------------------------------------------------------------------------------------


def _task(job: tuple[int, int, GenerationConfig, str]) -> tuple[str, int, int, float]:
    index, rotation, config, url = job
    started = time.perf_counter()
    spec = read_objects_file(OBJECTS).objects[index]
    with single_threaded_blas():
        prepared = prepare_object(spec, config)
        result = run_task(prepared, rotation, config, build_view_space(config.view_space), make_refiner(config))
        write_task(open_location(url), task_payload(result, config), "bench")
    return spec.name, rotation, len(result.samples), time.perf_counter() - started


def build(url: str, rotations: int, processes: int) -> None:
    config = GenerationConfig(rotations=rotations)
    view_space = build_view_space(config.view_space)
    location = open_location(url)
    init_dataset(
        location,
        DatasetInfo(
            schema_version=1,
            config=config,
            config_hash=config.config_hash(),
            view_positions=[tuple(p) for p in view_space.positions.tolist()],
            versions={},
            created=datetime.datetime.now().isoformat(),
        ),
    )
    specs = read_objects_file(OBJECTS).objects
    order = sorted(range(len(specs)), key=lambda i: (specs[i].name not in SLOW_FIRST, i))
    jobs = [(i, r, config, url) for i in order for r in range(rotations)]
    print(
        f"building {len(specs)} built-ins x {rotations} rotations = {len(jobs)} tasks "
        f"(default config, refiner {config.refiner}, but rotations={rotations}, {processes} processes) into {url}",
        flush=True,
    )
    started = time.perf_counter()
    slowest: list[tuple[float, str]] = []
    with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("fork")) as pool:
        for name, rotation, _count, seconds in pool.map(_task, jobs):
            slowest.append((seconds, f"{name} r{rotation}"))
    finalise(location)
    slowest.sort(reverse=True)
    print(
        f"built in {time.perf_counter() - started:.0f} s; slowest tasks: "
        + ", ".join(f"{n} {s:.0f} s" for s, n in slowest[:3]),
        flush=True,
    )


# ---------------------------------------------------------------------------------------------------------
# measurements
# ---------------------------------------------------------------------------------------------------------


def rate(count: int, seconds: float) -> float:
    return count / seconds if seconds > 0 else float("inf")


def open_for_reading(url: str, checks: bool) -> Dataset:
    """A fresh dataset; ``checks=False`` skips the per-shard verification (the baseline)."""
    dataset = open_dataset(url)
    dataset._integrity_checks = checks
    return dataset


def random_access(url: str, budget: float, seed: int, checks: bool = True) -> tuple[float, int]:
    dataset = open_for_reading(url, checks)
    order = np.random.default_rng(seed).permutation(len(dataset))
    started = time.perf_counter()
    count = 0
    for i in order:
        dataset[int(i)]
        count += 1
        if time.perf_counter() - started > budget:
            break
    return rate(count, time.perf_counter() - started), count


def shuffled_iteration(url: str, budget: float, seed: int, checks: bool = True) -> tuple[float, int]:
    dataset = open_for_reading(url, checks)
    started = time.perf_counter()
    count = 0
    for _ in dataset.iter_shuffled(seed=seed):
        count += 1
        if time.perf_counter() - started > budget:
            break
    return rate(count, time.perf_counter() - started), count


def dataloader(
    url: str, budget: float, seed: int, mix: int | None = None, checks: bool = True
) -> tuple[float, float, int, np.ndarray, np.ndarray, np.ndarray]:
    """(rate with start-up, rate after the first batch, samples, clouds, masks, indices) of one epoch
    (``mix``: shards the sampler mixes at a time; None for its default)."""
    dataset = OSVPDataset(url, num_points=NUM_POINTS, seed=seed)
    dataset.dataset._integrity_checks = checks  # pickled with the dataset into each worker
    sampler = (
        ShardShuffleSampler(dataset, seed=seed) if mix is None else ShardShuffleSampler(dataset, seed, shards_mixed=mix)
    )
    loader = DataLoader(dataset, batch_size=BATCH, sampler=sampler, num_workers=WORKERS)
    clouds = np.empty((len(dataset), NUM_POINTS, 3), dtype=np.float32)
    masks = np.empty((len(dataset), 2, dataset.dataset.num_views), dtype=np.float32)
    seen: list[np.ndarray] = []
    started = time.perf_counter()
    first_batch = 0.0
    count = 0
    for batch in loader:
        if not first_batch:
            first_batch = time.perf_counter()
        index = batch["index"].numpy()
        clouds[index] = batch["points"].numpy()
        masks[index, 0] = batch["view_state"].numpy()
        masks[index, 1] = batch["label"].numpy()
        seen.append(index)
        count += len(index)
        if time.perf_counter() - started > budget:
            break
    ended = time.perf_counter()
    indices = np.concatenate(seen)
    first = len(seen[0])
    return rate(count, ended - started), rate(count - first, ended - first_batch), count, clouds, masks, indices


CHECKED_PATHS = ("random ds[i] (fresh dataset)", "iter_shuffled", "DataLoader, after 1st batch")


def check_cost(url: str, budget: float, seed: int, repeats: int) -> dict[str, tuple[float, float]]:
    """Best rate of each path with the checks (on, off), measured alternately so that drift in the
    machine's load hits both alike."""
    best: dict[str, list[float]] = {name: [0.0, 0.0] for name in CHECKED_PATHS}
    for repeat in range(repeats):
        for checks in (True, False) if repeat % 2 == 0 else (False, True):
            column = 0 if checks else 1
            rates = (
                random_access(url, budget, seed, checks)[0],
                shuffled_iteration(url, budget, seed, checks)[0],
                dataloader(url, budget, seed, checks=checks)[1],
            )
            for name, value in zip(CHECKED_PATHS, rates, strict=True):
                best[name][column] = max(best[name][column], value)
    return {name: (on, off) for name, (on, off) in best.items()}


def verify_cost(url: str) -> tuple[float, float]:
    """(ms per shard, µs per sample) of `ShardReader.verify` on fresh readers of every shard."""
    dataset = open_dataset(url)
    shards = sorted(set(dataset.index.column("shard").to_pylist()))
    readers = [ShardReader(dataset.location, shard, verify=False) for shard in shards]
    started = time.perf_counter()
    for reader in readers:
        reader.verify()
    seconds = time.perf_counter() - started
    return 1000 * seconds / len(shards), 1e6 * seconds / len(dataset)


def open_check_cost(url: str, repeats: int = 5) -> tuple[float, float]:
    """(ms to open the dataset, ms of that spent checking the index against the commit records),
    best of ``repeats``."""
    opens, checks = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        dataset = open_dataset(url)
        opens.append(time.perf_counter() - started)
        commits = committed_tasks(dataset.location)
        started = time.perf_counter()
        list(row_count_disagreements(dataset.index, commits))
        coverage = read_coverage(dataset.location) or {}
        list(coverage_disagreements(coverage, commits))
        checks.append(time.perf_counter() - started)
    return 1000 * min(opens), 1000 * min(checks)


def memmap_baseline(folder: Path, clouds: np.ndarray, masks: np.ndarray, budget: float, seed: int) -> float:
    path = folder / "clouds.npy"
    np.save(path, clouds)
    mapped = np.load(path, mmap_mode="r")
    rng = np.random.default_rng(seed)
    started = time.perf_counter()
    count = 0
    while time.perf_counter() - started < min(budget, 5.0):
        index = np.sort(rng.choice(len(mapped), size=BATCH, replace=False))
        points = torch.from_numpy(np.ascontiguousarray(mapped[index]))
        state = torch.from_numpy(masks[index, 0])
        label = torch.from_numpy(masks[index, 1])
        assert points.shape[0] == state.shape[0] == label.shape[0]
        count += BATCH
    return rate(count, time.perf_counter() - started)


def profile_worker_loop(url: str, samples: int, seed: int, mix: int | None = None) -> str:
    dataset = OSVPDataset(url, num_points=NUM_POINTS, seed=seed)
    sampler = (
        ShardShuffleSampler(dataset, seed=seed) if mix is None else ShardShuffleSampler(dataset, seed, shards_mixed=mix)
    )
    order = list(sampler)[:samples]
    opened = 0
    original = ShardReader.__init__

    def counting_init(self: ShardReader, *args: Any, **kwargs: Any) -> None:
        nonlocal opened
        opened += 1
        original(self, *args, **kwargs)

    profiler = cProfile.Profile()
    ShardReader.__init__ = counting_init  # type: ignore[method-assign]
    try:
        started = time.perf_counter()
        profiler.enable()
        for start in range(0, len(order), BATCH):
            default_collate([dataset[i] for i in order[start : start + BATCH]])
        profiler.disable()
        seconds = time.perf_counter() - started
    finally:
        ShardReader.__init__ = original  # type: ignore[method-assign]
    shards = len({dataset.dataset.index.column("shard")[i].as_py() for i in order})
    stream = io.StringIO()
    stats = pstats.Stats(profiler, stream=stream)
    stats.sort_stats("cumulative").print_stats(r"storage|zarr/core/(array|group)", 12)
    stats.sort_stats("tottime").print_stats(8)
    text = "\n".join(line for line in stream.getvalue().splitlines() if line.strip())
    name = f"default mix {sampler.shards_mixed} shards" if mix is None else f"mix {mix} shards"
    return (
        f"worker-equivalent loop ({name}), one process: {len(order)} samples of {shards} shards in "
        f"{seconds:.2f} s = {len(order) / seconds:,.0f}/s (profiled); ShardReader opened {opened} times "
        f"(the Dataset keeps {SHARD_CACHE} shards open)\n{text}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="dataset folder: built if absent, reused if present")
    parser.add_argument("--rotations", type=int, default=3, help="rotations per built-in (default 3)")
    parser.add_argument("--processes", type=int, default=2, help="build processes (default 2)")
    parser.add_argument("--seconds", type=float, default=20.0, help="time budget per measurement")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile", action="store_true", help="cProfile a worker-equivalent loop")
    parser.add_argument("--repeats", type=int, default=3, help="alternating runs per integrity-check row")
    args = parser.parse_args()

    scratch = Path(tempfile.mkdtemp(prefix="reader_bench_"))
    try:
        folder = args.out if args.out is not None else scratch / "dataset"
        url = str(folder)
        if (folder / DATASET_FILE).exists():
            print(f"reusing the dataset at {url}")
        else:
            build(url, args.rotations, args.processes)
        dataset = open_dataset(url)
        config = dataset.info.config
        sizes = dataset.index.column("num_points").to_numpy()
        print(
            f"dataset: {len(dataset)} samples, {len(dataset.shard_blocks())} shards (tasks), "
            f"{len(set(dataset.index.column('object_id').to_pylist()))} objects, rotations={config.rotations}, "
            f"refiner={config.refiner}; points per sample median {int(np.median(sizes))}, "
            f"min {int(sizes.min())}, max {int(sizes.max())}"
        )
        print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, budget {args.seconds:.0f} s per measurement")

        loader_rate, steady_rate, loaded, clouds, masks, indices = dataloader(url, args.seconds, args.seed)
        clouds, masks = clouds[indices], masks[indices]  # only the samples the loader returned
        random_rate, random_count = random_access(url, args.seconds, args.seed)
        shuffled_rate, shuffled_count = shuffled_iteration(url, args.seconds, args.seed)
        memmap_rate = memmap_baseline(scratch, clouds, masks, args.seconds, args.seed)
        small_buffer = dataloader(url, args.seconds, args.seed, mix=DIAGNOSTIC_MIX)
        checks = check_cost(url, args.seconds, args.seed, args.repeats)
        shard_ms, sample_us = verify_cost(url)
        open_ms, open_check_ms = open_check_cost(url)

        rows = [
            ("random ds[i] (fresh dataset)", random_rate, random_count),
            ("iter_shuffled", shuffled_rate, shuffled_count),
            (f"DataLoader, {WORKERS} workers, incl. start-up", loader_rate, loaded),
            (f"DataLoader, {WORKERS} workers, after 1st batch", steady_rate, loaded),
            (f"  diagnostic: shards mixed={DIAGNOSTIC_MIX}, after 1st batch", small_buffer[1], small_buffer[2]),
            ("numpy memmap, random batches", memmap_rate, 0),
        ]
        print(f"\n{'path':44s} {'samples/s':>12s} {'samples':>8s} {'vs memmap':>10s}")
        for name, value, count in rows:
            shown = str(count) if count else "-"
            print(f"{name:44s} {value:12,.0f} {shown:>8s} {value / memmap_rate:10.4f}")
        print(f"\nintegrity checks, best of {args.repeats} alternating runs each (samples/s):")
        print(f"{'path':44s} {'checks on':>12s} {'off (base)':>12s} {'on / off':>10s}")
        for name, (on, off) in checks.items():
            print(f"{name:44s} {on:12,.0f} {off:12,.0f} {on / off:10.3f}")
        print(
            f"ShardReader.verify: {shard_ms:.2f} ms per shard, {sample_us:.1f} us per sample spread over its shard; "
            f"open_dataset: {open_ms:.1f} ms, of which {open_check_ms:.2f} ms check the index (best of 5)"
        )
        verdict = "meets" if steady_rate >= 5000 else "MISSES"
        print(f"\nDataLoader target >= 5,000 samples/s: {verdict} ({steady_rate:,.0f}/s after the first batch)")
        if args.profile:
            print()
            print(profile_worker_loop(url, min(2048, len(dataset)), args.seed))
            print()
            print(profile_worker_loop(url, min(2048, len(dataset)), args.seed, DIAGNOSTIC_MIX))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
