"""An S3 store that cannot be used is one ``error:`` line, exit 2, in every command that takes a
dataset URL: an unreachable endpoint (a closed port), refused credentials and a missing bucket
(against SeaweedFS, a real server), each naming its fix, within seconds, and nothing already in
the bucket (or the export's folder) touched. Before, `shards export` and `shards validate` printed
a 94-136-line traceback and exited 1.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import storage as fx
from support.engine import submit_args
from support.s3_servers import BUCKET, S3Server, unused_port
from typer.testing import CliRunner

from datagen.cli.main import app

pytestmark = [pytest.mark.s3]

PREFIX = "store-errors"
URL = f"s3://{BUCKET}/{PREFIX}"
FAILURE_BOUND = 30.0
"""Seconds one refused command may take (an unreachable store is asked once, with one retry)."""

CAUSES = {
    "unreachable": ("cannot reach the S3 endpoint", "AWS_ENDPOINT_URL"),
    "wrong credentials": ("refused the request", "AWS_SECRET_ACCESS_KEY"),
    "missing bucket": ("does not exist", "create it"),
}


@pytest.fixture(scope="module")
def dataset(seaweedfs_s3: S3Server) -> Iterator[S3Server]:
    """A small finalised dataset in the bucket (no Ray: the storage tests' two built-ins)."""
    import s3fs

    with pytest.MonkeyPatch.context() as patch:
        for name, value in seaweedfs_s3.env().items():
            patch.setenv(name, value)
        fx.build_dataset(URL, finalise_index=True)
        yield seaweedfs_s3
    s3fs.S3FileSystem.clear_instance_cache()


def commands(url: str, folder: Path, inputs: Path) -> dict[str, list[str]]:
    out = f"s3://{BUCKET}/{PREFIX}-relabelled"
    return {
        "ls": ["shards", "ls", url],
        "show": ["shards", "show", url, "0"],
        "stats": ["shards", "stats", url],
        "validate": ["shards", "validate", url],
        "relabel": ["shards", "relabel", url, "--out", out, "--alpha", "3"],
        "export": ["shards", "export", url, str(folder / "export"), "--layout", "air", "--points", "8"],
        "repair": ["shards", "repair", url, "--home", str(folder / "home")],
        "submit": submit_args(inputs, url, folder / "home"),
    }


def snapshot(server: S3Server) -> dict[str, str]:
    """Every key of the bucket with its ETag: what a failing command must leave as it is."""
    client = server.client()
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET)
    return {item["Key"]: item["ETag"] for page in pages for item in page.get("Contents", [])}


@pytest.mark.parametrize("cause", list(CAUSES))
def test_every_command_fails_with_one_line(
    cause: str, dataset: S3Server, runner: CliRunner, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import s3fs
    from support.engine import builtin_lines, write_config, write_objects

    write_config(tmp_path / "fast.toml", rotations=1)
    write_objects(tmp_path / "objects.txt", builtin_lines(("capsule",)))
    for name, value in dataset.env().items():
        monkeypatch.setenv(name, value)
    monkeypatch.setenv("DATAGEN_STORAGE_RETRIES", "4")  # the default: the job's retries stay as they are
    url = URL
    if cause == "unreachable":
        monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{unused_port()}")
    elif cause == "wrong credentials":
        monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "not-the-secret")
    else:
        url = f"s3://no-such-bucket-{tmp_path.name.lower().replace('_', '-')[:20]}/{PREFIX}"
    before = snapshot(dataset)
    for name, args in commands(url, tmp_path, tmp_path).items():
        s3fs.S3FileSystem.clear_instance_cache()  # a cached client would keep the good credentials
        started = time.monotonic()
        result = runner.invoke(app, args)
        seconds = time.monotonic() - started
        output = result.stdout + result.stderr
        assert result.exit_code == 2, (name, output, result.exception)
        assert "Traceback" not in output, (name, output)
        errors = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(errors) == 1 and errors[0].startswith("error: "), (name, output)
        for part in (url, *CAUSES[cause]):
            assert part in errors[0], (name, part, errors[0])
        assert seconds < FAILURE_BOUND, (name, seconds)
    assert snapshot(dataset) == before
    assert not (tmp_path / "export").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".export")] == []
