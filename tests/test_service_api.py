"""The REST API in this process (``TestClient``, lifespan run), jobs executed in-process (no Dask).

Authentication, the caps (each refusal names the cap and its value), spec errors naming the field or token,
YAML and JSON bodies, 404s, the schema, a whole job followed through its event stream with its results and
figure names checked against path traversal, cancellation, and the recovery of jobs an earlier API process
left running. The same app on a real cluster, over HTTP: ``tests/test_service_e2e.py``.
"""

from __future__ import annotations

import io
import json
import sqlite3
import time
import zipfile
from collections.abc import Iterator
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from pipelines.spec.model import json_schema, parse_spec
from service.app import create_app
from service.cli import main
from service.manager import new_store
from service.settings import Settings
from workers import jobdir

from .conftest import EXAMPLES

TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SMALL_YAML = (EXAMPLES / "small.yaml").read_text()


def small(**options: Any) -> dict[str, Any]:
    """small.yaml as a dict, with a cheap tail (few closed-loop runs, a small audit) unless overridden."""
    data = yaml.safe_load(SMALL_YAML)
    data["options"].update({"audit_transitions": 20000, "closed_loop_runs": 3, **options})
    return data


def quick() -> dict[str, Any]:
    """The cheapest real job: small.yaml's abstraction only (~1 s)."""
    return small(synthesis=False, audit_transitions=0)


def heavy() -> dict[str, Any]:
    """A job whose per-cell stage runs for seconds in 33 chunks (something to cancel or to keep the queue busy)."""
    data = small(chunk_cells=1, synthesis=False)
    data["subsystems"][0]["samples"] = 3000
    return data


@pytest.fixture
def make_client(tmp_path) -> Iterator:
    """``make_client(**settings)``: a started app (in-process jobs, token set unless ``token=None``)."""
    clients = []

    def make(**overrides: Any) -> TestClient:
        values = {"data_dir": tmp_path / "data", "in_process": True, "token": TOKEN, **overrides}
        c = TestClient(create_app(Settings(**values)))
        c.__enter__()
        clients.append(c)
        return c

    yield make
    for c in reversed(clients):
        c.__exit__(None, None, None)


@pytest.fixture
def client(make_client) -> TestClient:
    return make_client()


def submit(c: TestClient, spec: dict[str, Any], **params: Any) -> dict[str, Any]:
    r = c.post("/jobs", json=spec, headers=AUTH, params=params)
    assert r.status_code == 201, r.text
    return r.json()


def wait_for(c: TestClient, job_id: str, statuses: set[str], timeout: float = 60) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        job = c.get(f"/jobs/{job_id}", headers=AUTH).json()
        if job["status"] in statuses:
            return job
        assert time.monotonic() < deadline, f"job still {job['status']} after {timeout} s: {job}"
        time.sleep(0.05)


def read_events(c: TestClient, job_id: str, headers: dict[str, str] | None = None) -> list[dict[str, Any]]:
    out, ev = [], {}
    with c.stream("GET", f"/jobs/{job_id}/events", params={"token": TOKEN}, headers=headers or {}) as r:
        assert r.status_code == 200
        for line in r.iter_lines():
            if not line:
                if ev:
                    out.append(ev)
                ev = {}
            elif not line.startswith(":"):
                key, _, value = line.partition(": ")
                ev[key] = json.loads(value) if key == "data" else value
    return out


# ---------------------------------------------------------------------------------------------- security
def test_health_needs_no_token(client):
    r = client.get("/health")
    assert r.status_code == 200
    assert r.json() == {"status": "ok", "workers": 0, "jobs_running": 0, "jobs_queued": 0}  # nothing locates the cluster


@pytest.mark.parametrize("method,path", [
    ("GET", "/jobs"), ("POST", "/jobs"), ("GET", "/jobs/abc"), ("DELETE", "/jobs/abc"), ("GET", "/jobs/abc/events"),
    ("GET", "/jobs/abc/report"), ("GET", "/jobs/abc/figures/trajectory.png"), ("GET", "/jobs/abc/controller"),
    ("GET", "/schema"), ("GET", "/openapi.json"),  # /docs and /redoc: static pages (tests/test_api_strict.py)
])
def test_every_route_but_health_needs_the_token(client, method, path):
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"}):
        r = client.request(method, path, headers=headers)
        assert r.status_code == 401, (headers, r.text)
        assert "token" in r.json()["detail"] and r.headers["www-authenticate"] == "Bearer"
    r = client.request(method, path, headers=AUTH, content=b"" if method == "POST" else None)
    assert r.status_code != 401
    r = client.request(method, path, params={"token": TOKEN})
    assert r.status_code != 401
    assert client.request(method, path, params={"token": TOKEN + "x"}).status_code == 401


def test_token_works_header_and_query(client):
    assert client.get("/jobs", headers=AUTH).json() == {"jobs": []}
    assert client.get("/jobs", params={"token": TOKEN}).json() == {"jobs": []}


def test_dashboard_page_and_assets_hold_no_data_and_need_no_token(client):
    r = client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert client.get("/static/index.html").status_code == 200
    assert client.get("/static/../app.py").status_code == 404


def test_without_a_token_setting_everything_is_open(make_client):
    c = make_client(token=None)
    assert c.get("/jobs").status_code == 200


# ---------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("field,expression,token", [
    (("subsystems", 0, "dynamics"), "__import__('os').system('true')", "__import__"),
    (("interconnection", "map"), "x[0].__class__", "__class__"),
    (("subsystems", 0, "dynamics"), "x[0].__class__.__mro__", "__class__"),
    (("subsystems", 0, "dynamics"), "(lambda: 1)()", "lambda"),
    (("subsystems", 0, "dynamics"), "os:system", "allowlist"),
])
def test_non_whitelisted_expression_is_422_naming_it(client, field, expression, token):
    spec = small()
    d = spec
    for k in field[:-1]:
        d = d[k]
    d[field[-1]] = expression
    r = client.post("/jobs", json=spec, headers=AUTH)
    assert r.status_code == 422, r.text
    assert token in r.json()["detail"]
    assert "Traceback" not in r.text
    assert client.get("/jobs", headers=AUTH).json() == {"jobs": []}  # never queued


@pytest.mark.parametrize("mutate,match", [
    (lambda d: d["subsystems"][0].update(samples="lots"), "subsystems.0.samples"),
    (lambda d: d["subsystems"][0].update(state={"lb": 5, "ub": 1, "eta": 1}), "empty box"),
    (lambda d: d["interconnection"].update(sigma=0), "interconnection.sigma"),
    (lambda d: d["specification"].update(target={"boxes": [{"lb": 0.6, "ub": 1.4}]}), "no whole grid cell"),
    (lambda d: d.update(surprise=1), "surprise"),
    (lambda d: d["subsystems"][0].update(replicate="M"), "'M'"),
])
def test_invalid_spec_is_422_naming_the_field(client, mutate, match):
    spec = small()
    mutate(spec)
    r = client.post("/jobs", json=spec, headers=AUTH)
    assert r.status_code == 422, r.text
    assert match in r.json()["detail"]


@pytest.mark.parametrize("body,content_type,status,match", [
    (b"{not json", "application/json", 422, "not valid JSON"),
    (b"[1, 2]", "application/json", 422, "mapping"),
    (b'{"name": NaN}', "application/json", 422, "NaN"),
    (b"a: [1, 2\n", "application/yaml", 422, "not valid YAML"),
    (b"a: &x [1, *x]\n", "application/yaml", 422, "recursive alias"),  # aliases: tests/test_api_strict.py
    (b"\xff\xfe", "text/plain", 422, "UTF-8"),
    (b"name: x", "application/xml", 415, "application/yaml"),
    (b"[" * 50_000, "application/json", 422, "nested"),
])
def test_unparsable_bodies_are_4xx_json(client, body, content_type, status, match):
    r = client.post("/jobs", content=body, headers={**AUTH, "content-type": content_type})
    assert r.status_code == status, r.text
    assert match in r.json()["detail"]


def test_query_errors_are_json_with_a_message(client):
    r = client.get("/jobs", params={"limit": 0}, headers=AUTH)
    assert r.status_code == 422 and "limit" in r.json()["detail"]


# ---------------------------------------------------------------------------------------------- caps
def test_body_cap_is_413_before_parsing(make_client):
    c = make_client(max_body_bytes=900)
    assert len(SMALL_YAML) > 900
    r = c.post("/jobs", content=SMALL_YAML, headers={**AUTH, "content-type": "application/yaml"})
    assert r.status_code == 413
    assert "max_body_bytes = 900" in r.json()["detail"]

    def chunks():  # no Content-Length: the cap must hold while the body streams in
        for _ in range(10):
            yield b"#" * 500

    r = c.post("/jobs", content=chunks(), headers={**AUTH, "content-type": "application/yaml"})
    assert r.status_code == 413 and "max_body_bytes" in r.json()["detail"]


@pytest.mark.parametrize("settings,mutate,match", [
    ({"max_cells": 5000}, None, "max_cells is 5000"),  # small.yaml: 33 x 5 x 33 = 5445 triples
    ({"max_expression_length": 20}, None, "max_expression_length is 20"),
    ({"max_subsystems": 1}, None, "max_subsystems is 1"),
    ({}, lambda d: d["parameters"].update(N=1e9), "max_subsystems is 256"),
])
def test_caps_are_422_naming_the_cap(make_client, settings, mutate, match):
    c = make_client(**settings)
    spec = small()
    if mutate:
        mutate(spec)
    r = c.post("/jobs", json=spec, headers=AUTH)
    assert r.status_code == 422, r.text
    assert match in r.json()["detail"]


def test_concurrency_cap_is_429_and_delete_frees_a_place(make_client):
    c = make_client(max_concurrent_jobs=2, max_running=1)
    first = submit(c, heavy())
    second = submit(c, heavy())
    r = c.post("/jobs", json=quick(), headers=AUTH)
    assert r.status_code == 429
    assert "max_concurrent_jobs is 2" in r.json()["detail"]
    # The second waits behind the first (max_running = 1): cancelling it is immediate.
    assert c.get(f"/jobs/{second['id']}", headers=AUTH).json()["status"] == "queued"
    r = c.delete(f"/jobs/{second['id']}", headers=AUTH)
    assert r.status_code == 200 and r.json()["status"] == "cancelled" and r.json()["finished_at"]
    third = submit(c, quick())
    # A running job stops at its next progress event.
    deadline = time.monotonic() + 60
    while not any(s["stage"] == "subsystems" for s in c.get(f"/jobs/{first['id']}", headers=AUTH).json()["stages"]):
        assert time.monotonic() < deadline, "the first job never reached its per-cell stage"
        time.sleep(0.05)
    r = c.delete(f"/jobs/{first['id']}", headers=AUTH)
    assert r.status_code == 200 and r.json()["status"] in ("running", "cancelled")
    job = wait_for(c, first["id"], {"cancelled", "failed", "succeeded"})
    assert job["status"] == "cancelled" and job["error"] is None
    # It stopped short of its end: the per-cell stage or a later one (the in-process per-cell stage can finish
    # between the request and the next progress event) is left unfinished.
    assert any(s["done"] < s["total"] for s in job["stages"]), job["stages"]
    assert wait_for(c, third["id"], {"succeeded", "failed"})["status"] == "succeeded"


# ---------------------------------------------------------------------------------------------- resources
def test_unknown_job_is_404(client):
    for path in ("/jobs/nope", "/jobs/nope/report", "/jobs/nope/events", "/jobs/nope/controller",
                 "/jobs/nope/figures/trajectory.png"):
        r = client.get(path, headers=AUTH)
        assert r.status_code == 404 and r.json() == {"detail": "no job nope"}, (path, r.text)
    assert client.delete("/jobs/nope", headers=AUTH).status_code == 404


def test_schema_and_openapi(client):
    assert client.get("/schema", headers=AUTH).json() == json_schema()
    doc = client.get("/openapi.json", headers=AUTH).json()
    assert "JobSpec" in doc["components"]["schemas"] and "Job" in doc["components"]["schemas"]
    body = doc["paths"]["/jobs"]["post"]["requestBody"]["content"]
    assert body["application/json"]["schema"] == {"$ref": "#/components/schemas/JobSpec"}
    assert "application/yaml" in body
    # Every $ref resolves inside the document.
    refs = set()

    def walk(o):
        if isinstance(o, dict):
            if "$ref" in o:
                refs.add(o["$ref"])
            for v in o.values():
                walk(v)
        elif isinstance(o, list):
            for v in o:
                walk(v)

    walk(doc)
    assert all(r.split("/")[-1] in doc["components"]["schemas"] for r in refs), refs
    page = client.get("/docs", params={"token": TOKEN})
    assert page.status_code == 200 and TOKEN not in page.text  # the page fetches the document with the header


@pytest.mark.parametrize("content_type", ["application/yaml", "text/yaml", "text/plain", None])
def test_yaml_bodies_are_accepted(client, content_type):
    headers = dict(AUTH)
    if content_type:
        headers["content-type"] = content_type
    text = yaml.safe_dump(quick())
    r = client.post("/jobs", content=text, headers=headers, params={"name": "from yaml"})
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["name"] == "from yaml" and job["status"] in ("queued", "running")
    assert wait_for(client, job["id"], {"succeeded", "failed"})["status"] == "succeeded"


def test_a_whole_job_events_results_and_no_path_traversal(client, tmp_path):
    job = submit(client, small())
    assert job["name"] == "small" and job["figures"] == [] and job["summary"] is None
    assert client.get(f"/jobs/{job['id']}/report", headers=AUTH).status_code in (409, 200)
    events = read_events(client, job["id"])
    assert [int(e["id"]) for e in events] == list(range(1, len(events) + 1))
    assert [e["data"]["status"] for e in events if e["event"] == "status"] == ["queued", "running", "succeeded"]
    progress = [e["data"] for e in events if e["event"] == "progress"]
    assert set(progress[0]) == {"stage", "done", "total", "message"}
    order = ["plan", "lipschitz", "subsystems", "interconnection", "audit", "synthesis", "closed_loop"]
    seen = [p["stage"] for p in progress]
    # Each stage once, in order; the audit runs beside synthesis (workers.processes.audit_beside): it starts before
    # synthesis, reports each part as it finishes (between synthesis events) and its end after the closed loop.
    others = [s for s in seen if s != "audit"]
    assert [s for i, s in enumerate(others) if i == 0 or others[i - 1] != s] == [s for s in order if s != "audit"]
    assert seen.index("audit") < seen.index("synthesis") and seen[-1] == "audit"
    audit = [p for p in progress if p["stage"] == "audit"]
    assert audit[0]["done"] == 0 and audit[-1]["done"] == audit[-1]["total"] and len(audit) >= 2
    assert [p["done"] / p["total"] for p in audit] == sorted(p["done"] / p["total"] for p in audit)
    final = events[-1]["data"]
    done = client.get(f"/jobs/{job['id']}", headers=AUTH).json()
    assert final == done
    assert [s["stage"] for s in done["stages"]] == order
    assert all(s["fraction"] == 1.0 for s in done["stages"])
    assert done["summary"]["audit_violations"] == 0 and done["summary"]["closed_loop_violations"] == 0
    assert done["summary"]["abstract_states"] == 1089
    assert done["started_at"] <= done["finished_at"]

    # A client that reconnects after the end is told to stop (204); one that missed events gets the rest.
    r = client.get(f"/jobs/{job['id']}/events", headers={**AUTH, "Last-Event-ID": events[-1]["id"]})
    assert r.status_code == 204
    rest = read_events(client, job["id"], headers={"Last-Event-ID": events[-3]["id"]})
    assert [e["id"] for e in rest] == [e["id"] for e in events[-2:]]

    report = client.get(f"/jobs/{job['id']}/report", headers=AUTH)
    assert report.status_code == 200 and report.json()["figures"] == done["figures"] == ["trajectory.png", "phase_plane.png"]
    for name in done["figures"]:
        r = client.get(f"/jobs/{job['id']}/figures/{name}", params={"token": TOKEN})
        assert r.status_code == 200 and r.headers["content-type"] == "image/png" and r.content[:4] == b"\x89PNG"
    # Only the report's figure names reach the disk: files next to them, or outside, are refused.
    data_dir = tmp_path / "data"
    (data_dir / "secret.png").write_bytes(b"\x89PNG secret")
    for name in ("report.json", "spec.json", "controller.json", "..%2F..%2Fsecret.png", "..%2Fsecret.png",
                 "%2E%2E%2F%2E%2E%2Fsecret.png", "trajectory.png%00.json", "TRAJECTORY.PNG"):
        r = client.get(f"/jobs/{job['id']}/figures/{name}", headers=AUTH)
        assert r.status_code == 404, (name, r.status_code, r.content[:100])
        assert b"secret" not in r.content
    for path in (f"/jobs/{job['id']}/figures/../report", f"/jobs/{job['id']}/figures/../../../secret.png"):
        assert b"secret" not in client.get(path, headers=AUTH).content

    z = client.get(f"/jobs/{job['id']}/controller", headers=AUTH)
    assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(z.content)) as archive:
        assert sorted(archive.namelist()) == ["controller.dddmp", "controller.json"]
    assert client.get("/jobs", headers=AUTH).json()["jobs"][0]["id"] == job["id"]


def test_results_of_an_unfinished_or_failed_job_are_409(client):
    spec = small()
    spec["subsystems"][0]["dynamics"] = "sqrt(x[0] - 16)"  # compiles, then returns NaN below 16: fails at run time
    job = submit(client, spec)
    failed = wait_for(client, job["id"], {"failed", "succeeded"})
    assert failed["status"] == "failed" and "not finite" in failed["error"]
    for what in ("report", "controller", "figures/trajectory.png"):
        r = client.get(f"/jobs/{job['id']}/{what}", headers=AUTH)
        assert r.status_code == 409 and "failed" in r.json()["detail"]


def test_jobs_list_is_newest_first(client):
    ids = [submit(client, quick())["id"] for _ in range(3)]
    listed = [j["id"] for j in client.get("/jobs", headers=AUTH).json()["jobs"]]
    assert listed == ids[::-1]
    assert [j["id"] for j in client.get("/jobs", params={"limit": 2}, headers=AUTH).json()["jobs"]] == ids[:0:-1]
    for i in ids:
        wait_for(client, i, {"succeeded", "failed"})


# ---------------------------------------------------------------------------------------------- restart
def test_jobs_left_running_are_requeued_or_ended_at_start_up(tmp_path, make_client):
    """What an API process killed mid-job leaves in the store, seen by the next process."""
    settings = Settings(data_dir=tmp_path / "data", in_process=True, token=TOKEN, max_resumes=2)
    store = new_store(settings)
    spec = parse_spec(quick()).model_dump_json()
    ids = {}
    for label, attempts, cancel in (("resume", 1, False), ("given-up", 3, False), ("cancelled", 1, True)):
        store.create(label, label, spec)
        store.set_status(label, "running", started=True, attempts_delta=attempts)
        if cancel:
            store.request_cancel(label)
        ids[label] = label
    store.close()
    # The synthesis iterates a stopped job left (workers.checkpoint_store) go with a job that ends there, its other
    # files stay.
    for label in ("given-up", "cancelled"):
        checkpoints = settings.jobs_dir / label / jobdir.CHECKPOINTS
        checkpoints.mkdir(parents=True)
        (checkpoints / "reach_safe-safe.dddmp").write_bytes(b"iterate")
        (checkpoints / "reach_safe-safe.json").write_text("{}")
        (settings.jobs_dir / label / "chunk.npy").write_bytes(b"kept")

    c = make_client(max_resumes=2)
    resumed = wait_for(c, "resume", {"succeeded", "failed", "cancelled"})
    assert resumed["status"] == "succeeded", resumed
    gave_up = c.get("/jobs/given-up", headers=AUTH).json()
    assert gave_up["status"] == "failed" and "max_resumes = 2" in gave_up["error"]
    assert c.get("/jobs/cancelled", headers=AUTH).json()["status"] == "cancelled"
    for label in ("given-up", "cancelled"):
        assert not (settings.jobs_dir / label / jobdir.CHECKPOINTS).exists()
        assert (settings.jobs_dir / label / "chunk.npy").read_bytes() == b"kept"
    statuses = [e["data"]["status"] for e in read_events(c, "resume") if e["event"] == "status"]
    assert statuses == ["queued", "running", "queued", "running", "succeeded"]
    db = sqlite3.connect(settings.database_url.removeprefix("sqlite:///"))
    try:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    finally:
        db.close()


def test_settings_from_environment():
    s = Settings.from_env({"COMPABS_TOKEN": "t", "COMPABS_WORKERS": "3", "COMPABS_ALLOWED_MODULES": "a.b, c",
                           "COMPABS_MAX_CELLS": "10", "COMPABS_SCHEDULER": "", "OTHER": "x"}, port=9000)
    assert (s.token, s.workers, s.allowed_modules, s.max_cells, s.scheduler, s.port) == ("t", 3, ["a.b", "c"], 10, None, 9000)
    assert s.host == "127.0.0.1" and s.database_url.endswith("/compabs-data/jobs.sqlite")
    with pytest.raises(ValueError, match="COMPABS_WORKERS"):
        Settings.from_env({"COMPABS_WORKERS": "many"})


def test_serve_refuses_an_unset_token_variable(monkeypatch, capsys):
    monkeypatch.delenv("NO_SUCH_TOKEN_VARIABLE", raising=False)
    assert main(["serve", "--token-env", "NO_SUCH_TOKEN_VARIABLE"]) == 2
    assert "NO_SUCH_TOKEN_VARIABLE" in capsys.readouterr().err
