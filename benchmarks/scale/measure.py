"""Measure one command in a fresh process: wall seconds, CPU seconds and peak memory, from the kernel.

Every figure of the scale benchmarks comes from a child process of its own (`run_measured`): the
kernel's own accounting of that process (``os.wait4``: user and system CPU seconds, the largest
resident set), not a sampler, so a short command is measured as well as a long one. A command that
must not run past a deadline gets SIGINT (Python stops where it is and runs its ``finally`` blocks:
a driver leaves the ledger and Ray shuts down), then SIGKILL after a grace period.

The machine is shared (2 cores here, other jobs beside), so CPU seconds are the figure to compare;
wall seconds are reported beside them. Results are kept in a JSON cache beside the work, so a long
run that stopped can go on where it was (`Cache`).
"""

from __future__ import annotations

import itertools
import json
import math
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from benchmarks.common import interruptible_child

GRACE_SECONDS = 60.0
"""How long a command stopped with SIGINT may take to clean up before it is killed."""


@dataclass(frozen=True)
class Measurement:
    """One command, measured by the kernel; ``extra`` holds what the command reported itself."""

    wall: float
    """Seconds from start to exit."""
    cpu: float
    """User + system CPU seconds of the process (and of its children it waited for)."""
    peak_mb: float
    """Largest resident set of the process (or of a waited-for child, whichever was larger), MiB. Linux
    counts the spawning process's resident set at the fork in it, so the harness itself stays small."""
    rc: int
    """Exit status; negative: killed by that signal."""
    stopped: bool = False
    """True when the deadline stopped it."""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_json(data: Mapping[str, Any]) -> Measurement:
        return Measurement(**data)


def run_measured(
    args: Sequence[str],
    *,
    cwd: Path,
    env: Mapping[str, str],
    stdout: Path,
    deadline: float | None = None,
    on_deadline: Callable[[], None] | None = None,
    report: Path | None = None,
) -> Measurement:
    """Run ``args`` with stdout (and stderr) into the file ``stdout``; its measurement.

    At ``deadline`` (seconds) ``on_deadline`` is called to ask the command to stop the way it stops
    on its own (a driver: its job is cancelled in the ledger); `GRACE_SECONDS` later it gets SIGINT,
    and SIGKILL after as long again. ``report`` is a JSON file the command may write about itself
    (its own peak, its driver's CPU): read into ``extra``.
    """
    if report is not None and report.exists():
        report.unlink()
    started = time.perf_counter()
    with stdout.open("wb") as sink:
        process = subprocess.Popen(
            list(args),
            cwd=cwd,
            env=dict(env),
            stdout=sink,
            stderr=subprocess.STDOUT,
            preexec_fn=interruptible_child,
        )
    stopped = threading.Event()

    def stop() -> None:
        stopped.set()
        if on_deadline is not None:
            on_deadline()
            if _exited(process.pid, GRACE_SECONDS):
                return
        _signal(process.pid, signal.SIGINT)
        if not _exited(process.pid, GRACE_SECONDS):
            _signal(process.pid, signal.SIGKILL)

    timer = threading.Timer(deadline, stop) if deadline else None
    if timer is not None:
        timer.daemon = True
        timer.start()
    try:
        _, status, usage = os.wait4(process.pid, 0)
    finally:
        if timer is not None:
            timer.cancel()
    process.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
    wall = time.perf_counter() - started
    extra: dict[str, Any] = {}
    if report is not None and report.exists():
        extra = json.loads(report.read_text())
    return Measurement(
        wall=wall,
        cpu=usage.ru_utime + usage.ru_stime,
        peak_mb=usage.ru_maxrss / 1024,
        rc=process.returncode,
        stopped=stopped.is_set(),
        extra=extra,
    )


def _exited(pid: int, seconds: float) -> bool:
    """Whether the child ended (it is a zombie until reaped) within ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            return True
        if state in ("Z", "X"):
            return True
        time.sleep(0.2)
    return False


def _signal(pid: int, sig: int) -> None:
    """Signal a child that may have exited meanwhile (its pid is not reused before it is reaped)."""
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        return


class Cache:
    """Measurements by key in a JSON file, written after each one, so an interrupted run goes on."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.entries: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}

    def get(self, key: str) -> Any | None:
        return self.entries.get(key)

    def put(self, key: str, value: Any) -> None:
        self.entries[key] = value
        temporary = self.path.with_name(self.path.name + ".tmp")
        temporary.write_text(json.dumps(self.entries, indent=1, sort_keys=True))
        temporary.replace(self.path)


def growth(values: Mapping[int, float]) -> str:
    """How a figure grows with N: the ratio of each size to the one before, and the slope of a
    log-log fit (1 = linear, 0 = flat, 2 = quadratic)."""
    sizes = sorted(n for n, v in values.items() if v > 0)
    if len(sizes) < 2:
        return ""
    ratios = [f"x{values[b] / values[a]:.1f}" for a, b in itertools.pairwise(sizes)]
    xs = [math.log(n) for n in sizes]
    ys = [math.log(values[n]) for n in sizes]
    mean_x, mean_y = sum(xs) / len(xs), sum(ys) / len(ys)
    slope = sum((x - mean_x) * (y - mean_y) for x, y in zip(xs, ys, strict=True)) / sum((x - mean_x) ** 2 for x in xs)
    return f"{' '.join(ratios)} (slope {slope:.2f})"


def machine_line() -> str:
    """CPU model, cores, memory and load average, for the results file."""
    model = "unknown CPU"
    with _quietly():
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    memory = ""
    with _quietly():
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                memory = f", {int(line.split()[1]) / 1024**2:.1f} GiB memory"
    load = ", load average {:.2f} {:.2f} {:.2f} as the report was written".format(*os.getloadavg())
    return f"{model}, {os.cpu_count()} cores{memory}{load}"


@contextmanager
def _quietly() -> Iterator[None]:
    try:
        yield
    except OSError:
        return
