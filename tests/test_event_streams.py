"""Event streams under limits (issue 47): one client held 920 ``GET /jobs/{id}/events`` streams and
``GET /jobs/{id}`` timed out. Open streams are capped per client and in all (429 naming the cap), a stream
without events ends after ``stream_idle_timeout`` seconds, and a stream's place is given back however it ends.

The app runs in this process (``TestClient``, whose streamed responses end only when the stream does: each open
stream is a thread here, ended by the idle timeout). Jobs are submitted but never started, so their streams are
idle. Waits are bounded; nothing asserts a speed.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service.streams import StreamLimits

from .conftest import EXAMPLES

TOKEN = "stream-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Seconds a test's streams stay open without events (long enough to hold them while the test looks).
IDLE = 8.0


@pytest.fixture
def make(tmp_path) -> Iterator[Callable[..., TestClient]]:
    clients: list[TestClient] = []

    def start(**overrides: Any) -> TestClient:
        values = {"data_dir": tmp_path / "data", "in_process": True, "token": TOKEN, "stream_idle_timeout": IDLE,
                  **overrides}
        c = TestClient(create_app(Settings(**values)))
        c.__enter__()
        c.app.state.manager._kick = lambda: None  # type: ignore[attr-defined]  # jobs stay queued
        clients.append(c)
        return c

    yield start
    for c in reversed(clients):
        c.__exit__(None, None, None)


def queued_job(c: TestClient) -> str:
    spec = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    r = c.post("/jobs", json=spec, headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def open_streams(c: TestClient, job_id: str, n: int) -> tuple[list[threading.Thread], list[Any]]:
    """``n`` streams of the job, each in a thread, open once this returns (they end after IDLE seconds)."""
    answers: list[Any] = []
    threads = [threading.Thread(target=lambda: answers.append(c.get(f"/jobs/{job_id}/events", headers=AUTH)))
               for _ in range(n)]
    for t in threads:
        t.start()
    deadline = time.monotonic() + 60
    while c.app.state.streams.open < n:
        assert time.monotonic() < deadline, f"{c.app.state.streams.open} of {n} streams opened"
        time.sleep(0.02)
    return threads, answers


def finish(threads: list[threading.Thread]) -> None:
    for t in threads:
        t.join(60)
        assert not t.is_alive(), "a stream did not end"


@pytest.mark.parametrize("cap,settings", [("max_streams_per_client is 2", {"max_streams_per_client": 2}),
                                          ("max_streams is 2", {"max_streams": 2})])
def test_streams_beyond_a_cap_are_429_and_the_api_still_answers(make, cap, settings):
    c = make(**settings)
    job_id = queued_job(c)
    threads, answers = open_streams(c, job_id, 2)
    try:
        r = c.get(f"/jobs/{job_id}/events", headers=AUTH)
        assert r.status_code == 429 and cap in r.json()["detail"] and r.headers["retry-after"], r.text
        assert c.get(f"/jobs/{job_id}", headers=AUTH).json()["status"] == "queued"
        assert c.get("/health").status_code == 200
    finally:
        finish(threads)
    # Each open stream got the job's events, then ended idle; their places are free again.
    assert [a.status_code for a in answers] == [200, 200]
    assert all("event: status" in a.text for a in answers)
    assert c.app.state.streams.open == 0
    threads, answers = open_streams(c, job_id, 2)
    finish(threads)
    assert [a.status_code for a in answers] == [200, 200]


def test_an_idle_stream_ends_and_a_reconnect_resumes(make):
    c = make(stream_idle_timeout=0.5)
    job_id = queued_job(c)
    r = c.get(f"/jobs/{job_id}/events", headers=AUTH)  # ends by itself: the job never starts
    assert r.status_code == 200 and "id: 1\n" in r.text and "event: status" in r.text, r.text
    again = c.get(f"/jobs/{job_id}/events", headers={**AUTH, "Last-Event-ID": "1"})
    assert again.status_code == 200 and "event:" not in again.text  # nothing new, nothing repeated
    assert c.app.state.streams.open == 0


def test_a_stream_refused_by_its_token_or_missing_job_holds_no_place(make):
    c = make(max_streams=1)
    for headers, path in (({}, "/jobs/x/events"), (AUTH, "/jobs/nope/events")):
        assert c.get(path, headers=headers).status_code in (401, 404)
    assert c.app.state.streams.open == 0


def test_stream_limits_count_per_client_and_in_all():
    limits = StreamLimits(total=3, per_client=2)
    assert limits.acquire("a") is None and limits.acquire("a") is None
    assert "max_streams_per_client is 2" in (limits.acquire("a") or "")
    assert limits.acquire("b") is None
    assert "max_streams is 3" in (limits.acquire("c") or "")
    limits.release("a")
    assert limits.acquire("c") is None and limits.open == 3
