"""Benchmark: the streaming read path (`storage.stream.ShardStream`) against today's map-style one
(`storage.torch.OSVPDataset` + `ShardShuffleSampler` + DataLoader), measured in the same run.

    python -m benchmarks.reading.streaming --make --source DATASET --big NEW_DATASET
    python -m benchmarks.reading.streaming --data DATASET [--data OTHER ...] --big NEW_DATASET
        [--seconds 0] [--repeats 3] [--s3 seaweedfs|moto|none] [--s3-shards 120]
        [--out benchmarks/reading/results/streaming.md]

Rows (every measurement in a fresh subprocess, DataLoader with 2 workers, batch 32, ``--points`` 2,048):

- throughput from local disk (each ``--data``: a dataset and its version-4 relabel compare window
  reads with whole-cloud reads in one run) and from an S3 server on loopback (SeaweedFS from
  `tests/support/s3_servers.py`, or moto), holding the first ``--s3-shards`` shards of the first ``--data``
  (S3 runs start their workers with ``spawn``: the map-style `OSVPDataset` cannot fork after its
  parent used s3fs, "This class is not fork-safe"; `ShardStream` reopens its store in each worker):
  samples/s over an epoch (or ``--seconds``) from the first ``next`` (worker start and the buffer
  fill included), and CPU time per sample, median of ``--repeats`` runs, the two paths
  alternating so both meet the same machine load;
- peak memory while streaming ``--big`` (>= 200,000 samples): the largest sum over the process and
  its DataLoader workers of RSS and of PSS (shared pages counted once), sampled every 0.5 s, for
  shuffle buffers of 1,024, 4,096 and 16,384 samples, beside the map-style path and what the
  in-memory `osvp.data.SampleBank` would need (`osvp.stream.memory_estimate`).

``--make`` writes ``--big``: the tasks of ``--source`` committed again under new task ids (copy k of
task T is task ``T-k``) through `storage.write_task`, until it holds ``--samples`` samples, then
finalised. Valid shards with real clouds, only the ids are new.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks.common import REPO_ROOT, add_report_options, check_report, use_test_support

OPTIONS_ENV = "STREAMING_BENCH_STORAGE_OPTIONS"
"""Storage options of an S3 run reach the measuring subprocess here (never on its command line)."""
BUFFERS = (1024, 4096, 16384)


# ---------------------------------------------------------------------------------------------------------
# --make: a >= 200k-sample dataset from an existing one
# ---------------------------------------------------------------------------------------------------------


def make_big(source: str, out: str, samples: int) -> None:
    import pyarrow.compute as pc

    import storage
    from schemas.shard import array_names
    from storage import ShardPayload, ShardReader, finalise, init_dataset, open_location, write_task

    found = storage.open_dataset(source)
    location = open_location(out)
    init_dataset(location, found.info)
    shards = sorted(set(found.index.column("shard").to_pylist()))
    written, copy, started = 0, 0, time.perf_counter()
    while written < samples:
        copy += 1
        for relative in shards:
            if written >= samples:
                break
            reader = ShardReader(found.location, relative)
            arrays = {name: reader.array(name) for name in array_names(reader.attributes.schema_version)}
            rows = found.index.filter(pc.equal(found.index["shard"], relative)).sort_by("row")
            columns = {
                c: rows.column(c).to_pylist() for c in rows.column_names if c not in ("shard", "row", "attempt_id")
            }
            task_id = f"{reader.attributes.task_id}-{copy}"
            columns["task_id"] = [task_id] * rows.num_rows
            columns["sample_id"] = [f"{task_id}-{sample.rsplit('-', 1)[1]}" for sample in columns["sample_id"]]
            attributes = reader.attributes.model_copy(update={"task_id": task_id})
            write_task(location, ShardPayload(attributes, arrays, columns), "copy")
            written += rows.num_rows
        print(f"copy {copy}: {written} samples, {time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)
    finalise(location)
    print(f"{out}: {written} samples in {time.perf_counter() - started:.0f} s")


# ---------------------------------------------------------------------------------------------------------
# one measurement (run in its own process)
# ---------------------------------------------------------------------------------------------------------


class PeakMemory:
    """The largest RSS and PSS summed over this process and its children, sampled every ``every`` s."""

    def __init__(self, every: float = 0.5) -> None:
        import psutil

        self._me = psutil.Process()
        self._every = every
        self.rss = self.pss = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> PeakMemory:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        import psutil

        while not self._stop.is_set():
            rss = pss = 0
            for process in [self._me, *self._me.children(recursive=True)]:
                try:
                    info = process.memory_full_info()
                except (psutil.NoSuchProcess, psutil.AccessDenied):
                    continue
                rss, pss = rss + info.rss, pss + info.pss
            self.rss, self.pss = max(self.rss, rss), max(self.pss, pss)
            self._stop.wait(self._every)


def cpu_seconds() -> float:
    """CPU time (user + system) of this process, its children that ended (reaped) and those alive."""
    import psutil

    me = psutil.Process()
    mine = me.cpu_times()
    total = mine.user + mine.system + mine.children_user + mine.children_system
    for process in me.children(recursive=True):
        try:
            times = process.cpu_times()
        except psutil.NoSuchProcess:
            continue
        total += times.user + times.system
    return total


def measure(args: argparse.Namespace) -> dict[str, Any]:
    import torch
    from torch.utils.data import DataLoader

    torch.set_num_threads(1)
    options = json.loads(os.environ.get(OPTIONS_ENV, "null"))
    with PeakMemory() as memory:
        started = time.perf_counter()
        if args.path == "stream":
            from storage.stream import ShardStream

            stream = ShardStream(
                args.url,
                num_points=args.points,
                batch_size=args.batch,
                seed=0,
                shuffle_buffer=args.buffer,
                read_ahead=args.read_ahead,
                num_workers=args.workers,
                storage_options=options,
            )
            loader: DataLoader[Any] = stream.loader(multiprocessing_context=args.context)
            total = stream.num_samples
        else:
            from storage.torch import OSVPDataset, ShardShuffleSampler, collate_samples

            dataset = OSVPDataset(args.url, num_points=args.points, storage_options=options)
            loader = DataLoader(
                dataset,
                batch_size=args.batch,
                sampler=ShardShuffleSampler(dataset),
                collate_fn=collate_samples,  # items are dicts since SampleBatch; this makes the batch one
                num_workers=args.workers,
                multiprocessing_context=args.context,
            )
            total = len(dataset)
        seen, first, cpu, clock = 0, 0.0, cpu_seconds(), time.perf_counter()
        for batch in loader:
            # the map-style path's default collate gives a dict, the stream a SampleBatch
            seen += int((batch["points"] if isinstance(batch, dict) else batch.points).shape[0])
            if not first:
                first = time.perf_counter() - clock
            if args.seconds > 0 and time.perf_counter() - clock > args.seconds:
                break
        spent = time.perf_counter() - clock
        cpu = cpu_seconds() - cpu
        del loader
    return {
        "samples": seen,
        "seconds": spent,
        "rate": seen / spent if spent > 0 else 0.0,
        "first_batch_s": first,
        "dataset_samples": total,
        "setup_s": clock - started,
        "peak_rss": memory.rss,
        "peak_pss": memory.pss,
        "cpu_per_sample": cpu / seen if seen else 0.0,
    }


def run_one(path: str, url: str, args: argparse.Namespace, seconds: float, **extra: Any) -> dict[str, Any]:
    """`measure` in a fresh interpreter (clean memory, nothing cached from another run)."""
    command = [
        sys.executable,
        "-m",
        "benchmarks.reading.streaming",
        "--measure",
        path,
        "--url",
        url,
        "--seconds",
        str(seconds),
        "--points",
        str(args.points),
        "--batch",
        str(args.batch),
        "--workers",
        str(args.workers),
        "--buffer",
        str(extra.get("buffer", 4096)),
        "--read-ahead",
        str(extra.get("read_ahead", 2)),
        "--context",
        str(extra.get("context", "fork")),
    ]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", OPTIONS_ENV: json.dumps(extra.get("options"))}
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=REPO_ROOT)
    if done.returncode != 0:
        raise RuntimeError(f"{path} on {url} failed:\n{done.stderr[-3000:]}")
    found: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    print(f"  {path} {url} {extra.get('buffer', '')}: {found['rate']:,.0f} samples/s", file=sys.stderr, flush=True)
    return found


# ---------------------------------------------------------------------------------------------------------
# the benchmark
# ---------------------------------------------------------------------------------------------------------


def throughput(url: str, args: argparse.Namespace, **extra: Any) -> dict[str, list[dict[str, Any]]]:
    runs: dict[str, list[dict[str, Any]]] = {"baseline": [], "stream": []}
    for _ in range(args.repeats):
        for path in ("baseline", "stream"):  # alternating: both meet the same machine load
            runs[path].append(run_one(path, url, args, args.seconds, **extra))
    return runs


def s3_copy(server: Any, source: str, shards: int) -> str:
    """The first ``shards`` tasks of ``source`` uploaded to the server (files as they are), finalised."""
    import storage
    from storage import finalise, open_location
    from storage.dataset import COMMITS

    found = storage.open_dataset(source)
    chosen = sorted(set(found.index.column("shard").to_pylist()))[:shards]
    root = Path(found.location.root)
    tasks = {relative.split("/")[1] for relative in chosen}
    client = server.client()
    prefix = f"streaming-{os.getpid()}"
    files = [root / "dataset.json"] + [root / COMMITS / f"{task}.json" for task in sorted(tasks)]
    for task in sorted(tasks):
        files += [p for p in (root / "shards" / task).rglob("*") if p.is_file()]
    for path in files:
        client.upload_file(str(path), "datasets", f"{prefix}/{path.relative_to(root).as_posix()}")
    url = f"s3://datasets/{prefix}"
    finalise(open_location(url, s3_options(server)))
    return url


def s3_options(server: Any) -> dict[str, Any]:
    from support.s3_servers import REGION

    return {
        "key": server.key_id,
        "secret": server.secret,
        "endpoint_url": server.endpoint,
        "client_kwargs": {"region_name": REGION},
    }


def median(runs: list[dict[str, Any]], key: str = "rate") -> float:
    return float(statistics.median(run[key] for run in runs))


def machine_state() -> str:
    load = os.getloadavg()
    memory = ""
    try:
        import psutil

        used = psutil.virtual_memory()
        memory = f", memory {used.used / 2**30:.1f} of {used.total / 2**30:.1f} GiB in use"
    except ImportError:
        pass
    cpu = platform.processor() or platform.machine()
    return f"{os.cpu_count()} CPU cores ({cpu}), load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}{memory}"


def benchmark(args: argparse.Namespace) -> str:
    from osvp.stream import memory_estimate

    import storage

    use_test_support()
    before = machine_state()
    lines: list[tuple[str, str, int, dict[str, list[dict[str, Any]]]]] = []
    for url in args.data:
        data = storage.open_dataset(url)
        lines.append((f"local disk, version {data.info.schema_version}", url, len(data), throughput(url, args)))
    s3: tuple[str, str, int, dict[str, list[dict[str, Any]]]] | None = None
    if args.s3 != "none":
        from support.s3_servers import moto_server, seaweedfs_server

        with tempfile.TemporaryDirectory() as folder:
            server_of = seaweedfs_server if args.s3 == "seaweedfs" else moto_server
            with server_of(Path(folder)) as server:
                url = s3_copy(server, args.data[0], args.s3_shards)
                options = s3_options(server)
                samples = len(storage.open_dataset(url, options))
                runs = throughput(url, args, options=options, read_ahead=4, context="spawn")
                s3 = (f"S3 ({args.s3}, loopback)", url, samples, runs)
    memory: list[tuple[str, dict[str, Any]]] = []
    big_samples = 0
    if Path(args.big).exists():
        big_samples = len(storage.open_dataset(args.big))
        memory.append(("map-style (baseline)", run_one("baseline", args.big, args, args.memory_seconds)))
        for buffer in BUFFERS:
            memory.append(
                (f"stream, buffer {buffer:,}", run_one("stream", args.big, args, args.memory_seconds, buffer=buffer))
            )
        small = len(storage.open_dataset(args.data[0]))
        found = run_one("stream", args.data[0], args, args.memory_seconds, buffer=4096)
        memory.append((f"stream, buffer 4,096, on --data ({small:,} samples)", found))
    after = machine_state()

    window = f"{args.seconds:g} s" if args.seconds > 0 else "the end of the epoch"
    out = [
        "# Streaming read path: `storage.stream.ShardStream` against the map-style DataLoader",
        "",
        f"`python -m benchmarks.reading.streaming --seconds {args.seconds:g} --repeats {args.repeats} "
        f"--s3 {args.s3}` on "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Machine: {before} at the start; {after} at the end. "
        "The machine is shared with other agents' jobs: timings are noisy; each figure is the median of the runs, "
        "the two paths alternating.",
        "",
        f"Every run: a fresh process, DataLoader with {args.workers} workers, batch {args.batch}, "
        f"{args.points:,} points per cloud; samples/s = samples / seconds from the DataLoader's first `next` "
        f"(worker start and the stream's buffer fill included) to {window}. "
        "Workers fork, except on S3 (spawn: the map-style path cannot fork after its parent used s3fs). "
        "Baseline: `OSVPDataset` + `ShardShuffleSampler` (per-sample reads, shards cached per worker, "
        "`storage.torch.collate_samples`). Stream: `ShardStream` (whole shards, or a version-4 dataset's "
        "windows, read ahead in threads, shuffle buffer 4,096, "
        "batches made in the workers, `batch_size=None`). CPU ms per sample: user + system time of the process "
        "and its workers over the counted window, divided by the samples (robust to other jobs' load, unlike "
        "samples/s; on S3 the server's own CPU is not in it); the ceiling is 2 cores divided by it.",
        "",
        "## Throughput",
        "",
        "| source | dataset | samples | path | samples/s (median) | runs | / baseline | CPU ms per sample "
        "| ceiling on 2 idle cores (samples/s) | first batch after (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, url, samples, runs in [*lines, *([s3] if s3 else [])]:
        base = median(runs["baseline"])
        for path, label in (("baseline", "map-style (baseline)"), ("stream", "ShardStream")):
            value = median(runs[path])
            each = ", ".join(f"{run['rate']:,.0f}" for run in runs[path])
            shown = url if not url.startswith("s3://") else f"first {args.s3_shards} shards of --data"
            cpu = median(runs[path], "cpu_per_sample")
            out.append(
                f"| {name} | {shown} | {samples:,} | {label} | {value:,.0f} | {each} | {value / base:.2f} | "
                f"{cpu * 1e3:.3f} | {2 / cpu if cpu else 0:,.0f} | {median(runs[path], 'first_batch_s'):.1f} |"
            )
    if memory:
        estimate = memory_estimate(storage.open_dataset(args.big))
        out += [
            "",
            f"## Peak memory while streaming {args.big} ({big_samples:,} samples)",
            "",
            f"{args.memory_seconds:g} s of reading (0: the whole epoch) from the first `next`; peak over the process "
            f"and its {args.workers} workers. In memory (`SampleBank`) the same dataset needs about "
            f"{estimate / 1e9:.1f} GB (`osvp.stream.memory_estimate`), and twice its keys while loading.",
            "",
            "| path | samples read | samples/s | peak RSS, summed (GB) | peak PSS, summed (GB) |",
            "|---|---|---|---|---|",
        ]
        for label, found in memory:
            out.append(
                f"| {label} | {found['samples']:,} | {found['rate']:,.0f} | {found['peak_rss'] / 1e9:.2f} | "
                f"{found['peak_pss'] / 1e9:.2f} |"
            )
    return "\n".join(out) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--make", action="store_true", help="write --big from --source, then stop")
    parser.add_argument("--source", help="with --make: the dataset whose samples are repeated into --big")
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--data", action="append", help="a dataset to read; repeat to compare")
    parser.add_argument("--big", help="the 200k-sample dataset the memory rows stream (made by --make)")
    parser.add_argument("--seconds", type=float, default=0.0, help="stop each throughput run after this (0: an epoch)")
    parser.add_argument("--memory-seconds", type=float, default=60.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--points", type=int, default=2048)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--s3", choices=("seaweedfs", "moto", "none"), default="seaweedfs")
    parser.add_argument("--s3-shards", type=int, default=120)
    add_report_options(parser, None, "also write the table here (markdown)")
    # one measurement, in a subprocess of the benchmark
    parser.add_argument("--measure", choices=("baseline", "stream"), help=argparse.SUPPRESS)
    parser.add_argument("--url", help=argparse.SUPPRESS)
    parser.add_argument("--buffer", type=int, default=4096, help=argparse.SUPPRESS)
    parser.add_argument("--read-ahead", type=int, default=2, help=argparse.SUPPRESS)
    parser.add_argument("--context", default="fork", help=argparse.SUPPRESS)
    args = parser.parse_args()
    check_report(parser, args.out, args.replace)
    if args.measure:
        args.path = args.measure
        print(json.dumps(measure(args)))
        return
    if args.make:
        if not args.source or not args.big:
            parser.error("--make needs --source DATASET and --big NEW_DATASET")
        make_big(args.source, args.big, args.samples)
        return
    if not args.data or not args.big:
        parser.error("give --data DATASET (repeat to compare) and --big DATASET (made by --make)")
    table = benchmark(args)
    print(table)
    if args.out is not None:
        args.out.write_text(table)


if __name__ == "__main__":
    main()
