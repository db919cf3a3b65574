"""Benchmark: CPU-seconds of one task's ``poco`` refinement, original vs fast execution, same run.

    python -m benchmarks.generation.refine_speed [--builtins mug,torus_knot,chair] [--meshes cow,fandisk]
        [--repeats 3] [--split] [--no-version2] [--out benchmarks/generation/results/refine-speed.md]

For each object (rotation 0, default config): the task's refine requests are built as generation
builds them (`pipeline.task`): its 32 single views, then one combined observation per multi-view
case of `long_tail_cases`. Every request is refined by the original execution
(``PocoRefiner(fast=False)``) and by the fast one (``fast=True``, the default), alternating, ``--repeats``
times each; the table gives the median CPU-seconds (``time.process_time``: robust to other work on
the machine, wall time is not) and old / new. Each run also checks that the two give bit-identical
probabilities (so identical refined sets and labels): the ``identical`` column. When pykdtree is
installed, ``poco_version = 2`` (fast execution; another dataset identity) runs in the same rotation:
its CPU-seconds, speed-up over the original, and the share of R(O)'s keys that differ from version 1.

``--split`` adds where the time goes (kNN tables, encoder, decoder, query keys, rest), from timers
around those steps (their own overhead is small; the totals of that pass are not the timed ones).
torch runs with one thread and BLAS single-threaded, as in a worker. ``uptime`` load is printed
before and after: the machine is shared, so compare the ratio, not the absolute seconds.
"""

from __future__ import annotations

import os

from benchmarks.common import SHARED_MESHES, add_report_options, check_report, limit_threads

limit_threads(torch_threads=1)

import argparse  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from datagen.pipeline.cases import long_tail_cases  # noqa: E402
from datagen.pipeline.imaging import Observation  # noqa: E402
from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.random_streams import Purpose, stream  # noqa: E402
from datagen.pipeline.refine import RefineRequest, make_refiner  # noqa: E402
from datagen.pipeline.refine.poco import inputs as poco_inputs  # noqa: E402
from datagen.pipeline.refine.poco import network as poco_network  # noqa: E402
from datagen.pipeline.refine.poco import refiner as poco_refiner  # noqa: E402
from datagen.pipeline.refine.poco import spatial as poco_spatial  # noqa: E402
from datagen.pipeline.refine.poco.refiner import PocoRefiner  # noqa: E402
from datagen.pipeline.refine.poco.spatial import pykdtree_available  # noqa: E402
from datagen.pipeline.scanning import scan_task  # noqa: E402
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402


def task_requests(line: str, config: GenerationConfig, rotation: int = 0) -> tuple[str, list[RefineRequest]]:
    """(name, requests) of one objects-file line: every single view, then each multi-view case."""
    listing = Path(f"/tmp/datagen_refine_speed_{os.getpid()}.txt")
    listing.write_text(line + "\n")
    spec = read_objects_file(listing).objects[0]
    listing.unlink()
    scan = scan_task(prepare_object(spec, config), rotation, config, build_view_space(config.view_space))
    singles = list(scan.observations)
    visible = [o.keys for o in singles]
    cases = long_tail_cases(visible, stream(config.seed, spec.object_id, rotation, Purpose.CASES))
    multi = sorted({c for c in cases if c.bit_count() > 1}, key=lambda c: (c.bit_count(), c))
    combined = [Observation.combine([singles[v] for v in range(c.bit_length()) if c >> v & 1]) for c in multi]
    requests = [RefineRequest(o, config.seed, spec.object_id, rotation) for o in singles + combined]
    return spec.name, requests


def probabilities(refiner: PocoRefiner, requests: list[RefineRequest]) -> tuple[float, list[Any]]:
    """CPU-seconds of refining every request (as `refine` does: probabilities, then the threshold)."""
    started = time.process_time()
    with refiner.execution():
        out = [refiner.probabilities(request) for request in requests]
    return time.process_time() - started, out


class Split:
    """Timers wrapped around the refinement's steps (module attributes patched while inside)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    def _wrap(self, label: Callable[..., str], function: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            started = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds[label(*args, **kwargs)] += time.process_time() - started

        return timed

    @contextmanager
    def patched(self, decoder_k: int) -> Iterator[None]:
        def knn_label(source: Any, target: Any, k: int, **_: Any) -> str:
            return "kNN decoder table" if k == decoder_k else "kNN encoder tables"

        patches = [
            (poco_spatial, "knn", knn_label),
            (poco_spatial, "quantized_sampling", lambda *a, **k: "quantized sampling"),
            (poco_network.PocoModel, "encode", lambda *a, **k: "encoder forward"),
            (poco_network.PocoModel, "decode", lambda *a, **k: "decoder forward"),
            (poco_network.PocoModel, "decode_inference", lambda *a, **k: "decoder forward"),
            (poco_refiner, "query_keys", lambda *a, **k: "query keys (band, sensor-empty)"),
            (poco_refiner, "observation_inputs", lambda *a, **k: "inputs"),
        ]
        saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
        try:
            for owner, name, label in patches:
                setattr(owner, name, self._wrap(label, getattr(owner, name)))
            yield
        finally:
            for owner, name, original in saved:
                setattr(owner, name, original)


def load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--builtins", default="mug,torus_knot,chair")
    parser.add_argument("--meshes", default="cow,fandisk", help=f"names of meshes in {SHARED_MESHES}")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--split", action="store_true", help="also time the steps (one more pass each)")
    parser.add_argument("--no-version2", action="store_true", help="skip poco_version = 2")
    add_report_options(parser, None, "write the markdown tables here")
    args = parser.parse_args()
    check_report(parser, args.out, args.replace)
    config = GenerationConfig()
    lines = [f"builtin:{name}" for name in args.builtins.split(",") if name]
    for name in (n for n in args.meshes.split(",") if n):
        found = sorted(SHARED_MESHES.glob(f"{name}.*")) if SHARED_MESHES.is_dir() else []
        if found:
            lines.append(f"{found[0]} name={name}")
        else:
            print(f"(no mesh {name} in {SHARED_MESHES}; skipped)")
    base = make_refiner(config)
    assert isinstance(base, PocoRefiner)
    version2 = not args.no_version2 and pykdtree_available()
    runs: list[str] = ["original", "fast"] + (["version 2"] if version2 else [])

    def refiner(run: str) -> PocoRefiner:  # a fresh one per task, as a worker builds it
        chosen = config.model_copy(update={"poco_version": 2}) if run == "version 2" else config
        fast = run != "original"
        return PocoRefiner(chosen, base.model, base.weights_id, base.threshold, base.finetune_steps, fast=fast)

    started_load = load()
    print(started_load)
    rows, splits = [], {}
    with single_threaded_blas(), fixed_torch_threads(1):
        for run in runs:  # warm-up
            refiner(run).probabilities(task_requests("builtin:capsule", config)[1][0])
        for line in lines:
            name, requests = task_requests(line, config)
            queries = sum(poco_inputs.query_keys(r.observation, config)[1].size for r in requests)
            times: dict[str, list[float]] = {run: [] for run in runs}
            outputs: dict[str, list[Any]] = {}
            for _ in range(args.repeats):
                for run in runs:
                    seconds, out = probabilities(refiner(run), requests)
                    times[run].append(seconds)
                    outputs[run] = out
            identical = all(
                np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
                for a, b in zip(outputs["original"], outputs["fast"], strict=True)
            )
            median = {run: statistics.median(seconds) for run, seconds in times.items()}
            changed = refined_change(outputs["fast"], outputs["version 2"], base.threshold) if version2 else None
            rows.append((name, len(requests), queries, median, identical, changed))
            print(
                f"{name:<12} requests {len(requests):>3} queries {queries:>9,} "
                + "  ".join(f"{run} {median[run]:6.2f} s" for run in runs)
                + f"  x{median['original'] / median['fast']:4.2f}  identical {identical}"
                + (f"  version 2 changes {100 * changed:.2f} % of R(O)" if changed is not None else "")
                + f"  (all: { {run: [round(t, 2) for t in seconds] for run, seconds in times.items()} })",
                flush=True,
            )
            if args.split:
                for run in runs:
                    split = Split()
                    with split.patched(base.model.preset.decoder_k):
                        total, _ = probabilities(refiner(run), requests)
                    split.seconds["rest (Python, tensors, threshold)"] = total - sum(split.seconds.values())
                    splits[(name, run)] = (total, dict(split.seconds))
    finished_load = load()
    print(finished_load)
    report = markdown(rows, splits, runs, started_load, finished_load, args.repeats)
    print(report)
    if args.out is not None:
        args.out.write_text(report)


def refined_change(first: list[Any], second: list[Any], threshold: float) -> float:
    """Keys in exactly one of the two R(O) (symmetric difference), over the keys of the first's R(O)."""
    differing = kept = 0
    for (_, prob_a), (_, prob_b) in zip(first, second, strict=True):
        kept += int((prob_a > threshold).sum())
        differing += int(((prob_a > threshold) != (prob_b > threshold)).sum())
    return differing / max(1, kept)


Row = tuple[str, int, int, dict[str, float], bool, float | None]


def markdown(
    rows: list[Row],
    splits: dict[tuple[str, str], tuple[float, dict[str, float]]],
    runs: list[str],
    started: str,
    finished: str,
    repeats: int,
) -> str:
    cpu = subprocess.run(["sh", "-c", "lscpu | grep 'Model name'"], capture_output=True, text=True).stdout.strip()
    version2 = "version 2" in runs
    out = [
        "# poco refinement per task: original vs fast execution (benchmarks/generation/refine_speed.py)",
        "",
        f"{cpu or 'CPU unknown'}; torch {torch.__version__}, 1 torch thread, BLAS single-threaded (a worker's",
        f"setting). CPU-seconds (time.process_time), median of {repeats} alternating runs per execution.",
        f"Load before: `{started}`; after: `{finished}`.",
        "",
        "| object | requests | queries | original CPU-s | fast CPU-s | speed-up | identical probabilities |"
        + (" version 2 CPU-s | speed-up | R(O) keys changed |" if version2 else ""),
        "|---|---|---|---|---|---|---|" + ("---|---|---|" if version2 else ""),
    ]

    def line(name: str, requests: int, queries: int, median: dict[str, float], same: bool, changed: str) -> str:
        old, new = median["original"], median["fast"]
        text = f"| {name} | {requests} | {queries:,} | {old:.2f} | {new:.2f} | {old / new:.2f}x | "
        text += "yes |" if same else "**no** |"
        if version2:
            text += f" {median['version 2']:.2f} | {old / median['version 2']:.2f}x | {changed} |"
        return text

    for name, requests, queries, median, identical, changed in rows:
        share = f"{100 * changed:.2f} %" if changed is not None else "-"
        out.append(line(name, requests, queries, median, identical, share))
    if rows:
        totals = {run: sum(r[3][run] for r in rows) for run in runs}
        same = all(r[4] for r in rows)
        out.append(line("**all**", sum(r[1] for r in rows), sum(r[2] for r in rows), totals, same, ""))
    if splits:
        labels = sorted({label for _, seconds in splits.values() for label in seconds})
        names = sorted({name for name, _ in splits})
        out += ["", "Where the time goes (CPU-s summed over the objects above, one timed pass each):", ""]
        out += ["| step | " + " | ".join(runs) + " | " + " | ".join(f"share {run}" for run in runs) + " |"]
        out += ["|---|" + "---|" * (2 * len(runs))]
        totals = {run: sum(splits[(n, run)][0] for n in names) for run in runs}
        for label in sorted(labels, key=lambda la: -sum(splits[(n, "original")][1].get(la, 0.0) for n in names)):
            seconds = {run: sum(splits[(n, run)][1].get(label, 0.0) for n in names) for run in runs}
            out.append(
                f"| {label} | "
                + " | ".join(f"{seconds[run]:.2f}" for run in runs)
                + " | "
                + " | ".join(f"{100 * seconds[run] / totals[run]:.0f} %" for run in runs)
                + " |"
            )
        out.append("| total | " + " | ".join(f"{totals[run]:.2f}" for run in runs) + " |" + " 100 % |" * len(runs))
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    main()
