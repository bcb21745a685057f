"""Strict input everywhere (issue 47): what a hostile but authenticated user found accepted, or answered with a 500.

* Expressions are parsed one at a time (CPython 3.11's ``ast.parse`` is not thread-safe, gh-106905: 20 concurrent
  ``POST /jobs`` gave one ``SystemError``): every parse holds ``PARSE_LOCK``, and 20 concurrent submissions are
  all accepted.
* The API runs every check ``compabs validate`` runs: initial states of the wrong dimension are a 422, not a 201.
* A boolean is not a number, a string is not a number, a float is not an integer; every example still validates.
* A key given twice (YAML or JSON) is refused, naming it and where; a YAML merge key is not a duplicate.
* ``?token=`` never reaches the access log (a real uvicorn server, its ``uvicorn.access`` lines read).
* A killed process's temporary cluster credentials are removed at the next start.
"""

from __future__ import annotations

import ast
import logging
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import yaml
from fastapi.testclient import TestClient

from pipelines.errors import SpecError
from pipelines.spec.model import load_spec, parse_spec
from service.app import create_app, redact_token
from service.settings import Settings

from .conftest import EXAMPLES
from .processes import free_port

TOKEN = "strict-input-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def small() -> dict[str, Any]:
    return yaml.safe_load((EXAMPLES / "small.yaml").read_text())


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    """The app whose queue never starts a job: a submitted job stays queued."""
    settings = Settings(data_dir=tmp_path / "data", in_process=True, token=TOKEN, max_concurrent_jobs=1000)
    with TestClient(create_app(settings)) as c:
        c.app.state.manager._kick = lambda: None  # type: ignore[attr-defined]
        yield c


# ============================================================================================ parsing under a lock
def test_every_parse_holds_the_lock_and_concurrent_submissions_are_accepted(client, monkeypatch):
    from pipelines.expressions.checks import PARSE_LOCK

    real_parse, active, seen, unlocked = ast.parse, [0], [0], []
    guard = threading.Lock()

    def parse(source, *args, **kwargs):
        if not PARSE_LOCK.locked():
            unlocked.append(source[:40])
        with guard:
            active[0] += 1
            seen[0] = max(seen[0], active[0])
        try:
            time.sleep(0.001)  # widen the window two unlocked parses would need to overlap
            return real_parse(source, *args, **kwargs)
        finally:
            with guard:
                active[0] -= 1

    monkeypatch.setattr(ast, "parse", parse)
    spec = small()
    spec["subsystems"][0]["reads"] = ["0 * i"]  # the spec model's own parse of reads entries too
    results: list[int] = []

    def submit() -> None:
        results.append(client.post("/jobs", json=spec, headers=AUTH).status_code)

    threads = [threading.Thread(target=submit) for _ in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert results == [201] * 20
    assert unlocked == [] and seen[0] == 1


# ============================================================================================ the checks of validate
def test_initial_states_of_the_wrong_dimension_are_422(client):
    spec = small()
    spec["options"]["initial_states"] = [[12.3, 16.2, 1.0]]
    r = client.post("/jobs", json=spec, headers=AUTH)
    assert r.status_code == 422, r.text
    assert "options.initial_states[0] has 3 components; the system has 2 states" in r.json()["detail"]
    assert client.get("/jobs", headers=AUTH).json() == {"jobs": []}


# ============================================================================================ types
@pytest.mark.parametrize("path,value,said", [
    (("subsystems", 0, "substeps"), True, "not the boolean true"),
    (("subsystems", 0, "samples"), True, "not the boolean true"),
    (("subsystems", 0, "samples"), "100", "not the string '100'"),
    (("subsystems", 0, "lipschitz", "x"), "1.76", "not the string '1.76'"),
    (("options", "audit_transitions"), 1.5, "an integer, not 1.5"),
    (("options", "synthesis"), 1, "valid boolean"),
    (("options", "seed"), False, "not the boolean false"),
    (("parameters", "N"), True, "not the boolean true"),
    (("subsystems", 0, "state", "eta"), "1", "not the string '1'"),
    (("name",), 5, "valid string"),
])
def test_booleans_and_strings_are_not_numbers(client, path, value, said):
    spec = small()
    if path[-1] == "substeps":  # an ode subsystem, where substeps belongs
        spec["subsystems"][0]["ode"] = spec["subsystems"][0].pop("dynamics")
        spec["subsystems"][0]["sampling_time"] = 0.1
    target = spec
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    field = ".".join(str(p) for p in path)
    with pytest.raises(SpecError) as err:
        parse_spec(spec)
    assert field in str(err.value) and said in str(err.value), str(err.value)
    r = client.post("/jobs", json=spec, headers=AUTH)
    assert r.status_code == 422 and field in r.json()["detail"] and said in r.json()["detail"], r.text


def test_integers_are_still_numbers():
    spec = small()
    spec["subsystems"][0]["lipschitz"]["x"] = 2
    spec["subsystems"][0]["state"] = {"lb": 0, "ub": 32, "eta": 1}
    assert parse_spec(spec).subsystems[0].lipschitz.x == 2.0


def test_yaml_exponents_are_numbers_as_in_json():
    """YAML 1.1 reads ``1e-6`` and ``1.5e3`` as strings, which the strict model would refuse; a spec reads numbers,
    as YAML 1.2 and JSON do. A quoted one stays a string (and is refused)."""
    text = (EXAMPLES / "scalability.yaml").read_text()
    assert "alpha: 1.0e-6" in text
    for literal, value in (("1e-6", 1e-6), ("1.5e-3", 1.5e-3), ("2E-2", 0.02)):
        assert parse_spec(text.replace("alpha: 1.0e-6", f"alpha: {literal}")).interconnection.alpha == value
    with pytest.raises(SpecError, match="interconnection.alpha: Input should be a number, not the string '1e-6'"):
        parse_spec(text.replace("alpha: 1.0e-6", "alpha: '1e-6'"))


@pytest.mark.parametrize("example", sorted(EXAMPLES.glob("*.yaml")), ids=lambda p: p.name)
def test_every_example_is_still_accepted(example):
    spec = load_spec(example)
    assert parse_spec(spec.model_dump(mode="json")) == spec  # and through the job store's JSON


# ============================================================================================ duplicate keys
def test_a_duplicate_yaml_key_is_422_naming_it_and_its_line(client):
    text = (EXAMPLES / "small.yaml").read_text().replace("  samples: 20\n", "  samples: 20\n  sigma: 2\n  samples: 30\n")
    r = client.post("/jobs", content=text, headers={**AUTH, "content-type": "application/yaml"})
    assert r.status_code == 422, r.text
    assert "the key 'samples' is given twice" in r.json()["detail"] and "line" in r.json()["detail"]
    with pytest.raises(SpecError, match="'samples' is given twice"):
        parse_spec(text)


def test_a_duplicate_json_key_is_422_naming_its_object(client):
    body = '{"name": "a", "options": {"seed": 1, "seed": 2}}'
    r = client.post("/jobs", content=body, headers={**AUTH, "content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["detail"] == "options: the key 'seed' is given twice in one object; give each key once"


def test_a_merge_key_is_not_a_duplicate():
    text = (EXAMPLES / "tanks.yaml").read_text()
    assert "<<:" in text
    parse_spec(text)


# ============================================================================================ tokens in logs
def test_redact_token():
    assert redact_token("/jobs/1/events?token=s3cret&x=1") == "/jobs/1/events?token=[redacted]&x=1"
    assert redact_token("/jobs?tok%65n=s3cret") == "/jobs?tok%65n=[redacted]"
    assert redact_token("/jobs?x=token=1") == "/jobs?x=token=1"
    assert redact_token("/jobs") == "/jobs"


def test_the_token_never_reaches_the_access_log(tmp_path):
    import uvicorn

    secret = "query-token-s3cret"
    settings = Settings(data_dir=tmp_path / "data", in_process=True, token=secret)
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1", port=free_port(),
                                           log_level="info", lifespan="on"))
    lines: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(record.getMessage())

    handler = Collect()
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 60
        while not server.started:
            assert time.monotonic() < deadline and thread.is_alive(), "the server did not start"
            time.sleep(0.05)
        logging.getLogger("uvicorn.access").addHandler(handler)
        url = f"http://127.0.0.1:{server.config.port}"
        with httpx.Client(base_url=url, timeout=30) as http:
            assert http.get("/jobs", params={"token": secret}).status_code == 200
            assert http.get(f"/jobs?tok%65n={secret}").status_code == 200
            assert http.get("/jobs/none/events", params={"token": secret, "x": "1"}).status_code == 404
            assert http.get("/jobs", params={"token": secret + "x"}).status_code == 401
        assert len(lines) == 4, lines
        assert not any(secret in line for line in lines), lines
        assert all("[redacted]" in line for line in lines), lines
    finally:
        logging.getLogger("uvicorn.access").removeHandler(handler)
        server.should_exit = True
        thread.join(30)


# ============================================================================================ stale credentials
def test_stale_credentials_directories_are_removed(tmp_path):
    from workers.cluster import TLS_TMP_PREFIX, remove_stale_credentials

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    import os

    stale = tmp_path / f"{TLS_TMP_PREFIX}{gone.pid}-abcd"
    mine = tmp_path / f"{TLS_TMP_PREFIX}{os.getpid()}-efgh"
    old_form = tmp_path / f"{TLS_TMP_PREFIX}xyz123"  # no pid: whose it is cannot be told
    for d in (stale, mine, old_form):
        d.mkdir(mode=0o700)
        (d / "key.pem").write_text("PRIVATE KEY")
    assert remove_stale_credentials(tmp_path) == [stale]
    assert not stale.exists() and mine.exists() and old_form.exists()


# ============================================================================================ helper processes
@pytest.mark.parametrize("given,on,cluster,want", [
    (64, "processes", False, 2), (64, "processes", True, 2), (64, "auto", False, 2), (64, "auto", True, 64),
    (64, "cluster", True, 64), (2, "processes", False, 2), (1, "processes", False, 1),
    ("auto", "processes", False, "auto"),
])
def test_local_synthesis_helpers_are_capped_by_the_cores(given, on, cluster, want):
    """``synthesis_processes: 64`` with local helpers (56 were started on 2 cores, 3.5 GB) becomes the cores
    present; on a cluster it is the number of parts and stays."""
    from pipelines.spec.validate import cap_synthesis_processes

    spec = small()
    spec["options"].update(synthesis_processes=given, synthesis_on=on)
    capped = cap_synthesis_processes(parse_spec(spec), on_cluster=cluster, cpus=2)
    assert capped.options.synthesis_processes == want
