"""Jobs run in their own process trees, never in the API's (issue 47): the API answers while a job computes,
DELETE ends the job's processes at every stage, a job past its time limit is stopped and failed with the reason,
and a job process that outlived its API is killed before the job is resumed.

The app runs in this process (``TestClient``) with in-process jobs (no Dask: each job process computes alone).
Nothing here asserts a speed: waits have generous timeouts, and what is checked is the answers and which processes
exist (psutil).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import psutil
import pytest
import yaml
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service.supervisor import JOB_MODULE, kill_orphans

from .conftest import EXAMPLES

pytestmark = pytest.mark.timeout(900)

TOKEN = "process-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
#: Seconds to wait for a job to reach a stage, or to end (a bound on a hang, not a speed requirement).
WAIT = 300


def small(n: int = 2, **options: Any) -> dict[str, Any]:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["parameters"]["N"] = n
    data["options"].update({"audit_transitions": 0, "closed_loop_runs": 3, "initial_states": [], **options})
    return data


def long_in(stage: str) -> dict[str, Any]:
    """A job that spends many seconds in ``stage``."""
    if stage == "subsystems":  # ~25 s here: 257 cells of 100,000 samples each, one chunk per cell
        data = small(synthesis=False, chunk_cells=1)
        data["subsystems"][0]["samples"] = 100_000
        data["subsystems"][0]["state"]["eta"] = 0.125
    elif stage == "audit":  # in the job's process (no synthesis to run beside)
        data = small(synthesis=False, audit_transitions=30_000_000)
    elif stage == "synthesis":  # N = 4: ~50 s of CUDD, with the audit beside it in a child process
        data = small(4, audit_transitions=20_000_000)
    elif stage == "closed_loop":
        data = small(closed_loop_runs=40_000, closed_loop_steps=100)
    else:
        raise ValueError(stage)
    return data


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    settings = Settings(data_dir=tmp_path / "data", in_process=True, token=TOKEN, stop_grace=2.0)
    with TestClient(create_app(settings)) as c:
        yield c


def submit(c: TestClient, spec: dict[str, Any]) -> str:
    r = c.post("/jobs", json=spec, headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def job(c: TestClient, job_id: str) -> dict[str, Any]:
    r = c.get(f"/jobs/{job_id}", headers=AUTH)
    assert r.status_code == 200, r.text
    return r.json()


def wait_until(c: TestClient, job_id: str, done, what: str, timeout: float = WAIT) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        j = job(c, job_id)
        if done(j):
            return j
        assert time.monotonic() < deadline, f"{what}: not within {timeout:g} s: {j}"
        time.sleep(0.1)


def in_stage(stage: str):
    return lambda j: j["status"] != "queued" and (
        j["status"] != "running" or any(s["stage"] == stage for s in j["stages"]))


def ended(j: dict[str, Any]) -> bool:
    return j["status"] in ("succeeded", "failed", "cancelled")


def family(c: TestClient, job_id: str) -> list[psutil.Process]:
    """The job's process and every process it started, now."""
    proc = c.app.state.manager.process_of(job_id)
    assert proc is not None, "the job has no process"
    leader = psutil.Process(proc.pid)
    return [leader, *leader.children(recursive=True)]


def assert_gone(processes: list[psutil.Process], timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while True:
        alive = [p for p in processes if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
        if not alive:
            return
        assert time.monotonic() < deadline, f"still running: {[(p.pid, p.cmdline()[:4]) for p in alive]}"
        time.sleep(0.1)


def test_the_api_answers_while_a_job_synthesizes(client):
    """The job's CUDD calls hold its own interpreter's lock, not the API's: /health and GET /jobs/{id} answer."""
    job_id = submit(client, long_in("synthesis"))
    try:
        j = wait_until(client, job_id, in_stage("synthesis"), "the job to reach synthesis")
        assert j["status"] == "running", j
        processes = family(client, job_id)
        assert os.getpid() not in [p.pid for p in processes]
        answers = []
        for _ in range(100):
            health = client.get("/health")
            answers.append((health.status_code, health.json()["jobs_running"]))
            answers.append((client.get(f"/jobs/{job_id}", headers=AUTH).status_code, 1))
        assert answers == [(200, 1)] * 200
        # Still computing after all those answers: they did not wait for the job.
        assert job(client, job_id)["status"] == "running"
        assert any(p.is_running() for p in processes)
    finally:
        client.delete(f"/jobs/{job_id}", headers=AUTH)
        wait_until(client, job_id, ended, "the job to end after DELETE")


@pytest.mark.parametrize("stage", ["subsystems", "audit", "synthesis", "closed_loop"])
def test_delete_ends_the_jobs_processes_in_every_stage(client, stage):
    job_id = submit(client, long_in(stage))
    try:
        j = wait_until(client, job_id, in_stage(stage), f"the job to reach {stage}")
        assert j["status"] == "running", j
        processes = family(client, job_id)
        if stage == "synthesis":  # the audit runs beside it, in a child of the job's process
            assert len(processes) >= 2, processes
        r = client.delete(f"/jobs/{job_id}", headers=AUTH)
        assert r.status_code == 200 and r.json()["status"] in ("running", "cancelled"), r.text
        done = wait_until(client, job_id, ended, "the job to end after DELETE", timeout=60)
        assert done["status"] == "cancelled" and done["error"] is None, done
        assert_gone(processes)
        assert client.app.state.manager.process_of(job_id) is None
    finally:
        client.delete(f"/jobs/{job_id}", headers=AUTH)


def test_a_job_past_its_time_limit_is_failed_with_the_reason(client):
    job_id = submit(client, {**long_in("subsystems"), "options": {**long_in("subsystems")["options"], "time_limit": 3}})
    try:
        # Its process, once started (a loaded machine may reach the limit before this poll sees it: then the
        # record below is all there is to check, and no process of it is left by construction).
        started = wait_until(client, job_id, lambda j: ended(j) or client.app.state.manager.process_of(job_id)
                             is not None, "the job to start")
        processes = [] if ended(started) else family(client, job_id)
        done = wait_until(client, job_id, ended, "the job to be stopped")
        assert done["status"] == "failed", done
        assert "time limit of 3 s" in done["error"] and "options.time_limit" in done["error"], done["error"]
        assert_gone(processes)
    finally:
        client.delete(f"/jobs/{job_id}", headers=AUTH)


def test_a_time_limit_over_the_servers_cap_is_422(client):
    r = client.post("/jobs", json=small(time_limit=10**6), headers=AUTH)
    assert r.status_code == 422, r.text
    assert "options.time_limit" in r.json()["detail"] and "max_time_limit is 14400" in r.json()["detail"]


def test_a_job_process_that_outlived_its_api_is_killed(tmp_path):
    """What a SIGKILLed API can leave behind (its job process, had it not died with it) is killed at start-up."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    orphan = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
    try:
        started = open(f"/proc/{orphan.pid}/stat").read().rpartition(")")[2].split()[19]
        (run_dir / "job1.pid").write_text(f"{orphan.pid} {started} {JOB_MODULE}\n")
        (run_dir / "job2.pid").write_text(f"{orphan.pid} 1 {JOB_MODULE}\n")  # another process by that pid: spared
        assert kill_orphans(run_dir) == [orphan.pid]
        assert orphan.wait(30) == -signal.SIGKILL
        assert list(run_dir.iterdir()) == []
    finally:
        if orphan.poll() is None:
            orphan.kill()
            orphan.wait()
