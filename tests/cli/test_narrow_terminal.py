"""On an 80-column terminal the ids a user copies into the next command stay whole (issue 52, finding 6):
`status`'s job id (for resume and cancel), `shards ls`'s task ids (two rotations of one object are two
rows that must not read alike), and no cell anywhere is cut short with an ellipsis."""

from __future__ import annotations

from pathlib import Path

import pytest
from support import storage as fx
from support.engine import planned_task_ids
from typer.testing import CliRunner

from datagen import api
from datagen.cli import common
from datagen.cli.main import app
from datagen.settings import RunSettings
from schemas.config import GenerationConfig
from storage import open_dataset


@pytest.fixture
def narrow(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(common.console, "_force_terminal", True)
    monkeypatch.setattr(common.console, "_width", 80)
    monkeypatch.setattr(common.console, "_color_system", None)


def test_status_keeps_the_job_id_whole(tmp_path: Path, narrow: None) -> None:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    out = tmp_path / ("a-rather-long-folder-name-for-the-dataset-" * 2) / "dataset"
    settings = RunSettings(home=tmp_path / "home", out=str(out))
    job = api.enqueue(objects, GenerationConfig(rotations=2, refiner="none"), settings)
    result = CliRunner().invoke(app, ["status", "--home", str(tmp_path / "home")])
    assert result.exit_code == 0, result.output
    assert job.job_id in result.stdout and "…" not in result.stdout
    assert max(len(line) for line in result.stdout.splitlines()) <= 80
    result = CliRunner().invoke(app, ["status", job.job_id, "--home", str(tmp_path / "home")])
    task_ids = planned_task_ids(tmp_path / "home", job.job_id)
    assert len(task_ids) == 2 and all(task_id in result.stdout for task_id in task_ids), result.stdout
    assert "…" not in result.stdout


def test_shards_ls_keeps_every_task_id_whole(tmp_path: Path, narrow: None) -> None:
    url = str(tmp_path / "ds")
    fx.build_dataset(url, finalise_index=True)
    result = CliRunner().invoke(app, ["shards", "ls", url])
    assert result.exit_code == 0, result.output
    tasks = sorted({open_dataset(url).index_row(i)["task_id"] for i in range(len(open_dataset(url)))})
    assert len(tasks) >= 2
    for task_id in tasks:
        assert task_id in result.stdout, (task_id, result.stdout)
    assert "…" not in result.stdout
    assert max(len(line) for line in result.stdout.splitlines()) <= 80


def test_evaluate_draws_its_tables_to_fit_the_terminal(tmp_path: Path, narrow: None) -> None:
    """Finding 8: the 16-column Markdown tables wrapped into noise on a terminal; there they are drawn to
    fit (into a pipe they stay Markdown, for a README)."""
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    args = ["evaluate", "--objects", str(objects), "-p", "gain", "-p", "spread:4", "--margins", "2", "--workers", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    drawn = [line for line in lines if line[:1] in "┏┃┡│└"]
    assert drawn and max(len(line) for line in drawn) <= 80 and not any(line.startswith("| ") for line in lines)
    assert any("spread:4" in line for line in lines) and "…" not in result.stdout
