"""``datagen submit | status | cancel | resume | serve``: jobs on the local or a remote Ray cluster.

Plain functions over `datagen.api` and `datagen.engine.serve`; `datagen.cli.main` registers them.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.text import Text

from datagen.cli.common import Cell, IntervalProgress, console, error_console, plural, print_rows, say, user_errors
from datagen.settings import RunSettings, default_home, ledger_for
from jobs.ledger import DONE, FAILED, RUNNING, Job

if TYPE_CHECKING:  # the engine (Ray, trimesh, the pipeline) is imported by the commands that run jobs only
    from datagen.engine.driver import JobProgress, ProgressCallback

HomeOption = Annotated[
    Path | None,
    typer.Option("--home", help="Ledger and default datasets folder (default: DATAGEN_HOME or ~/.datagen)."),
]
AddressOption = Annotated[
    str | None, typer.Option("--address", help="Ray cluster address (default: RAY_ADDRESS, else a local Ray).")
]
WorkersOption = Annotated[int | None, typer.Option("--workers", min=1, help="Local Ray worker CPUs (default: all).")]


GpusOption = Annotated[
    float,
    typer.Option(
        "--refiner-gpus", min=0.0, max=1.0, help="GPU share per task; > 0 runs the poco refiner on CUDA (default 0)."
    ),
]


SharedOption = Annotated[
    bool,
    typer.Option(
        "--shared-refiner",
        help="One POCO network per node shared by its tasks (on its GPU with --refiner-gpus); same samples.",
    ),
]
BatchOption = Annotated[
    int,
    typer.Option(
        "--refiner-batch",
        min=1,
        max=256,
        help="Jobs per encoder call on a shared refiner (default 1: bit for bit; more for a GPU).",
    ),
]


def _settings(
    home: Path | None,
    out: str | None = None,
    address: str | None = None,
    workers: int | None = None,
    refiner_gpus: float = 0.0,
    shared_refiner: bool = False,
    refiner_batch: int = 1,
) -> RunSettings:
    base = RunSettings()
    return RunSettings(
        home=home or default_home(),
        out=out,
        ray_address=address or base.ray_address,
        num_workers=workers,
        refiner_gpus=refiner_gpus,
        shared_refiner=shared_refiner,
        refiner_batch=refiner_batch,
    )


@contextmanager
def _progress_display(title: str) -> Iterator[ProgressCallback]:
    with IntervalProgress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[samples]} samples, {task.fields[failed]} failed"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
    ) as progress:
        bar = progress.add_task(title, total=None, samples=0, failed=0)
        said = ""

        def update(state: JobProgress) -> None:
            nonlocal said
            if state.waiting and state.waiting != said:
                progress.console.print(state.waiting, markup=False, highlight=False, soft_wrap=True)
            said = state.waiting
            progress.update(
                bar, total=state.total, completed=state.done + state.failed, samples=state.samples, failed=state.failed
            )

        yield update


def _report(job: Job) -> None:
    """The job's outcome on stdout; each failed object or line as one ``error:`` line on stderr,
    never wrapped (logs keep FILE:LINE and paths whole)."""
    summary = job.summary or {}
    colour = "green" if job.state == DONE else "red"
    console.print(Text.assemble("job ", (job.job_id, "bold"), " ", (job.state, colour)), soft_wrap=True)
    if summary:
        refused = summary.get("refused_lines", 0)
        lines = f"; {refused} objects-file line{'s' if refused != 1 else ''} refused" if refused else ""
        console.print(
            f"{summary.get('done', 0)}/{summary.get('tasks', 0)} tasks done, {summary.get('samples', 0)} samples, "
            f"{summary.get('failed', 0)} failed{lines}",
            highlight=False,
            soft_wrap=True,
        )
        if summary.get("swept"):
            examples = summary.get("swept_examples", [])
            more = ", ..." if summary["swept"] > len(examples) else ""
            say(f"removed {summary['swept']} leftover files of interrupted attempts ({', '.join(examples)}{more})")
        if summary.get("sweep_error"):
            error_console.print(
                f"warning: leftovers of interrupted attempts not removed: {summary['sweep_error']}",
                markup=False,
                highlight=False,
                soft_wrap=True,
            )
        if "step_seconds" in summary:
            from datagen.pipeline.step_timing import step_lines, totals_from_json

            for line in step_lines(totals_from_json(summary["step_seconds"])):
                say(line)
        for line in summary.get("warnings", []):
            error_console.print(Text("warning: ", style="yellow") + Text(str(line)), highlight=False, soft_wrap=True)
        for line in [*summary.get("line_errors", []), *summary.get("failures", [])]:
            error_console.print(Text("error: ", style="red") + Text(str(line)), highlight=False, soft_wrap=True)
    console.print(Text("dataset: ") + Text(job.out, style="bold"), highlight=False, soft_wrap=True)


def submit(
    objects: Annotated[Path, typer.Option("--objects", "-o", help="Objects file (one mesh or builtin:NAME per line).")],
    config: Annotated[Path | None, typer.Option("--config", "-c", help="Generation config (TOML).")] = None,
    out: Annotated[str | None, typer.Option("--out", help="Dataset URL (default: HOME/datasets/JOB).")] = None,
    address: AddressOption = None,
    detach: Annotated[bool, typer.Option("--detach", help="Only enqueue for a running 'datagen serve'.")] = False,
    workers: WorkersOption = None,
    refiner_gpus: GpusOption = 0.0,
    shared_refiner: SharedOption = False,
    refiner_batch: BatchOption = 1,
    home: HomeOption = None,
    strict: Annotated[
        bool,
        typer.Option("--strict", help="Refuse the job when an objects-file line names no usable object."),
    ] = False,
) -> None:
    """Create a dataset job and run it now with a live progress display (or enqueue it). Every line's
    mesh file is read first: a bad line is named at once and left out (--strict: the job is refused)."""
    from datagen import api

    with user_errors():
        settings = _settings(home, out, address, workers, refiner_gpus, shared_refiner, refiner_batch)

        def skipped(error: str) -> None:
            error_console.print(f"skipped {error}", markup=False, highlight=False, soft_wrap=True)

        job = api.enqueue(objects, config, settings, strict=strict, on_line_error=skipped)
        ledger = api.ledger_for(settings)
        try:
            tasks = sum(ledger.task_counts(job.job_id).values())
        finally:
            ledger.close()
        console.print(
            f"job {job.job_id}: {plural(tasks, 'task')} -> {job.out}",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )
        if detach:
            console.print("queued; a running 'datagen serve' on this ledger will take it")
            return
        with _progress_display("tasks") as update:
            job = api.resume(job.job_id, settings, progress=update)
        _report(job)
        if job.state != DONE:
            raise typer.Exit(1)


def resume(
    job_id: Annotated[str, typer.Argument(help="Job id (see 'datagen status').")],
    address: AddressOption = None,
    workers: WorkersOption = None,
    refiner_gpus: GpusOption = 0.0,
    shared_refiner: SharedOption = False,
    refiner_batch: BatchOption = 1,
    home: HomeOption = None,
) -> None:
    """Run what is not done of a job again; committed tasks are kept, never recomputed."""
    from datagen import api

    with user_errors():
        settings = _settings(home, None, address, workers, refiner_gpus, shared_refiner, refiner_batch)
        with _progress_display("tasks") as update:
            job = api.resume(job_id, settings, progress=update)
        _report(job)
        if job.state != DONE:
            raise typer.Exit(1)


def status(
    job_id: Annotated[str | None, typer.Argument(help="Job id; all jobs when omitted.")] = None,
    home: HomeOption = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="One JSON object (jobs; with JOB, its tasks too) instead of tables.")
    ] = False,
) -> None:
    """Jobs and their task counts (one job: every task, one line each outside a terminal)."""
    with user_errors():
        ledger = ledger_for(_settings(home))
        jobs = [ledger.job(job_id)] if job_id else ledger.jobs()
        if as_json:
            try:
                _print_status_json(ledger, jobs, job_id)
            finally:
                ledger.close()
            return
        try:
            job_rows: list[list[Cell]] = []
            hints = []
            lost_jobs = set()
            for job in jobs:
                counts = ledger.task_counts(job.job_id)
                state = job.state
                lost = ledger.lost_driver(job.job_id)
                if lost is not None:
                    lost_jobs.add(job.job_id)
                    state = f"{job.state} (driver lost {_ago(lost.since)} ago)"
                    who = f"its driver ({lost.driver.describe()}) is gone" if lost.driver else "no driver holds it"
                    hints.append(
                        f"job {job.job_id}: {who}, last heard from {_ago(lost.since)} ago; "
                        f"run `datagen resume {job.job_id}` to finish it"
                    )
                job_rows.append(
                    [
                        job.job_id,
                        state,
                        str(sum(counts.values())),
                        str(counts.get("done", 0)),
                        str(counts.get("failed", 0)),
                        str(counts.get("running", 0)),
                        job.out,
                    ]
                )
            # Whole lines off a terminal: the id that `resume` and `cancel` take is copied from a pipe.
            print_rows(["job", "state", "tasks", "done", "failed", "running", "dataset"], job_rows, whole=["job"])
            for hint in hints:
                say(hint)
            for job in jobs:
                if job.state == FAILED:
                    say(f"job {job.job_id} failed: {failure_reason(job)}")
            if job_id:
                lost_tasks = job_id in lost_jobs
                rows: Iterator[list[Cell]] = (
                    [
                        task.task_id,
                        f"{task.state} (driver lost)" if lost_tasks and task.state == RUNNING else task.state,
                        str(task.attempts),
                        str(task.samples or ""),
                        task.placement or "",
                        Text(task.error or "", style="red"),
                    ]
                    for task in ledger.each_task(job_id)
                )
                print_rows(["task", "state", "attempts", "samples", "placement", "error"], rows, whole=["task"])
        finally:
            ledger.close()


def failure_reason(job: Job) -> str:
    """Why a job failed, in one line: the error that stopped it, else what failed of it (the first one named)."""
    summary = job.summary or {}
    if summary.get("error"):
        return str(summary["error"])
    parts = []
    failed, refused = int(summary.get("failed", 0)), int(summary.get("refused_lines", 0))
    if failed:
        parts.append(f"{plural(failed, 'task')} failed")
    if refused:
        parts.append(f"{plural(refused, 'objects-file line')} named no usable object")
    first = [*summary.get("line_errors", []), *summary.get("failures", [])][:1]
    reason = " and ".join(parts) or "see `datagen status JOB`"
    return f"{reason} (first: {first[0]})" if first else reason


def _print_status_json(ledger: Any, jobs: list[Any], job_id: str | None) -> None:
    """`status --json`: ``{"jobs": [...]}`` and, for one job, ``"tasks"``, written a task at a time (a job
    of 100,000 tasks is never held as one document)."""
    rows = []
    for job in jobs:
        counts = ledger.task_counts(job.job_id)
        lost = ledger.lost_driver(job.job_id)
        rows.append(
            {
                "job_id": job.job_id,
                "state": job.state,
                "driver_lost": lost is not None,
                "tasks": sum(counts.values()),
                "counts": dict(sorted(counts.items())),
                "dataset": job.out,
            }
        )
    out = sys.stdout
    out.write('{"jobs": ' + json.dumps(rows))
    if job_id:
        out.write(', "tasks": [')
        for number, task in enumerate(ledger.each_task(job_id)):
            entry = {
                "task_id": task.task_id,
                "state": task.state,
                "attempts": task.attempts,
                "samples": task.samples,
                "placement": task.placement,
                "error": task.error,
            }
            out.write(("," if number else "") + "\n" + json.dumps(entry))
        out.write("\n]")
    out.write("}\n")
    out.flush()


def _ago(moment: float) -> str:
    """How long ago, for people: ``45 s``, ``3 min``, ``2 h``."""
    seconds = max(0.0, time.time() - moment)
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.0f} h"


def cancel(
    job_id: Annotated[str, typer.Argument(help="Job id.")],
    home: HomeOption = None,
) -> None:
    """Stop a job: running tasks are cancelled, committed shards stay readable."""
    from datagen import api

    with user_errors():
        job = api.cancel(job_id, _settings(home))
        console.print(f"job {job.job_id}: {job.state}", highlight=False)


def serve(
    address: AddressOption = None,
    workers: WorkersOption = None,
    refiner_gpus: GpusOption = 0.0,
    shared_refiner: SharedOption = False,
    refiner_batch: BatchOption = 1,
    home: HomeOption = None,
    poll: Annotated[float, typer.Option(help="Seconds between looks at the queue.")] = 2.0,
    once: Annotated[bool, typer.Option("--once", help="Exit when the queue is empty.")] = False,
) -> None:
    """A long-running driver: takes queued jobs in order and runs them (several may share a ledger)."""
    from datagen.engine.serve import serve as serve_loop

    with user_errors():
        serve_loop(
            _settings(home, None, address, workers, refiner_gpus, shared_refiner, refiner_batch),
            poll=poll,
            once=once,
            report=say,
            error=lambda line: error_console.print(line, markup=False, highlight=False, soft_wrap=True),
        )
