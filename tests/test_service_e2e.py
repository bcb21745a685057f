"""The REST service end to end: ``compabs serve`` as a real process on its embedded two-worker LocalCluster.

Over HTTP (httpx): the small example submitted as YAML, followed through ``/events`` to completion, its report,
figures and controller downloaded; a job whose API process is SIGKILLed mid-job completes after a restart on
the same data directory (resumed from the chunks already stored); a running job cancelled with DELETE ends
``cancelled`` and leaves no task on the cluster.
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest
import yaml

from .conftest import EXAMPLES
from .processes import Proc, clean_env, free_port, wait_http_ok, wait_until

pytestmark = pytest.mark.slow

#: Seconds to wait for ``compabs serve`` to answer (the embedded cluster starts in ~6 s on an idle machine).
START_TIMEOUT = 120


class Server:
    """A ``compabs serve`` process and an HTTP client for it."""

    def __init__(self, data: Path, log: Path, port: int | None = None) -> None:
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        argv = ["compabs", "serve", "--host", "127.0.0.1", "--port", str(self.port), "--data", str(data),
                "--workers", "2"]
        # The embedded cluster runs on TLS credentials this test holds too (COMPABS_TLS_*), so that it can join it.
        self.credentials = _credentials(data.parent / "tls")
        self.proc = Proc("compabs serve", argv, clean_env(**self.credentials.env()), data.parent, log)
        self.http = httpx.Client(base_url=self.url, timeout=30)
        try:
            wait_http_ok(f"{self.url}/health", START_TIMEOUT, [self.proc])
        except BaseException:
            self.close()  # a server that did not come up is stopped here: no caller holds it to close it
            raise

    def job(self, job_id: str) -> dict[str, Any]:
        r = self.http.get(f"/jobs/{job_id}")
        assert r.status_code == 200, r.text
        return r.json()

    def wait_status(self, job_id: str, statuses: set[str], timeout: float) -> dict[str, Any]:
        wait_until(lambda: self.job(job_id)["status"] in statuses, timeout, f"job {job_id} to be {statuses}",
                   [self.proc])
        return self.job(job_id)

    def explain(self, job_id: str | None = None) -> str:
        head = ""
        if job_id and self.proc.alive():
            try:
                head = "job: " + json.dumps(self.job(job_id), indent=1)[:3000] + "\n"
            except (httpx.HTTPError, AssertionError):
                pass
        return head + self.proc.tail(60)

    def scheduler(self) -> str:
        """The embedded cluster's scheduler address, from the server's log (``/health`` does not tell it)."""
        found = re.findall(r"Dask scheduler (tls://\S+),", self.proc.log.read_text(errors="replace"))
        assert found, self.proc.tail(60)
        return found[-1]

    def close(self) -> None:
        self.http.close()
        self.proc.stop()


def _credentials(directory: Path):
    from workers.cluster import Credentials, write_credentials

    return Credentials.in_directory(directory) if (directory / "key.pem").exists() else write_credentials(directory)


def sse(http: httpx.Client, path: str, timeout: float) -> Iterator[dict[str, Any]]:
    """The events of an SSE stream as ``{"event", "id", "data"}`` dicts (data parsed as JSON)."""
    with http.stream("GET", path, timeout=httpx.Timeout(timeout, connect=10)) as r:
        assert r.status_code == 200, r.read()
        assert r.headers["content-type"].startswith("text/event-stream")
        ev: dict[str, Any] = {}
        for line in r.iter_lines():
            if not line:
                if "data" in ev:
                    yield ev
                ev = {}
            elif line.startswith(":"):
                continue  # keep-alive comment
            else:
                key, _, value = line.partition(":")
                value = value[1:] if value.startswith(" ") else value
                ev[key] = json.loads(value) if key == "data" else value


def heavy_spec() -> dict[str, Any]:
    """small.yaml with a per-cell stage of several seconds in 33 one-cell chunks (~0.3 s each on a worker),
    and a short synthesis tail."""
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["name"] = "small-heavy"
    data["subsystems"][0]["samples"] = 80_000  # 20x the 4000 that took ~0.3 s per chunk before the closed-form SCP
    data["options"].update(chunk_cells=1, audit_transitions=20000, closed_loop_runs=5)
    return data


def chunks_done(job: dict[str, Any]) -> int:
    return next((s["done"] for s in job["stages"] if s["stage"] == "subsystems"), 0)


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[Server]:
    tmp = tmp_path_factory.mktemp("serve")
    s = Server(tmp / "data", tmp / "serve.log")
    try:
        yield s
    finally:
        s.close()


def test_small_example_over_http(server):
    health = server.http.get("/health").json()
    assert health["status"] == "ok" and health["workers"] == 2 and "scheduler" not in health
    r = server.http.post("/jobs", content=(EXAMPLES / "small.yaml").read_bytes(),
                         headers={"content-type": "application/yaml"})
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    try:
        events = list(sse(server.http, f"/jobs/{job_id}/events", timeout=300))
        ids = [int(e["id"]) for e in events]
        assert ids == list(range(1, len(ids) + 1))
        statuses = [e["data"]["status"] for e in events if e["event"] == "status"]
        assert statuses == ["queued", "running", "succeeded"], statuses
        stages = [e["data"]["stage"] for e in events if e["event"] == "progress"]
        order = ["plan", "lipschitz", "subsystems", "interconnection", "audit", "synthesis", "closed_loop"]
        assert sorted(set(stages), key=order.index) == order
        # each stage once, in order; the audit runs beside synthesis (its parts report between synthesis events), so
        # it reports its end after the closed loop
        others = [s for s in stages if s != "audit"]
        assert [s for i, s in enumerate(others) if i == 0 or others[i - 1] != s] == [s for s in order if s != "audit"]
        assert stages.index("audit") < stages.index("synthesis") and stages[-1] == "audit"
        job = events[-1]["data"]
        assert job["status"] == "succeeded" and job["error"] is None
        assert all(s["fraction"] == 1.0 for s in job["stages"]), job["stages"]
        assert job["dask_dashboard"], job
        assert job["summary"]["audit_violations"] == 0 and job["summary"]["closed_loop_violations"] == 0
        assert job["summary"]["abstract_states"] == 1089 and job["summary"]["domain_states"] == 629

        report = server.http.get(f"/jobs/{job_id}/report").json()
        assert report["audit"]["violations"] == 0 and report["audit"]["transitions_checked"] > 0
        assert report["closed_loop"]["violations"] == 0 and report["closed_loop"]["runs"] > 0
        assert report["runner"]["workers"] == 2 and report["runner"]["chunks_computed"] == report["runner"]["chunks_total"]
        assert job["figures"] == report["figures"] == ["trajectory.png", "phase_plane.png"]
        for name in job["figures"]:
            img = server.http.get(f"/jobs/{job_id}/figures/{name}")
            assert img.status_code == 200 and img.headers["content-type"] == "image/png"
            assert img.content.startswith(b"\x89PNG\r\n\x1a\n")
        z = server.http.get(f"/jobs/{job_id}/controller")
        assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
        with zipfile.ZipFile(io.BytesIO(z.content)) as archive:
            assert sorted(archive.namelist()) == ["controller.dddmp", "controller.json"]
            assert json.loads(archive.read("controller.json"))
        listed = server.http.get("/jobs").json()["jobs"]
        assert listed[0]["id"] == job_id
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{server.explain(job_id)}") from None


def test_delete_running_job_cancels_its_cluster_tasks(server):
    from distributed import Client

    def chunk_tasks(c: Client) -> int:
        keys = c.run_on_scheduler(lambda dask_scheduler: [str(k) for k in dask_scheduler.tasks])
        return sum("abstract_chunk" in k for k in keys)

    r = server.http.post("/jobs", json=heavy_spec(), params={"name": "to-cancel"})
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    assert r.json()["name"] == "to-cancel"
    scheduler = server.scheduler()
    try:
        with Client(scheduler, timeout=30, security=server.credentials.security()) as c:
            wait_until(lambda: chunks_done(server.job(job_id)) >= 2, 120, "two chunks done", [server.proc])
            assert chunk_tasks(c) > 5  # the job's chunks are on the cluster
            r = server.http.delete(f"/jobs/{job_id}")
            assert r.status_code == 200 and r.json()["status"] in ("running", "cancelled")
            job = server.wait_status(job_id, {"cancelled", "failed", "succeeded"}, 60)
            assert job["status"] == "cancelled", job
            assert chunks_done(job) < 33 and job["finished_at"]
            # The scheduler forgets the job's tasks: none queued or held (a running one finishes first).
            wait_until(lambda: chunk_tasks(c) == 0, 30, "the scheduler to drop the cancelled job's tasks", [server.proc])
        assert server.job(job_id)["status"] == "cancelled"
        assert server.http.get(f"/jobs/{job_id}/report").status_code == 409
        assert server.http.delete(f"/jobs/{job_id}").json()["status"] == "cancelled"  # idempotent
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{server.explain(job_id)}") from None


def test_api_killed_mid_job_resumes_after_restart(tmp_path):
    data, port = tmp_path / "data", free_port()
    first = Server(data, tmp_path / "serve-1.log", port)
    second = None
    job_id = None
    try:
        r = first.http.post("/jobs", json=heavy_spec())
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]
        wait_until(lambda: chunks_done(first.job(job_id)) >= 4, 120, "four chunks done", [first.proc])
        before = first.job(job_id)
        assert before["status"] == "running" and chunks_done(before) < 33, before
        job_pid = int((data / "run" / f"{job_id}.pid").read_text().split()[0])  # the job's own process
        job_process = psutil.Process(job_pid)
        os.kill(first.proc.popen.pid, signal.SIGKILL)  # the API process only: no shutdown, no cleanup
        first.proc.popen.wait(30)
        # The job's process dies with its API (it would otherwise compute beside the resumed job).
        wait_until(lambda: not job_process.is_running() or job_process.status() == psutil.STATUS_ZOMBIE, 30,
                   "the job's process to die with the API")
        first.close()  # its Dask workers follow their parent; this reaps whatever is left of the group

        second = Server(data, tmp_path / "serve-2.log", port)
        job = second.wait_status(job_id, {"succeeded", "failed", "cancelled"}, 240)
        assert job["status"] == "succeeded", job
        assert job["summary"]["audit_violations"] == 0 and job["summary"]["closed_loop_violations"] == 0
        report = second.http.get(f"/jobs/{job_id}/report").json()
        runner = report["runner"]
        assert runner["chunks_total"] == 33
        assert runner["chunks_reused"] >= 4, runner  # resumed from the chunks stored before the kill
        assert runner["chunks_reused"] + runner["chunks_computed"] == 33
        assert report["audit"]["violations"] == 0 and report["closed_loop"]["violations"] == 0
        # The stored events survived: running, (killed) re-queued, running again, succeeded.
        events = list(sse(second.http, f"/jobs/{job_id}/events", timeout=30))
        statuses = [e["data"]["status"] for e in events if e["event"] == "status"]
        assert statuses == ["queued", "running", "queued", "running", "succeeded"], statuses
        assert [int(e["id"]) for e in events] == list(range(1, len(events) + 1))
    except AssertionError as exc:
        logs = "\n".join(s.explain(job_id) for s in (first, second) if s is not None)
        raise AssertionError(f"{exc}\n{logs}") from None
    finally:
        for s in (first, second):
            if s is not None:
                s.close()
