"""Connecting to a Ray cluster's client server (`datagen.engine.driver.ensure_ray`): a server that refuses a
new session because it still holds a lost driver's is asked again, with one line saying how long; any other
failure, or a refusal past the wait, is one error line with Ray's whole reason. Ray itself is replaced by a
stand-in whose `init` fails as Ray's client does; the real cluster is exercised by tests/system."""

from __future__ import annotations

import sys
import types

import pytest

from datagen.engine import driver
from datagen.errors import DatagenError

ADDRESS = "ray://127.0.0.1:10001"


class FakeRay(types.ModuleType):
    """``init`` raises each of ``failures`` in turn, then connects."""

    def __init__(self, failures: list[BaseException]) -> None:
        super().__init__("ray")
        self.failures = failures
        self.calls = 0
        self.shutdowns = 0
        self.connected = False
        self.__version__ = "0"

    def is_initialized(self) -> bool:
        return self.connected

    def init(self, **kwargs: object) -> None:
        self.calls += 1
        if self.failures:
            raise self.failures.pop(0)
        self.connected = True

    def shutdown(self) -> None:
        self.shutdowns += 1


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """A clock that sleeping advances (no real waits)."""
    now = [0.0]
    monkeypatch.setattr(driver.time, "monotonic", lambda: now[0])
    monkeypatch.setattr(driver.time, "sleep", lambda seconds: now.__setitem__(0, now[0] + seconds))
    return now


def install(monkeypatch: pytest.MonkeyPatch, failures: list[BaseException]) -> FakeRay:
    fake = FakeRay(failures)
    monkeypatch.setitem(sys.modules, "ray", fake)
    return fake


def test_a_refused_session_is_asked_again_and_said_once(monkeypatch: pytest.MonkeyPatch, clock: list[float]) -> None:
    refusal = ConnectionError("Initialization failure from server:\n")
    fake = install(monkeypatch, [refusal, ConnectionError("Initialization failure from server:"), refusal])
    said: list[str] = []
    driver.ensure_ray(ADDRESS, None, said.append)
    assert fake.connected and fake.calls == 4 and fake.shutdowns == 3
    assert said == [
        f"the Ray client server at {ADDRESS} refused a new session (it may still hold a lost driver's); "
        f"asking again for up to {driver.CLIENT_SESSION_WAIT:.0f} s"
    ]
    assert 0 < clock[0] < driver.CLIENT_SESSION_WAIT


def test_a_refusal_past_the_wait_is_one_line_with_the_whole_reason(
    monkeypatch: pytest.MonkeyPatch, clock: list[float]
) -> None:
    refusals = [ConnectionError("Initialization failure from server:\nthe session is held\n  by 1a2b")] * 200
    install(monkeypatch, list(refusals))
    with pytest.raises(DatagenError) as info:
        driver.ensure_ray(ADDRESS, None)
    assert str(info.value) == (
        f"cannot reach the Ray cluster at {ADDRESS}: Initialization failure from server: the session is held by 1a2b"
    )
    assert clock[0] >= driver.CLIENT_SESSION_WAIT


def test_a_client_port_that_does_not_answer_is_one_line_at_once(
    monkeypatch: pytest.MonkeyPatch, clock: list[float]
) -> None:
    fake = install(monkeypatch, [ConnectionError("ray client connection timeout")])
    with pytest.raises(
        DatagenError, match=rf"^cannot reach the Ray cluster at {ADDRESS}: ray client connection timeout$"
    ):
        driver.ensure_ray(ADDRESS, None)
    assert fake.calls == 1 and clock[0] == 0.0
