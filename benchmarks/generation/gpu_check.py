"""Benchmark: the ``poco`` refiner on a GPU against the CPU, per task, in one short run.

    python -m benchmarks.generation.gpu_check [--device cuda] [--objects examples/demo.txt] [--rotations 0]
        [--repeat] [--no-tf32] [--config FILE] [--budget SECONDS] [--out DIR]

Why: ``--refiner-gpus`` (`RunSettings.refiner_gpus`) builds the refiner with ``device='cuda'``, and a
dataset's hash does not say where it was refined. So the GPU path must be shown to give the CPU's R(O)
and labels, or how far it strays must be known, before anyone makes a dataset with it.

For every object and rotation, one task runs in this process as a worker runs it (`run_task`, BLAS
single-threaded and torch at one thread, a fresh refiner per task over a model loaded once per device):
first with the CPU refiner, the reference, then once per variant on ``--device``:

- ``DEVICE``: as the pipeline runs it (torch's defaults, TF32 for cuDNN's convolutions included);
- ``DEVICE again`` (``--repeat``): the same a second time: does the device repeat itself?
- ``DEVICE fp32`` (``--no-tf32``): TF32 off for matmuls and cuDNN: does TF32 explain a difference?

Each variant is compared with the reference (`benchmarks.generation.gpu_compare`): whether R(O) of
every single view and every multi-view case is identical; per refined observation, |R_ref xor R| /
|R_ref or R| (max and mean over the task) and the largest |p_ref - p| of a queried key; whether every
sample's label (its views and status) is identical; and the wall times of the task and of its
refinement. ``--out DIR`` gets ``gpu-check.json`` (every field) and ``gpu-check.md`` (the tables),
rewritten after every task so that a run cut short leaves what it did; ``results/gpu-check.md`` is
such a run on a GPU machine.

Differences are reported, never failures: the exit status is 0 when every run ran. A variant that
raises is recorded with its error (the traceback goes to the log), the other tasks go on, and the
status is 1. ``--device cuda`` where torch sees no CUDA device exits with status 2 and one line.
``--device cpu`` checks the CPU against itself: every comparison must come out identical, which is
how the tests check this script without a GPU.
"""

from __future__ import annotations

from benchmarks.common import REPO_ROOT, limit_threads

limit_threads()

import argparse  # noqa: E402
import importlib.metadata  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from collections.abc import Callable, Iterator, Sequence  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from datetime import UTC, datetime  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402
import torch  # noqa: E402

from benchmarks.generation.gpu_compare import (  # noqa: E402
    REFERENCE,
    Comparison,
    Refinement,
    TaskRun,
    compare_runs,
    markdown,
    run_json,
    summary,
)
from datagen.config_io import load_config  # noqa: E402
from datagen.errors import DatagenError  # noqa: E402
from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import PreparedObject, prepare_object  # noqa: E402
from datagen.pipeline.objects.spec import ObjectSpec  # noqa: E402
from datagen.pipeline.refine import RefineRequest, make_refiner  # noqa: E402
from datagen.pipeline.refine.poco.refiner import PocoRefiner  # noqa: E402
from datagen.pipeline.scanning import scan_task  # noqa: E402
from datagen.pipeline.step_timing import StepClock  # noqa: E402
from datagen.pipeline.task import run_task  # noqa: E402
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import ViewSpace, build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402

DEMO_OBJECTS = REPO_ROOT / "examples" / "demo.txt"
"""The eight quick built-ins of the README's demo: one CPU task each takes 5-15 s on the 2-core machine."""
REFINE_STEPS = ("refine_views", "refine_cases")
PACKAGES = ("numpy", "scipy", "torch", "trimesh", "embreex", "highspy", "pydantic", "pykdtree", "threadpoolctl")
"""Versions the report records: the CPU side of a refinement (cKDTree's neighbour tables) and the labels
(HiGHS) run on the checking machine's versions, which may not be the ones datasets were made with."""
JSON_NAME = "gpu-check.json"
MARKDOWN_NAME = "gpu-check.md"


@dataclass(frozen=True)
class Variant:
    """One way of refining: a device and, for CUDA, whether TF32 is allowed (None: torch's default)."""

    label: str
    device: str
    tf32: bool | None = None


class RecordingRefiner(PocoRefiner):
    """The ``poco`` refiner, unchanged, keeping what each request's refinement saw: the probabilities
    R(O) was cut from tell a rounding difference (a key near the threshold) from a broken computation.
    Each request runs alone (`probabilities`), which gives what `PocoRefiner.refine` gives together:
    every request's network job is its own."""

    def __init__(self, base: PocoRefiner) -> None:
        super().__init__(base.config, base.model, base.weights_id, base.threshold, base.finetune_steps, base.device)
        self.records: list[Refinement] = []

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        out = []
        for request in requests:
            queries, prob = self.probabilities(request)
            kept = queries[prob > self.threshold]
            self.records.append(Refinement(request.mask, queries, prob, kept))
            out.append(kept)
        return out


@contextmanager
def tf32_allowed(allowed: bool | None) -> Iterator[None]:
    """TF32 on or off for CUDA matmuls and cuDNN while inside (no change for None); restored after.

    Through the flags every torch since 1.7 has: torch 2.9's per-backend ``fp32_precision`` strings
    refuse to be mixed with them, and restoring the strings does not give back the same state. The
    flags restore cuDNN's exactly and leave matmuls at 'ieee' where they were 'none' (inherit), which
    is the same arithmetic: the default forbids TF32 there."""
    if allowed is None:
        yield
        return
    saved = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    torch.backends.cuda.matmul.allow_tf32 = allowed
    torch.backends.cudnn.allow_tf32 = allowed
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def base_refiner(config: GenerationConfig, device: str) -> PocoRefiner:
    """The factory's refiner for ``device`` (the factory loads the model once per device and keeps it)."""
    refiner = make_refiner(config, device)
    if not isinstance(refiner, PocoRefiner):
        raise DatagenError(f"the config's refiner is {config.refiner!r}; this check needs refiner = 'poco'")
    return refiner


def synchronise(device: str) -> None:
    """Wait for the device's queued work, so that a wall time includes it."""
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def run_variant(
    prepared: PreparedObject, rotation: int, config: GenerationConfig, view_space: ViewSpace, variant: Variant
) -> TaskRun:
    """One task as a worker runs it (`datagen.engine.worker.execute_task`), refined by ``variant``."""
    refiner = RecordingRefiner(base_refiner(config, variant.device))
    clock = StepClock()
    with single_threaded_blas(), fixed_torch_threads(), tf32_allowed(variant.tf32):
        synchronise(variant.device)
        started = time.perf_counter()
        result = run_task(prepared, rotation, config, view_space, refiner, clock=clock)
        synchronise(variant.device)
        seconds = time.perf_counter() - started
    return TaskRun(
        refinements=refiner.records,
        labels={sample.case: (sample.label, sample.cover.status) for sample in result.samples},
        failures={failure.case: failure.message for failure in result.failures},
        cases=result.cases,
        task_seconds=seconds,
        refine_seconds=clock.wall_of(*REFINE_STEPS),
        steps=dict(clock.wall),
    )


def warm_up(request: RefineRequest, config: GenerationConfig, variant: Variant) -> float:
    """Wall seconds of the first refinement on the variant's device (CUDA's context, the kernels' first
    load, the model's copy): a worker pays them once, so they are kept out of the task times."""
    started = time.perf_counter()
    refiner = base_refiner(config, variant.device)
    with single_threaded_blas(), fixed_torch_threads(), tf32_allowed(variant.tf32):
        refiner.refine([request])
        synchronise(variant.device)
    return time.perf_counter() - started


def failed(label: str, error: BaseException) -> str:
    """The error's last line for the report; the whole traceback goes to the log."""
    print(f"  {label}: raised; traceback follows", flush=True)
    traceback.print_exception(error, file=sys.stdout)
    sys.stdout.flush()
    return "".join(traceback.format_exception_only(error)).strip()


def check(
    objects: Sequence[ObjectSpec],
    rotations: Sequence[int],
    config: GenerationConfig,
    chosen: Sequence[Variant],
    saved: Callable[[dict[str, Any]], None] = lambda _: None,
    budget: float | None = None,
) -> dict[str, Any]:
    """Every (object, rotation) on the reference and on each variant, as JSON data; ``saved`` receives
    the result so far after every task (with ``complete`` False until the last). With ``budget``
    (seconds), no task starts that the last one's time says would end past it: a device is lent for
    minutes, and a short report beats none."""
    started = time.perf_counter()
    view_space = build_view_space(config.view_space)
    reference = Variant(REFERENCE, "cpu")
    first = prepare_object(objects[0], config)
    view = scan_task(first, 0, config, view_space).observations[0]
    request = RefineRequest(view, config.seed, first.spec.object_id, 0)
    warm: dict[str, float | None] = {}
    for variant in [reference, *chosen]:
        try:
            warm[variant.label] = warm_up(request, config, variant)
        except Exception as error:  # a device that fails is a finding; its tasks record the error
            failed(f"warm-up {variant.label}", error)
            warm[variant.label] = None
    times = (f"{label} {'failed' if s is None else f'{s:.2f} s'}" for label, s in warm.items())
    print("first refinement on each: " + ", ".join(times), flush=True)
    cpu = base_refiner(config, "cpu")
    result: dict[str, Any] = {
        "objects": [spec.source for spec in objects],
        "rotations": list(rotations),
        "config_hash": config.config_hash(),
        "refiner": {
            "name": cpu.name,
            "weights_id": cpu.weights_id,
            "threshold": cpu.threshold,
            "preset": config.poco_preset,
            "poco_version": config.poco_version,
            "finetune_steps": config.finetune_steps,
        },
        "reference": asdict(reference),
        "variants": [asdict(v) for v in chosen],
        "warm_up_seconds": warm,
        "tasks": [],
        "summary": {},
        "seconds": 0.0,
        "complete": False,
    }
    last = 0.0
    current: PreparedObject | None = None
    for spec, rotation in [(spec, rotation) for spec in objects for rotation in rotations]:
        if budget is not None and time.perf_counter() - started + last > budget:
            print(f"budget of {budget:g} s reached: {spec.name} r{rotation} and the rest not run", flush=True)
            break
        task_started = time.perf_counter()
        if current is None or current.spec.object_id != spec.object_id:
            current = prepare_object(spec, config)
        result["tasks"].append(check_task(current, rotation, config, view_space, chosen))
        result["summary"] = summary(result["tasks"], [v.label for v in chosen])
        result["seconds"] = time.perf_counter() - started
        result["complete"] = len(result["tasks"]) == len(objects) * len(rotations)
        last = time.perf_counter() - task_started
        saved(result)
    result["seconds"] = time.perf_counter() - started
    saved(result)
    return result


def check_task(
    prepared: PreparedObject, rotation: int, config: GenerationConfig, view_space: ViewSpace, chosen: Sequence[Variant]
) -> dict[str, Any]:
    """One task on the reference, then on each variant (one that raises is recorded), compared."""
    runs = {REFERENCE: run_variant(prepared, rotation, config, view_space, Variant(REFERENCE, "cpu"))}
    errors: dict[str, str] = {}
    for variant in chosen:
        try:
            runs[variant.label] = run_variant(prepared, rotation, config, view_space, variant)
        except Exception as error:  # reported, and the other tasks still run
            errors[variant.label] = failed(variant.label, error)
    compared = {label: compare_runs(runs[REFERENCE], run) for label, run in runs.items() if label != REFERENCE}
    for line in progress_lines(prepared.spec.name, rotation, runs, compared, errors):
        print(line, flush=True)
    return task_entry(prepared.spec, rotation, runs, compared, errors)


def task_entry(
    spec: ObjectSpec, rotation: int, runs: dict[str, TaskRun], compared: dict[str, Comparison], errors: dict[str, str]
) -> dict[str, Any]:
    base = runs[REFERENCE]
    return {
        "object": spec.name,
        "object_id": spec.object_id,
        "rotation": rotation,
        "refinements": len(base.refinements),
        "samples": len(base.labels),
        "runs": {label: run_json(run) for label, run in runs.items()},
        "comparisons": {label: c.to_json() for label, c in compared.items()},
        "errors": errors,
    }


def progress_lines(
    name: str, rotation: int, runs: dict[str, TaskRun], compared: dict[str, Comparison], errors: dict[str, str]
) -> list[str]:
    base = runs[REFERENCE]
    lines = [f"{name} r{rotation}: {REFERENCE} task {base.task_seconds:.2f} s (refine {base.refine_seconds:.2f} s)"]
    for label, c in compared.items():
        run = runs[label]
        lines.append(
            f"  {label}: task {run.task_seconds:.2f} s (refine {run.refine_seconds:.2f} s); R(O) identical "
            f"{c.singles_identical}/{c.singles} views {c.cases_identical}/{c.cases} cases, keys differing "
            f"{c.differing_keys} (max {100 * c.share_max:.3f} %, mean {100 * c.share_mean:.4f} %), "
            f"max |dp| {c.max_prob_diff:.2e}; labels identical {c.labels_identical} "
            f"({c.labels_differing}/{c.samples} differ)"
        )
    lines += [f"  {label}: error {message.splitlines()[-1]}" for label, message in errors.items()]
    return lines


def cuda_problem(device: str) -> str | None:
    """Why ``device`` cannot be checked here, in one line (None when it can)."""
    if device == "cpu":
        return None
    if not device.startswith("cuda"):
        return f"gpu_check: --device {device!r}: use cuda (or cuda:N), or cpu to check the script itself"
    if not torch.cuda.is_available():
        build = f"CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        return (
            f"gpu_check: --device {device} but torch {torch.__version__} ({build}) sees no CUDA device; "
            "run it on a GPU machine, or pass --device cpu to check the script itself"
        )
    return None


def variants(device: str, repeat: bool, no_tf32: bool) -> list[Variant]:
    chosen = [Variant(device, device)]
    if repeat:
        chosen.append(Variant(f"{device} again", device))
    if no_tf32:
        chosen.append(Variant(f"{device} fp32", device, tf32=False))
    return chosen


def environment(device: str) -> dict[str, Any]:
    """Versions and the device: a result means little without them."""
    cuda = device.startswith("cuda")
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "cudnn": torch.backends.cudnn.version() if cuda else None,
        "device": device,
        "device_name": torch.cuda.get_device_name(device) if cuda else cpu_model(),
        "device_capability": list(torch.cuda.get_device_capability(device)) if cuda else None,
        "cuda_driver": command_output(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"])
        if cuda
        else None,
        "torch_threads_in_tasks": 1,
        "packages": {name: package_version(name) for name in PACKAGES},
        "tf32_default": {
            "matmul_allow_tf32": bool(torch.backends.cuda.matmul.allow_tf32),
            "cudnn_allow_tf32": bool(torch.backends.cudnn.allow_tf32),
            "float32_matmul_precision": torch.get_float32_matmul_precision(),
            "fp32_precision": {
                name: getattr(owner, "fp32_precision", None)
                for name, owner in (
                    ("cuda.matmul", torch.backends.cuda.matmul),
                    ("cudnn.conv", getattr(torch.backends.cudnn, "conv", None)),
                )
            },
        },
    }


def package_version(name: str) -> str | None:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").is_file() else []:
        if line.startswith("model name"):
            return line.partition(":")[2].strip()
    return platform.processor() or platform.machine()


def command_output(command: list[str]) -> str | None:
    try:
        return subprocess.run(command, capture_output=True, text=True, timeout=30).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def read_objects(path: Path) -> list[ObjectSpec]:
    listing = read_objects_file(path)
    for error in listing.errors:
        print(f"(skipped) {error}", flush=True)
    if not listing.objects:
        raise DatagenError(f"{path} lists no usable object")
    return listing.objects


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--device", default="cuda", help="the device to check against the CPU (default cuda)")
    parser.add_argument("--objects", type=Path, default=DEMO_OBJECTS, help="objects file (default the demo's 8)")
    parser.add_argument("--rotations", type=int, nargs="+", default=[0], help="rotation indices (default 0)")
    parser.add_argument("--config", type=Path, default=None, help="config TOML (default: the default config)")
    parser.add_argument("--repeat", action="store_true", help="also run each task on the device a second time")
    parser.add_argument("--no-tf32", action="store_true", help="also run each task on the device with TF32 off")
    parser.add_argument("--out", type=Path, default=None, help=f"folder for {JSON_NAME} and {MARKDOWN_NAME}")
    parser.add_argument("--budget", type=float, default=None, help="seconds after which no new task starts")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    problem = cuda_problem(args.device)
    if problem is not None:
        print(problem, file=sys.stderr, flush=True)
        return 2
    try:
        config = load_config(args.config)
        if bad := [r for r in args.rotations if not 0 <= r < config.rotations]:
            raise DatagenError(f"rotations {bad} are outside 0..{config.rotations - 1}")
        objects = read_objects(args.objects)
        base_refiner(config, "cpu")
    except DatagenError as error:
        print(f"gpu_check: {error}", file=sys.stderr, flush=True)
        return 2
    chosen = variants(args.device, args.repeat, args.no_tf32)
    command = "python -m benchmarks.generation.gpu_check " + " ".join(sys.argv[1:] if argv is None else argv)
    machine = environment(args.device)
    header: dict[str, Any] = {"command": command, "environment": machine}
    print(
        f"gpu_check: {len(objects)} objects x {len(args.rotations)} rotations on {machine['device_name']}"
        f" (torch {torch.__version__}, CUDA {torch.version.cuda}); reference cpu; variants "
        + ", ".join(v.label for v in chosen),
        flush=True,
    )

    def save(result: dict[str, Any]) -> None:
        if args.out is None:
            return
        whole = {**header, "finished": datetime.now(UTC).isoformat(timespec="seconds"), **result}
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / JSON_NAME).write_text(json.dumps(whole, indent=1, sort_keys=True) + "\n")
        (args.out / MARKDOWN_NAME).write_text(markdown(whole))

    result = check(objects, args.rotations, config, chosen, save, args.budget)
    print(markdown({**header, "finished": datetime.now(UTC).isoformat(timespec="seconds"), **result}), flush=True)
    if args.out is not None:
        print(f"wrote {args.out / JSON_NAME} and {args.out / MARKDOWN_NAME}", flush=True)
    errors = sum(len(task["errors"]) for task in result["tasks"])
    if errors:
        print(f"gpu_check: {errors} device runs raised (tracebacks above); the report lists them", flush=True)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
