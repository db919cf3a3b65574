"""Where a task's time goes: per-step CPU and wall seconds (`schemas.index.TASK_STEPS`).

A `StepClock` times the steps of one task as they run; the worker's commit record keeps the result
(`schemas.index.TaskTimings`), and `step_totals` sums it over the commit records of a job or a
dataset. CPU time is the process's (`time.process_time`): a worker runs one task at a time, and the
threads a step starts (Embree's BVH build, torch's intra-op threads) are part of its cost. Timings are
volatile: they never enter a sample, an index column or a hash.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from typing import Any

from schemas.index import TASK_STEPS, CommitRecord, StepSeconds, TaskTimings


class StepClock:
    """Accumulates CPU and wall seconds per step name; `timings` closes the task's total."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}
        self.wall: dict[str, float] = {}
        self._started = (time.process_time(), time.perf_counter())

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        cpu, wall = time.process_time(), time.perf_counter()
        try:
            yield
        finally:
            self.cpu[name] = self.cpu.get(name, 0.0) + max(0.0, time.process_time() - cpu)
            self.wall[name] = self.wall.get(name, 0.0) + max(0.0, time.perf_counter() - wall)

    def add(self, name: str, cpu: float, wall: float) -> None:
        """Seconds of a step spent outside this process (a node's shared refiner host)."""
        self.cpu[name] = self.cpu.get(name, 0.0) + cpu
        self.wall[name] = self.wall.get(name, 0.0) + wall

    def wall_of(self, *names: str) -> float:
        return sum(self.wall.get(name, 0.0) for name in names)

    def timings(self) -> TaskTimings:
        """The steps so far (in `TASK_STEPS` order, others after) and the total since the clock started."""
        names = [n for n in TASK_STEPS if n in self.cpu] + [n for n in self.cpu if n not in TASK_STEPS]
        cpu, wall = self._started
        return TaskTimings(
            steps={n: StepSeconds(cpu=self.cpu[n], wall=self.wall[n]) for n in names},
            total=StepSeconds(cpu=time.process_time() - cpu, wall=time.perf_counter() - wall),
        )


def timed(clock: StepClock | None, name: str) -> Any:
    """``clock.step(name)``, or nothing when there is no clock."""
    return nullcontext() if clock is None else clock.step(name)


@dataclass(frozen=True)
class StepTotals:
    """Per-step seconds summed over the timed tasks of a job or a dataset."""

    tasks: int
    """Commit records that carry timings."""
    untimed: int
    """Commit records without them (written before timings were kept, or relabelled)."""
    cpu: dict[str, float] = field(default_factory=dict)
    wall: dict[str, float] = field(default_factory=dict)
    total_cpu: float = 0.0
    total_wall: float = 0.0

    def share(self, name: str) -> float:
        """The step's share of the steps' CPU-seconds (0 without any)."""
        steps = sum(self.cpu.values())
        return self.cpu.get(name, 0.0) / steps if steps > 0 else 0.0

    def to_json(self) -> dict[str, Any]:
        return {
            "timed_tasks": self.tasks,
            "untimed_tasks": self.untimed,
            "steps": {
                name: {"cpu": self.cpu[name], "wall": self.wall[name], "share": self.share(name)} for name in self.cpu
            },
            "total": {"cpu": self.total_cpu, "wall": self.total_wall},
        }


def step_totals(records: Iterable[CommitRecord]) -> StepTotals:
    """`StepTotals` of these commit records (steps in `TASK_STEPS` order)."""
    cpu: dict[str, float] = {}
    wall: dict[str, float] = {}
    tasks = untimed = 0
    total_cpu = total_wall = 0.0
    for record in records:
        if record.timings is None:
            untimed += 1
            continue
        tasks += 1
        for name, seconds in record.timings.steps.items():
            cpu[name] = cpu.get(name, 0.0) + seconds.cpu
            wall[name] = wall.get(name, 0.0) + seconds.wall
        total_cpu += record.timings.total.cpu
        total_wall += record.timings.total.wall
    order = [n for n in TASK_STEPS if n in cpu] + sorted(n for n in cpu if n not in TASK_STEPS)
    return StepTotals(
        tasks=tasks,
        untimed=untimed,
        cpu={n: cpu[n] for n in order},
        wall={n: wall[n] for n in order},
        total_cpu=total_cpu,
        total_wall=total_wall,
    )


NOT_RECORDED = "time per step: not recorded (tasks committed before per-step timings were kept)"


def totals_from_json(data: dict[str, Any]) -> StepTotals:
    """`StepTotals` back from `StepTotals.to_json` (a job summary in the ledger)."""
    steps = data.get("steps", {})
    # The ledger may hand the JSON back with its keys sorted: the steps go back into pipeline order.
    order = [n for n in TASK_STEPS if n in steps] + sorted(n for n in steps if n not in TASK_STEPS)
    return StepTotals(
        tasks=int(data.get("timed_tasks", 0)),
        untimed=int(data.get("untimed_tasks", 0)),
        cpu={name: float(steps[name]["cpu"]) for name in order},
        wall={name: float(steps[name]["wall"]) for name in order},
        total_cpu=float(data.get("total", {}).get("cpu", 0.0)),
        total_wall=float(data.get("total", {}).get("wall", 0.0)),
    )


def step_lines(totals: StepTotals) -> list[str]:
    """A small plain-text table: CPU-seconds per step summed over the timed tasks, each step's share
    and its wall seconds, then the whole tasks' (steps, loading the refiner, what lies between);
    one line saying so when no task was timed."""
    if totals.tasks == 0:
        return [NOT_RECORDED]
    tasks = f"{totals.tasks} task" + ("" if totals.tasks == 1 else "s")
    lines = [f"time per step, summed over {tasks}:", f"  {'step':<13} {'CPU-s':>9} {'share':>6} {'wall s':>9}"]
    for name, cpu in totals.cpu.items():
        lines.append(f"  {name:<13} {_seconds(cpu):>9} {totals.share(name):>6.1%} {_seconds(totals.wall[name]):>9}")
    lines.append(f"  {'whole tasks':<13} {_seconds(totals.total_cpu):>9} {'':>6} {_seconds(totals.total_wall):>9}")
    if totals.untimed:
        lines.append(f"  ({totals.untimed} tasks committed before per-step timings were kept are not counted)")
    return lines


def _seconds(value: float) -> str:
    """Three significant digits, whole seconds with thousands separators from 1000 s."""
    return f"{value:,.0f}" if value >= 1000 else f"{value:.3g}"
