"""A reader that closes the pipe (``datagen shards stats URL | head -3``) ends the command quietly: no
``error:`` line blaming the dataset's store, no traceback (issue 52, finding 13)."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path

import pytest
from support import storage as fx
from typer.testing import CliRunner

from datagen.cli.main import app

COMMANDS = {
    "shards stats": ["shards", "stats", "{url}"],
    "shards ls": ["shards", "ls", "{url}"],
    "objects show": ["objects", "show", "{objects}"],
    "status": ["status", "--home", "{home}"],
}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> str:
    url = str(tmp_path_factory.mktemp("pipe") / "ds")
    fx.build_dataset(url, finalise_index=True)
    return url


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_closed_pipe_ends_the_command_quietly(command: str, dataset: str, tmp_path: Path) -> None:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\nbuiltin:cone\n")
    fill = {"url": dataset, "objects": str(objects), "home": str(tmp_path / "home")}
    argv = [part.format(**fill) for part in COMMANDS[command]]
    script = "import sys; from datagen.cli.main import app; sys.argv = ['datagen', *sys.argv[1:]]; app()"
    reader, writer = os.pipe()
    os.close(reader)  # the reader is gone before the command writes its first line
    done = subprocess.run(
        [sys.executable, "-c", script, *argv], stdout=writer, stderr=subprocess.PIPE, text=True, timeout=120
    )
    os.close(writer)
    assert "error:" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert "BrokenPipeError" not in done.stderr
    assert done.returncode in (0, 1), done.stderr  # click's exit for a closed pipe is 1; never 2 (a user error)


def test_a_pipe_closed_mid_output_is_not_blamed_on_the_store(
    dataset: str, monkeypatch: pytest.MonkeyPatch, runner: CliRunner
) -> None:
    """The write that meets the closed pipe raises BrokenPipeError, a ConnectionError: with a dataset URL
    at hand it read as "cannot use the dataset store" (exit 2) when the output was long enough to be
    written before the command ended (a 10,000-task dataset's stats)."""
    from datagen.cli import shards_view

    def closed(*args: object, **kwargs: object) -> None:
        raise BrokenPipeError(errno.EPIPE, "Broken pipe")

    monkeypatch.setattr(shards_view, "print_stats", closed)
    result = runner.invoke(app, ["shards", "stats", dataset])
    assert "error:" not in result.output and "dataset store" not in result.output, result.output
    assert result.exit_code != 2
