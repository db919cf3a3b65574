"""`datagen.engine.serve.serve`, the loop behind ``datagen serve``, called from Python without Ray:
the lines it reports, a job that cannot start (failed, reported, the loop goes on), a broken ledger
(propagates). Jobs that run are covered by tests/system/test_faults.py through the CLI."""

from __future__ import annotations

from pathlib import Path

import pytest

from datagen import api
from datagen.engine import serve as serve_module
from datagen.engine.serve import serve
from datagen.settings import LEDGER_FILE, RunSettings, ledger_for
from jobs.ledger import FAILED, PENDING, LedgerError


class Lines:
    def __init__(self) -> None:
        self.out: list[str] = []
        self.err: list[str] = []


def serve_once(settings: RunSettings) -> Lines:
    lines = Lines()
    serve(settings, poll=0.01, once=True, report=lines.out.append, error=lines.err.append)
    return lines


def enqueue(tmp_path: Path, out: str) -> str:
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:capsule\n")
    return api.enqueue(objects, None, RunSettings(home=tmp_path / "home", out=out)).job_id


def test_an_empty_queue_reports_the_ledger_and_returns(tmp_path: Path) -> None:
    settings = RunSettings(home=tmp_path)
    assert serve_once(settings).out == [f"serving {tmp_path / LEDGER_FILE}"]
    assert api.ledger_for is ledger_for


def test_a_job_that_cannot_start_is_failed_and_the_loop_goes_on(tmp_path: Path) -> None:
    from datagen.engine.driver import dataset_info
    from schemas.config import GenerationConfig
    from storage import init_dataset, open_location

    out = str(tmp_path / "out")
    job_id = enqueue(tmp_path, out)
    # Another job's dataset takes the folder after this one was queued (enqueue itself refuses one).
    init_dataset(open_location(out), dataset_info(GenerationConfig(rotations=3, refiner="none")))
    settings = RunSettings(home=tmp_path / "home")
    lines = serve_once(settings)
    assert lines.out == [f"serving {settings.home / LEDGER_FILE}", f"running job {job_id}", f"job {job_id}: failed"]
    (error,) = lines.err
    assert error.startswith(f"error: job {job_id}: {out}: holds a dataset of another config")
    ledger = ledger_for(settings)
    try:
        assert ledger.job(job_id).state == FAILED
    finally:
        ledger.close()


def test_an_unusable_url_is_refused_before_the_job_is_queued(tmp_path: Path) -> None:
    from schemas.errors import DatagenError

    with pytest.raises(DatagenError, match="nosuchscheme://bucket/data: unsupported dataset URL"):
        enqueue(tmp_path, "nosuchscheme://bucket/data")
    assert api.status(None, RunSettings(home=tmp_path / "home")) == []


def test_a_ledger_error_stops_the_loop_and_fails_no_job(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    job_id = enqueue(tmp_path, str(tmp_path / "out"))

    def broken(*args: object, **kwargs: object) -> None:
        raise LedgerError("the ledger is gone")

    monkeypatch.setattr(serve_module, "run_job", broken)
    settings = RunSettings(home=tmp_path / "home")
    with pytest.raises(LedgerError, match="the ledger is gone"):
        serve_once(settings)
    ledger = ledger_for(settings)
    try:
        assert ledger.job(job_id).state == PENDING
    finally:
        ledger.close()
