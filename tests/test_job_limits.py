"""A job's memory limit holds on its whole process tree (issue 47): a job over it is killed and failed with the
limit and the use measured, the API keeps answering and other jobs complete; a limit over the server's cap is a 422.

The jobs are real job processes under the API's supervisor (``TestClient``, in-process jobs, the real SQLite job
store). The memory comes from :func:`hog`, a ``module:function`` black box of this module that the test servers
allow: it holds 64 MiB more at each batch it evaluates in the process named by its ``where`` (the one-row probe
the API makes when it validates the spec allocates nothing). Nothing here asserts a speed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import psutil
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service.supervisor import group_members, group_memory_over

from .test_service_processes import AUTH, TOKEN, WAIT, ended, small, submit, wait_until

pytestmark = pytest.mark.timeout(600)

MIB = 1 << 20
#: The most a hog holds: far over the limits below, far under the machine (a supervisor that failed to stop it
#: would see the job succeed, and the test fail, with the machine unharmed).
HOG_CAP = 1536 * MIB
#: The limit of the hogging jobs, MiB: over a job process's own use (its imports: about 200 MiB here).
LIMIT = 512

_held: list[np.ndarray] = []
_lock = threading.Lock()


def _agent(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    return 32 / (1 + np.exp(-0.2 * (x + u + 0.1 * (x - w) - 16)))


def _hold(x: np.ndarray) -> None:
    if x.shape[0] > 1:
        with _lock:
            if sum(a.nbytes for a in _held) < HOG_CAP:
                _held.append(np.ones(64 * MIB // 8))  # written, so resident
        time.sleep(0.01)


def hog(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """small.yaml's agent, holding 64 MiB more at each batch in whichever process evaluates it."""
    _hold(x)
    return _agent(x, u, w)


def hog_in_audit(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """small.yaml's agent, holding memory only in the audit's child process (a helper of the job's process)."""
    if "audit_beside" in sys.argv[0]:
        _hold(x)
    return _agent(x, u, w)


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    settings = Settings(data_dir=tmp_path / "data", in_process=True, token=TOKEN, stop_grace=2.0,
                        allowed_modules=[__name__], max_running=2)
    with TestClient(create_app(settings)) as c:
        yield c


def hogging(function: str) -> dict[str, Any]:
    if function == "hog":  # the per-cell stage, in the job's own process
        data = small(synthesis=False, chunk_cells=1, memory_limit=LIMIT)
        data["subsystems"][0]["samples"] = 2_000
    else:  # the audit, in a child of the job's process, beside synthesis
        data = small(audit_transitions=2_000_000, memory_limit=LIMIT)
    data["subsystems"][0]["dynamics"] = f"{__name__}:{function}"
    return data


@pytest.mark.parametrize("function", ["hog", "hog_in_audit"])
def test_a_job_over_its_memory_limit_is_failed_with_the_reason_and_others_complete(client, function):
    hogger = submit(client, hogging(function))
    beside = submit(client, small(synthesis=False))  # runs at the same time (max_running 2)
    done = wait_until(client, hogger, ended, "the hogging job to end")
    assert done["status"] == "failed", done
    error = done["error"]
    assert f"memory limit of {LIMIT} MiB" in error and "options.memory_limit" in error, error
    used = int(error.split("used ")[1].split(" MiB")[0])
    assert used > LIMIT, error
    assert client.app.state.manager.process_of(hogger) is None
    assert client.get("/health").status_code == 200
    assert wait_until(client, beside, ended, "the job beside it to end")["status"] == "succeeded"
    after = submit(client, small(synthesis=False))
    assert wait_until(client, after, ended, "a job after it to end")["status"] == "succeeded"


def test_a_memory_limit_over_the_servers_cap_is_422(client):
    r = client.post("/jobs", json=small(memory_limit=10**6), headers=AUTH)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "options.memory_limit" in detail and "max_memory_limit is 16384 MiB" in detail, detail


def test_a_memory_limit_below_a_process_is_refused_by_the_spec(client):
    r = client.post("/jobs", json=small(memory_limit=8), headers=AUTH)
    assert r.status_code == 422 and "memory_limit" in r.text, r.text


def test_the_use_counts_every_process_of_the_group_and_shared_pages_once():
    """A group whose leader holds little and whose child (a grandchild of the test) holds 300 MiB is over a 200 MiB
    limit; the use measured is at most the resident sizes' sum (libraries shared by the two, counted once)."""
    child = ("import numpy as np, sys, time; a = np.ones(300 * 2**20 // 8); print('held', flush=True); "
             "time.sleep(120)")
    leader_code = (f"import subprocess, sys; p = subprocess.Popen([sys.executable, '-c', {child!r}]); "
                   "p.wait()")
    leader = subprocess.Popen([sys.executable, "-c", leader_code], start_new_session=True)
    try:
        deadline = time.monotonic() + WAIT
        while True:
            members = group_members(leader.pid)
            rss = sum(p.memory_info().rss for p in members)
            if len(members) == 2 and rss > 300 * MIB:
                break
            assert time.monotonic() < deadline, [p.pid for p in members]
            time.sleep(0.1)
        assert {p.pid for p in members} == {leader.pid, *[c.pid for c in psutil.Process(leader.pid).children()]}
        used = group_memory_over(leader.pid, 200 * MIB)
        assert used is not None and 250 * MIB < used <= rss, (used, rss)
        assert group_memory_over(leader.pid, 4096 * MIB) is None
    finally:
        os.killpg(leader.pid, signal.SIGKILL)
        leader.wait(30)
