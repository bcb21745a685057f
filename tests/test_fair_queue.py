"""The queue is fair between tokens (issue 47): the next job to start is taken round-robin over the tokens with
queued jobs, oldest first within a token, so one user's many jobs do not hold another's one behind them all;
``GET /jobs/{id}`` shows a queued job's place.

The order itself is :func:`service.manager.fair_order`, a pure function, checked on its own; the service test runs
real job processes under the API's supervisor with the real SQLite job store. Nothing here asserts a speed.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from datetime import datetime, timedelta, timezone
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.job_store import JobStatus, QueuedJob
from service.manager import fair_order
from service.manager import new_store as open_store
from service.settings import Settings, token_owner

from .test_service_processes import TOKEN, ended, long_in, small, wait_until

pytestmark = pytest.mark.timeout(600)

ALICE, BOB = "alice-token", "bob-token"
#: The operator's token: the one the helpers borrowed from test_service_processes send.
OPERATOR = TOKEN


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def queued(*owners: str) -> list[QueuedJob]:
    """Queued jobs of ``owners``, oldest first, named owner + their number within the owner."""
    t0 = datetime(2000, 1, 1, tzinfo=timezone.utc)
    seen: dict[str, int] = {}
    jobs = []
    for i, owner in enumerate(owners):
        seen[owner] = seen.get(owner, 0) + 1
        jobs.append(QueuedJob(f"{owner}{seen[owner]}", owner, t0 + timedelta(seconds=i)))
    return jobs


def ids(jobs: list[QueuedJob]) -> list[str]:
    return [j.id for j in jobs]


def test_fifty_jobs_of_one_token_do_not_hold_anothers_one():
    order = fair_order(queued(*["a"] * 50, "b"))
    assert ids(order)[:3] == ["a1", "b1", "a2"]
    assert ids(order)[3:] == [f"a{i}" for i in range(3, 51)]


def test_tokens_take_turns_oldest_first_within_each():
    order = fair_order(queued("a", "a", "a", "b", "b", "c"))
    assert ids(order) == ["a1", "b1", "c1", "a2", "b2", "a3"]


def test_a_token_with_jobs_running_waits_for_those_without():
    jobs = queued("a", "b")
    assert ids(fair_order(jobs, running={"a": 2})) == ["b1", "a1"]
    # Equal running counts: the token that started a job longest ago (or never) goes first.
    assert ids(fair_order(jobs, running={"a": 1, "b": 1}, last_start={"a": 1, "b": 2})) == ["a1", "b1"]
    assert ids(fair_order(jobs, running={"a": 1, "b": 1}, last_start={"a": 3, "b": 2})) == ["b1", "a1"]
    assert fair_order([]) == []


def users_settings(data_dir) -> Settings:
    """A server of two users (Alice, Bob) and the operator, one job at a time, in-process jobs."""
    return Settings(data_dir=data_dir, in_process=True, token=OPERATOR, tokens=[ALICE, BOB], max_running=1,
                    stop_grace=2.0)


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    with TestClient(create_app(users_settings(tmp_path / "data"))) as c:
        yield c


def submit(c: TestClient, spec: dict[str, Any], token: str) -> str:
    r = c.post("/jobs", json=spec, headers=auth(token))
    assert r.status_code == 201, r.text
    return r.json()["id"]


def get(c: TestClient, job_id: str) -> dict[str, Any]:
    r = c.get(f"/jobs/{job_id}", headers=auth(OPERATOR))
    assert r.status_code == 200, r.text
    return r.json()


def test_another_tokens_job_starts_before_the_first_tokens_later_ones(client):
    first = submit(client, long_in("subsystems"), ALICE)
    try:
        wait_until(client, first, lambda j: j["status"] == "running", "alice's first job to start")
        later = [submit(client, small(synthesis=False), ALICE) for _ in range(3)]
        bobs = submit(client, small(synthesis=False), BOB)
        places = {job_id: get(client, job_id)["queue_position"] for job_id in [*later, bobs]}
        assert places == {bobs: 1, later[0]: 2, later[1]: 3, later[2]: 4}, places
        assert get(client, first)["queue_position"] is None
        listed = {j["id"]: j["queue_position"] for j in client.get("/jobs", headers=auth(OPERATOR)).json()["jobs"]}
        assert listed == {**places, first: None}
        # Bob's list holds his job only, at its place in the one queue.
        assert {j["id"]: j["queue_position"] for j in client.get("/jobs", headers=auth(BOB)).json()["jobs"]} == \
            {bobs: 1}
    finally:
        client.delete(f"/jobs/{first}", headers=auth(ALICE))
    ends = {job_id: wait_until(client, job_id, ended, "the queue to run out") for job_id in [*later, bobs]}
    assert {job_id: j["status"] for job_id, j in ends.items()} == dict.fromkeys(ends, "succeeded")
    starts = sorted(ends, key=lambda job_id: ends[job_id]["started_at"])
    assert starts == [bobs, *later], starts
    assert all(j["queue_position"] is None for j in ends.values())


def test_a_wrong_token_is_refused_and_each_users_token_is_recorded_as_a_hash(client, tmp_path):
    assert client.get("/jobs", headers=auth("mallory-token")).status_code == 401
    assert client.get("/jobs").status_code == 401
    job_id = submit(client, small(synthesis=False), BOB)
    wait_until(client, job_id, ended, "bob's job to end")
    store = client.app.state.manager.store
    assert store.require(job_id).owner == token_owner(BOB) != token_owner(ALICE)
    db = (tmp_path / "data" / "jobs.sqlite").read_bytes()
    assert BOB.encode() not in db and ALICE.encode() not in db


def test_user_tokens_need_the_operators_and_are_never_echoed():
    with pytest.raises(ValueError) as err:
        Settings.from_env({"COMPABS_TOKENS": f"{ALICE},{BOB}"})
    assert "COMPABS_TOKEN" in str(err.value) and ALICE not in str(err.value) and BOB not in str(err.value)
    settings = Settings.from_env({"COMPABS_TOKEN": OPERATOR, "COMPABS_TOKENS": f" {ALICE}, {BOB} ,"})
    assert settings.accepted_tokens == [OPERATOR, ALICE, BOB]
    assert ALICE not in repr(settings)


def test_a_store_written_before_owners_keeps_its_jobs(tmp_path):
    """A job store from before the owner column: the column is added, its jobs queue under one owner ("")."""
    settings = Settings(data_dir=tmp_path)
    store = open_store(settings)
    store.create("old1", "old", "{}", owner="x")
    store.close()
    with sqlite3.connect(tmp_path / "jobs.sqlite") as db:
        db.execute("ALTER TABLE jobs DROP COLUMN owner")
    store = open_store(settings)
    try:
        assert store.require("old1").owner == "" and store.require("old1").status == JobStatus.QUEUED
        assert ids(store.queue()) == ["old1"]
        store.create("new1", "new", "{}", owner="y")
        assert [(q.id, q.owner) for q in store.queue()] == [("old1", ""), ("new1", "y")]
    finally:
        store.close()
