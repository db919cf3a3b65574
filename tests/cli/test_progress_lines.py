"""Progress that suits a log (issue 52, finding 5): off a terminal a long command writes one plain line
per interval (done of total, its fields, the rate and the time left) instead of silence, and nothing
between updates that come sooner than the interval."""

from __future__ import annotations

import io

import pytest
from rich.console import Console
from support import storage as fx
from typer.testing import CliRunner

from datagen.cli.common import IntervalProgress, duration, progress_line
from datagen.cli.main import app


def test_off_a_terminal_one_line_per_interval() -> None:
    clock = [100.0]
    out = io.StringIO()
    console = Console(file=out, force_terminal=False, width=80)
    with IntervalProgress(console=console, interval=30.0, get_time=lambda: clock[0], log=console) as progress:
        task = progress.add_task("tasks", total=1368, samples=0, failed=0)
        for step in range(1, 121):  # two minutes of updates, one a second
            clock[0] += 1.0
            progress.update(task, completed=step * 5, samples=step * 250, failed=step // 60)
    lines = out.getvalue().splitlines()
    assert len(lines) == 4, lines  # at 30, 60, 90 and 120 s
    assert lines[0].startswith("tasks: 150/1,368 (11 %), 7,500 samples, 0 failed; ")
    assert lines[-1].startswith("tasks: 600/1,368 (44 %), 30,000 samples, 2 failed; 5 a second, about 2 min 34 s left")
    assert all(len(line) < 120 and "\x1b" not in line for line in lines)


def test_on_a_terminal_no_lines_are_written() -> None:
    out = io.StringIO()
    console = Console(file=out, force_terminal=True, width=80)
    with IntervalProgress(console=console, interval=0.0) as progress:
        task = progress.add_task("tasks", total=3)
        progress.advance(task)
    assert "tasks: 1/3" not in out.getvalue()


def test_validate_in_a_log_says_how_far_it_is(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    url = str(tmp_path / "ds")
    fx.build_dataset(url, finalise_index=True)
    monkeypatch.setenv("DATAGEN_PROGRESS_SECONDS", "1e-9")
    result = CliRunner().invoke(app, ["shards", "validate", url])
    assert result.exit_code == 0, result.output
    assert "shards: structure, coverage, labels: 2/2 (100 %)" in result.stderr  # stdout keeps the results
    assert "shards: structure" not in result.stdout


def test_progress_words() -> None:
    assert [duration(s) for s in (0.4, 45, 200, 7500)] == ["0 s", "45 s", "3 min 20 s", "2 h 05 min"]
    console = Console(file=io.StringIO())
    with IntervalProgress(console=console, interval=1e9) as progress:
        task = progress.add_task("packs", total=None)
        assert progress_line(progress.tasks[task]) == "packs: 0"


def test_counts_read_as_people_write_them() -> None:
    """Issue 52, finding 14: "1 packs", "1 tasks", "1 views" no more."""
    from datagen.cli.common import plural

    assert [plural(n, "pack") for n in (0, 1, 2)] == ["0 packs", "1 pack", "2 packs"]


def test_progress_lines_never_mix_with_json_results(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\nbuiltin:cone\n")
    monkeypatch.setenv("DATAGEN_PROGRESS_SECONDS", "1e-9")
    result = CliRunner().invoke(app, ["evaluate", "--objects", str(objects), "-p", "gain:3", "--json", "-w", "1"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["rows"] and "evaluating objects" in result.stderr
