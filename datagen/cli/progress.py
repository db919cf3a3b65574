"""Progress that suits a terminal and a log alike.

On a terminal a long command draws rich's live bar. Into a pipe or a file (a batch job's log, ``nohup``,
CI) a bar is noise, and nothing at all is hours of silence: there `IntervalProgress` writes one plain
line every `interval` seconds instead, with what the bar shows (done of total, the task's fields such
as samples and failures, the rate and the time left), and none between its first and last update when
a command ends sooner than that.
"""

from __future__ import annotations

import os
from typing import Any

from rich.console import Console
from rich.progress import Progress, Task, TaskID

PROGRESS_SECONDS = 30.0
"""Seconds between two progress lines off a terminal (``DATAGEN_PROGRESS_SECONDS`` overrides)."""


def progress_seconds() -> float:
    """The interval between progress lines off a terminal, from the environment or `PROGRESS_SECONDS`."""
    try:
        value = float(os.environ.get("DATAGEN_PROGRESS_SECONDS", PROGRESS_SECONDS))
    except ValueError:
        return PROGRESS_SECONDS
    return value if value > 0 else PROGRESS_SECONDS


class IntervalProgress(Progress):
    """A rich `Progress` that, when its live display is off (not a terminal), logs a line per interval."""

    def __init__(self, *columns: Any, console: Console, interval: float | None = None, **kwargs: Any) -> None:
        self.logs = not console.is_terminal
        super().__init__(*columns, console=console, disable=self.logs, **kwargs)
        self.interval = progress_seconds() if interval is None else interval
        self._last = self.get_time()

    def update(self, task_id: TaskID, **kwargs: Any) -> None:
        super().update(task_id, **kwargs)
        self._log()

    def advance(self, task_id: TaskID, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._log()

    def _log(self) -> None:
        if not self.logs or self.get_time() - self._last < self.interval:
            return
        self._last = self.get_time()
        for task in self.tasks:
            self.console.print(progress_line(task), markup=False, highlight=False, soft_wrap=True)


def progress_line(task: Task) -> str:
    """``tasks: 812/1,368 (59 %), 41,233 samples, 0 failed; 5.1 a second, about 1 min 49 s left``."""
    done = int(task.completed)
    parts = [f"{task.description}: {done:,}" + (f"/{int(task.total):,}" if task.total else "")]
    if task.total:
        parts[0] += f" ({100 * task.completed / task.total:.0f} %)"
    parts += [
        f"{value:,} {name}" if isinstance(value, int) else f"{value} {name}" for name, value in task.fields.items()
    ]
    line = ", ".join(parts)
    speed, left = task.speed, task.time_remaining
    if speed:
        line += f"; {speed:.3g} a second"
        if left is not None:
            line += f", about {duration(left)} left"
    return line


def duration(seconds: float) -> str:
    """``45 s``, ``3 min 20 s``, ``2 h 05 min``."""
    whole = max(0, round(seconds))
    if whole < 60:
        return f"{whole} s"
    if whole < 3600:
        return f"{whole // 60} min {whole % 60} s"
    return f"{whole // 3600} h {(whole % 3600) // 60:02d} min"
