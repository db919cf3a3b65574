"""The engine and objects at 1k, 10k and 100k tasks: every job command's time and memory against N.

    python -m benchmarks.scale.engine --source before=/tmp/base-engine --source after=. \\
        --out benchmarks/scale/results/engine.md --plot benchmarks/scale/results/engine.png

The engine runs for real: the SQLite ledger (`jobs.ledger`), the driver (`run_job`, through
`datagen.api.resume` as `datagen resume` runs it) and a local Ray scheduling every task, over
`datagen.engine.worker.empty_task`, a task body that computes and writes nothing, so what is left is
the engine's own cost per task. Per size N and source tree, each step in a fresh process:

1. ``datagen submit --detach`` of an objects file of N/8 synthetic meshes at 8 rotations (plan:
   read and hash every mesh; enqueue N tasks);
0. ``datagen status`` of an empty ledger: what every command costs before it does anything;
2. ``datagen status`` and ``datagen status JOB`` (N pending tasks);
3. ``datagen cancel JOB`` (cancels N pending tasks);
4. the driver run (`benchmarks/scale/drive.py`): resume the cancelled job and run its N empty tasks
   on a 2-CPU local Ray; the driver's CPU and wall per task and its peak memory, and the progress
   every 1 % (whether a task costs more late in the run than early);
5. ``datagen status`` and ``datagen status JOB`` again (N done tasks), then the resume of the
   finished job (nothing to run: reopen, look, finish).

A driver run that passes ``--deadline`` seconds is stopped (SIGINT) and reported with how many tasks
it finished: the starting commit's engine runs 100k tasks in hours. The objects side
(`benchmarks.scale.objects`) measures ``objects synth``, ``objects scan``, ``objects show`` and
``submit --detach`` at 1k, 10k and 50k lines.

Several ``--source LABEL=DIR`` measure several trees (a worktree of an older commit, say) with the
same inputs; every figure is cached in ``WORK/measurements.json``, so a stopped run goes on where it
stopped (``--fresh`` measures again). The report says per row how it grows: the ratio of each size
to the one before, and the slope of a log-log fit (1 is linear in N).
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from benchmarks.common import REPO_ROOT, add_report_options, check_report
from benchmarks.scale.measure import Cache, Measurement, growth, machine_line, run_measured
from benchmarks.scale.objects import ROTATIONS, ensure_synth, first_lines, objects_cases, source_env

SIZES = (1_000, 10_000, 100_000)
LINES = (1_000, 10_000, 50_000)
DRIVE = Path(__file__).with_name("drive.py")
CONFIG = f'rotations = {ROTATIONS}\nrefiner = "none"\n'
"""The engine jobs' config: tasks never run, so the refiner only enters the config hash."""

ENGINE_ROWS = (
    ("floor", "`status` of an empty ledger (start-up: imports, open)"),
    ("submit", "`submit --detach` (plan + enqueue N tasks)"),
    ("status-pending", "`status` (N pending)"),
    ("status-job-pending", "`status JOB` (N pending)"),
    ("cancel", "`cancel JOB` (N pending)"),
    ("run", "`resume JOB`: driver runs N empty tasks"),
    ("status-done", "`status` (N done)"),
    ("status-job-done", "`status JOB` (N done)"),
    ("resume-done", "`resume JOB` (all done: nothing to run)"),
)
OBJECT_ROWS = (
    ("synth", "`objects synth --count L`"),
    ("scan", "`objects scan` (ShapeNet-shaped tree of L models)"),
    ("show", "`objects show` (L synth lines)"),
    ("submit", "`submit --detach` (L synth lines, 8 rotations: 8L tasks)"),
)


def datagen_command() -> list[str]:
    """The installed ``datagen`` script (it imports whichever ``datagen`` PYTHONPATH names first)."""
    return [str(Path(sys.executable).with_name("datagen"))]


def task_counts(home: Path, job: str) -> dict[str, int]:
    """The job's task states, read from the ledger file directly (any source tree's ledger)."""
    with sqlite3.connect(home / "ledger.db") as db:
        rows = db.execute("SELECT state, COUNT(*) FROM tasks WHERE job_id = ? GROUP BY state", (job,)).fetchall()
    return {state: int(n) for state, n in rows}


def engine_case(
    work: Path,
    label: str,
    source: Path,
    size: int,
    synth: Path,
    cache: Cache,
    env: Mapping[str, str],
    workers: int,
    deadline: float,
    say: Callable[[str], None],
) -> dict[str, Measurement]:
    """Every engine row at ``size`` tasks for one source tree (cached as a whole)."""
    key = f"engine|{label}|{size}"
    cached = cache.get(key)
    if cached is not None:
        return {name: Measurement.from_json(m) for name, m in cached.items()}
    base = work / label / f"engine-{size}"
    if base.exists():
        shutil.rmtree(base)
    base.mkdir(parents=True)
    home = base / "home"
    objects = first_lines(synth / "objects.txt", size // ROTATIONS, base / "objects.txt")
    config = base / "engine.toml"
    config.write_text(CONFIG)
    datagen = datagen_command()
    rows: dict[str, Measurement] = {}

    def measure(name: str, args: list[str], **options: Any) -> Measurement:
        say(f"{label} {size} tasks: {name}")
        measured = run_measured(args, cwd=source, env=env, stdout=base / f"{name}.log", **options)
        if measured.rc != 0 and not measured.stopped:
            raise RuntimeError(f"{name} failed ({measured.rc}): see {base / name}.log")
        rows[name] = measured
        return measured

    measure("floor", [*datagen, "status", "--home", str(base / "empty-home")])
    measure(
        "submit",
        [*datagen, "submit", "--objects", str(objects), "--config", str(config), "--home", str(home), "--detach"],
    )
    job = (base / "submit.log").read_text().split()[1].rstrip(":")
    measure("status-pending", [*datagen, "status", "--home", str(home)])
    measure("status-job-pending", [*datagen, "status", job, "--home", str(home)])
    measure("cancel", [*datagen, "cancel", job, "--home", str(home)])
    drive = [sys.executable, str(DRIVE), "--home", str(home), "--job", job, "--workers", str(workers)]
    cancel = [*datagen, "cancel", job, "--home", str(home)]

    def stop_the_driver() -> None:  # as a person stops a job: the driver sees it at its next tick
        subprocess.run(cancel, cwd=source, env=dict(env), capture_output=True, check=False)

    run = measure(
        "run",
        [*drive, "--report", str(base / "run.json")],
        deadline=deadline,
        on_deadline=stop_the_driver,
        report=base / "run.json",
    )
    counts = task_counts(home, job)
    rows["run"] = Measurement(**{**run.to_json(), "extra": {**run.extra, "counts": counts}})
    if counts.get("done", 0) == size:
        measure("status-done", [*datagen, "status", "--home", str(home)])
        measure("status-job-done", [*datagen, "status", job, "--home", str(home)])
        measure("resume-done", [*drive, "--report", str(base / "resume.json")], report=base / "resume.json")
    cache.put(key, {name: m.to_json() for name, m in rows.items()})
    return rows


# ---------------------------------------------------------------------------------------------------------
# the report
# ---------------------------------------------------------------------------------------------------------


def figures(name: str, measured: Measurement) -> tuple[float, float, float]:
    """(CPU s, wall s, peak MiB) of a row; for a driver run, the driver's own over the run (the
    process's, Ray's start included, when it was killed before it could say)."""
    if name in ("run", "resume-done") and "run_cpu_s" in measured.extra:
        extra = measured.extra
        return extra["run_cpu_s"], extra["run_wall_s"], extra["peak_mb"]
    return measured.cpu, measured.wall, measured.peak_mb


def _k(n: int) -> str:
    return f"{n // 1000}k" if n % 1000 == 0 else str(n)


def table(
    title: str,
    rows: tuple[tuple[str, str], ...],
    results: Mapping[int, Mapping[str, Measurement]],
    unit: str,
) -> list[str]:
    """Rows x sizes: CPU s / wall s / peak MiB per size, then how CPU and memory grow."""
    sizes = sorted(results)
    header = ["command", *(f"{_k(n)} {unit}: CPU s / wall s / MiB" for n in sizes), "CPU growth", "memory growth"]
    lines = [f"#### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, text in rows:
        cells, cpu, memory = [], {}, {}
        for n in sizes:
            measured = results[n].get(name)
            if measured is None:
                cells.append("-")
                continue
            c, w, m = figures(name, measured)
            stopped = " (stopped)" if measured.stopped else ""
            cells.append(f"{c:,.2f} / {w:,.2f} / {m:,.0f}{stopped}")
            if not measured.stopped:
                cpu[n], memory[n] = c, m
        lines.append(f"| {text} | " + " | ".join(cells) + f" | {growth(cpu)} | {growth(memory)} |")
    return [*lines, ""]


def per_task_table(label: str, results: Mapping[int, Mapping[str, Measurement]]) -> list[str]:
    """The driver run per task: CPU and wall ms a task, early against late in the run, peak memory."""
    lines = [
        f"#### {label}: the driver per task (`resume JOB` over N empty tasks, 2 worker CPUs)",
        "",
        "| N | tasks done | driver CPU ms/task | wall ms/task | CPU ms/task, first 10 % | CPU ms/task, last 10 % "
        "| driver RSS before run MiB | driver peak MiB | progress ticks |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for n in sorted(results):
        run = results[n].get("run")
        if run is None:
            continue
        extra = run.extra
        done = extra.get("counts", {}).get("done", 0)
        cpu, wall, peak = figures("run", run)
        early, late = _curve_slices(extra.get("curve", []))
        stopped = f" (stopped at {wall:,.0f} s)" if run.stopped else ""
        if "run_cpu_s" not in extra:
            stopped = f" (killed at {wall:,.0f} s: the process's totals)"
        before = f"{extra['rss_before_mb']:,.0f}" if "rss_before_mb" in extra else "-"
        lines.append(
            f"| {_k(n)} | {done:,}{stopped} | {1000 * cpu / max(done, 1):.2f} | {1000 * wall / max(done, 1):.2f} "
            f"| {early} | {late} | {before} | {peak:,.0f} | {extra.get('ticks', '-')} |"
        )
    return [*lines, ""]


def _curve_slices(curve: list[list[float]]) -> tuple[str, str]:
    """CPU ms per task over the first and the last tenth of the progress curve."""
    if len(curve) < 3:
        return "-", "-"
    tenth = max(1, len(curve) // 10)

    def rate(a: list[float], b: list[float]) -> str:
        tasks = b[2] - a[2]
        return f"{1000 * (b[1] - a[1]) / tasks:.2f}" if tasks > 0 else "-"

    return rate(curve[0], curve[tenth]), rate(curve[-1 - tenth], curve[-1])


def comparison(
    labels: list[str],
    rows: tuple[tuple[str, str], ...],
    results: Mapping[str, Mapping[int, Mapping[str, Measurement]]],
    unit: str,
) -> list[str]:
    """The first source against the last, per row and size: CPU seconds and peak MiB, and their ratio."""
    first, last = labels[0], labels[-1]
    sizes = sorted(set(results[first]) & set(results[last]))
    header = ["command", *(f"{_k(n)} {unit}: CPU s {first} -> {last} (peak MiB)" for n in sizes)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, text in rows:
        cells = []
        for n in sizes:
            a, b = results[first][n].get(name), results[last][n].get(name)
            if a is None or b is None:
                cells.append("-")
                continue
            (ca, _, ma), (cb, _, mb) = figures(name, a), figures(name, b)
            if name == "run":  # per task: a stopped run finished fewer
                ca, cb = ca / _done(a, n), cb / _done(b, n)
                cells.append(f"{1000 * ca:.2f} -> {1000 * cb:.2f} ms/task (x{ca / cb:.0f}); {ma:,.0f} -> {mb:,.0f}")
                continue
            stopped = " (stopped)" if a.stopped else ""
            cells.append(f"{ca:,.2f}{stopped} -> {cb:,.2f} (x{ca / max(cb, 1e-9):.1f}); {ma:,.0f} -> {mb:,.0f}")
        lines.append(f"| {text} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _done(measured: Measurement, size: int) -> int:
    return int(measured.extra.get("counts", {}).get("done", size)) or 1


def plot(
    path: Path,
    engine: Mapping[str, Mapping[int, Mapping[str, Measurement]]],
    objects: Mapping[str, Mapping[int, Mapping[str, Measurement]]],
) -> None:
    """Log-log CPU seconds and peak MiB against N (tasks, or lines), one line per row and source."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("engine", engine, ENGINE_ROWS, "tasks"), ("objects", objects, OBJECT_ROWS, "objects-file lines")]
    panels = [p for p in panels if p[1]]
    figure, axes = plt.subplots(len(panels), 2, figsize=(13, 5 * len(panels)), squeeze=False)
    styles = ["--", "-", ":", "-."]
    palette = plt.get_cmap("tab20")  # a colour a row: more rows than the default cycle's 10
    for row, (title, results, rows, unit) in enumerate(panels):
        for index, label in enumerate(sorted(results, key=list(results).index)):
            for colour, (name, text) in enumerate(rows):
                points = [
                    (n, figures(name, results[label][n][name]))
                    for n in sorted(results[label])
                    if name in results[label][n] and not results[label][n][name].stopped
                ]
                if not points:
                    continue
                xs = [n for n, _ in points]
                kwargs = {"color": palette(colour % 20), "linestyle": styles[index % len(styles)], "marker": "o"}
                axes[row][0].plot(xs, [max(f[0], 1e-3) for _, f in points], label=f"{label}: {text}", **kwargs)
                axes[row][1].plot(xs, [f[2] for _, f in points], label=f"{label}: {text}", **kwargs)
        for column, what in enumerate(("CPU seconds", "peak MiB")):
            axis = axes[row][column]
            axis.set_xscale("log")
            axis.set_yscale("log")
            axis.set_xlabel(unit)
            axis.set_ylabel(what)
            axis.set_title(f"{title}: {what} against {unit}")
            axis.grid(True, which="both", alpha=0.3)
        axes[row][0].legend(fontsize=6, loc="upper left")
    figure.tight_layout()
    figure.savefig(path, dpi=110)


def report(
    args: argparse.Namespace,
    labels: list[str],
    engine: dict[str, dict[int, dict[str, Measurement]]],
    objects: dict[str, dict[int, dict[str, Measurement]]],
    synth: dict[int, Measurement],
    machine: str,
    commits: dict[str, str],
) -> str:
    command = "python -m benchmarks.scale.engine " + " ".join(sys.argv[1:])
    lines = [
        "# The engine and objects at scale",
        "",
        f"`{command}` ({datetime.date.today().isoformat()}; {machine}; the machine is shared with other work,",
        "so compare CPU seconds; wall seconds are beside them). Sources: "
        + ", ".join(f"{label} = {commits[label]}" for label in labels)
        + ".",
        "",
    ]
    if engine:
        lines += ["## Engine", ""]
        if len(labels) > 1:
            lines += [f"### {labels[0]} against {labels[-1]}", ""]
            lines += comparison(labels, ENGINE_ROWS, engine, "tasks")
        for label in labels:
            if label in engine:
                lines += [f"### {label}", ""]
                lines += table(f"{label}: every command", ENGINE_ROWS, engine[label], "tasks")
                lines += per_task_table(label, engine[label])
    if objects:
        lines += ["## Objects files", ""]
        with_synth = {
            label: {n: {**rows, **({"synth": synth[n]} if n in synth else {})} for n, rows in by_size.items()}
            for label, by_size in objects.items()
        }
        if len(labels) > 1:
            lines += [f"### {labels[0]} against {labels[-1]}", ""]
            lines += comparison(labels, OBJECT_ROWS[1:], objects, "lines")
        for label in labels:
            if label in objects:
                lines += table(f"{label}: objects files of L lines", OBJECT_ROWS, with_synth[label], "lines")
        objects.update(with_synth)
    return "\n".join(lines) + "\n"


def describe(source: Path) -> str:
    """The source tree's commit (and whether it has changes not committed)."""
    try:
        head = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(source), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return str(source)
    return f"`{head}`{' with changes' if dirty else ''} ({source})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("/tmp/datagen-scale"), help="inputs, ledgers, cache")
    parser.add_argument("--source", action="append", default=[], help="LABEL=DIR, a source tree to measure")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="task counts (engine)")
    parser.add_argument("--lines", type=int, nargs="+", default=list(LINES), help="objects-file lines")
    parser.add_argument("--parts", nargs="+", default=["engine", "objects"], choices=["engine", "objects"])
    parser.add_argument("--workers", type=int, default=2, help="local Ray worker CPUs of a driver run")
    parser.add_argument("--deadline", type=float, default=1800.0, help="seconds before a driver run is stopped")
    parser.add_argument("--fresh", action="store_true", help="measure again what the cache holds")
    add_report_options(parser, None, "results file (Markdown)")
    parser.add_argument("--plot", type=Path, help="plot (PNG)")
    args = parser.parse_args()
    check_report(parser, args.out, args.replace)
    sources = [tuple(s.split("=", 1)) for s in args.source] or [("after", str(REPO_ROOT))]
    labels = [label for label, _ in sources]
    args.work.mkdir(parents=True, exist_ok=True)
    cache_file = args.work / "measurements.json"
    if args.fresh and cache_file.exists():
        cache_file.unlink()
    cache = Cache(cache_file)
    machine = machine_line()

    def say(text: str) -> None:
        print(f"[{datetime.datetime.now():%H:%M:%S}] {text}", flush=True)

    base_env = source_env(REPO_ROOT, os.environ)
    lines_needed = sorted(set(args.lines if "objects" in args.parts else []))
    if "engine" in args.parts and max(lines_needed, default=0) < max(args.sizes) // ROTATIONS:
        lines_needed.append(max(args.sizes) // ROTATIONS)  # the engine's objects files are its first lines
    synth_sets = {}
    for count in lines_needed:
        say(f"objects synth --count {count}")
        synth_sets[count] = ensure_synth(args.work, count, cache, base_env, datagen_command())
    largest = synth_sets[max(synth_sets)]
    engine: dict[str, dict[int, dict[str, Measurement]]] = {}
    objects: dict[str, dict[int, dict[str, Measurement]]] = {}
    for label, directory in sources:
        source = Path(directory).resolve()
        env = source_env(source, os.environ)
        if "objects" in args.parts:
            for count in sorted(args.lines):
                objects.setdefault(label, {})[count] = objects_cases(
                    args.work, label, source, count, cache, env, datagen_command(), say
                )
        if "engine" in args.parts:
            for size in sorted(args.sizes):
                engine.setdefault(label, {})[size] = engine_case(
                    args.work, label, source, size, largest, cache, env, args.workers, args.deadline, say
                )
    synth = {n: Measurement.from_json(cache.get(f"synth|{n}")) for n in args.lines if cache.get(f"synth|{n}")}
    commits = {label: describe(Path(directory).resolve()) for label, directory in sources}
    text = report(args, labels, engine, objects, synth, machine, commits)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    if args.plot:
        plot(args.plot, engine, objects)


if __name__ == "__main__":
    main()
