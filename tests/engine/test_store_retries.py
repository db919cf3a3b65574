"""A store that fails under a task (an S3 server restarting mid-job) is waited for: the worker tries
its store reads and shard write again, `STORE_RETRY_WAITS` apart, and fails only on other errors or
when the store stays down past the last wait."""

from __future__ import annotations

import errno

import pytest

from datagen.engine import worker


class EndpointConnectionError(Exception):
    """Named like botocore's: the store's connection was refused."""


@pytest.fixture(autouse=True)
def no_waiting(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    waits: list[float] = []
    monkeypatch.setattr(worker.time, "sleep", waits.append)
    return waits


def flaky(failures: list[BaseException]):  # type: ignore[no-untyped-def]
    calls = []

    def action() -> str:
        calls.append(1)
        if failures:
            raise failures.pop(0)
        return "written"

    return action, calls


@pytest.mark.parametrize(
    "error",
    [
        OSError(errno.EREMOTEIO, "Internal Server Error"),
        EndpointConnectionError("Could not connect to the endpoint URL"),
        ConnectionRefusedError("refused"),
    ],
)
def test_a_failing_store_is_tried_again(error: BaseException, no_waiting: list[float]) -> None:
    action, calls = flaky([error, error])
    assert worker._store_retried(action) == "written"
    assert len(calls) == 3
    assert no_waiting == list(worker.STORE_RETRY_WAITS[:2])


def test_a_store_down_past_the_last_wait_fails_the_task(no_waiting: list[float]) -> None:
    error = OSError(errno.EREMOTEIO, "Internal Server Error")
    action, calls = flaky([error] * (len(worker.STORE_RETRY_WAITS) + 1))
    with pytest.raises(OSError):
        worker._store_retried(action)
    assert len(calls) == len(worker.STORE_RETRY_WAITS) + 1
    assert sum(no_waiting) == sum(worker.STORE_RETRY_WAITS)


@pytest.mark.parametrize("error", [ValueError("a bug"), PermissionError("Access Denied")])
def test_other_errors_and_refusals_are_not_retried(error: BaseException, no_waiting: list[float]) -> None:
    action, calls = flaky([error, error])
    with pytest.raises(type(error)):
        worker._store_retried(action)
    assert len(calls) == 1 and no_waiting == []


def test_a_local_store_is_not_waited_for(no_waiting: list[float]) -> None:
    action, calls = flaky([OSError(errno.EREMOTEIO, "Internal Server Error")])
    with pytest.raises(OSError):
        worker._store_retried(action, remote=False)
    assert len(calls) == 1 and no_waiting == []
