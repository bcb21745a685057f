"""The API's boundary, strictly (issue 23, defects 4-7): numbers, integers, headers, disconnects, docs, YAML aliases.

* Finite numbers only: ``1e999`` in JSON, ``.inf``/``-.inf``/``.nan`` in YAML are a 422 naming the field, through
  the API and through ``parse_spec``/``load_spec`` (the CLI), for every number of every example (none becomes
  null or its default on the way to the job store).
* Integers of more than ``MAX_INT_DIGITS`` digits: a 422 naming where (the JSON path, the YAML line), not Python's
  "exceeds the limit (4300 digits)" ``ValueError`` as a 500.
* ``Last-Event-ID`` is 1 to 18 ASCII digits or a 422 (``"²"`` and ids >= 2^63 were 500s); ``Content-Length`` is
  decimal digits or a 400; a charset other than UTF-8 is a 415; a client that disconnects mid-body is one INFO
  line, not an ERROR with a traceback.
* ``/docs`` and ``/redoc``: the same static page whatever the query string, assets from this server only.
* YAML anchors and aliases: ``examples/tanks.yaml`` is accepted; a document that expands beyond
  ``MAX_YAML_NODES`` values (a "billion laughs") or contains itself is a 422 naming the bound, found without
  expanding it.

The browser side (Swagger UI and ReDoc rendering on a closed network, the dashboard's exact integers):
``tests/test_dashboard_browser.py``.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Iterator
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from pipelines.errors import SpecError
from pipelines.spec.loader import MAX_INT_DIGITS, MAX_YAML_NODES, expanded_size, load_json, load_yaml
from pipelines.spec.model import JobSpec, load_spec, parse_spec
from service.app import create_app
from service.job_store import JobStatus
from service.settings import Settings

from .conftest import EXAMPLES, ROOT

TOKEN = "strict-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SMALL_YAML = (EXAMPLES / "small.yaml").read_text()
EXAMPLE_FILES = sorted(EXAMPLES.glob("*.yaml"))
BIG = "9" * 5000


def small() -> dict[str, Any]:
    return yaml.safe_load(SMALL_YAML)


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    """The app with in-process jobs that never start (the queue is not kicked): a submitted job stays queued."""
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", in_process=True, token=TOKEN))) as c:
        c.app.state.manager._kick = lambda: None  # type: ignore[attr-defined]
        yield c


def post(c: TestClient, body: str | bytes, content_type: str) -> Any:
    return c.post("/jobs", content=body, headers={**AUTH, "content-type": content_type})


def put(data: Any, path: tuple[Any, ...], value: Any) -> None:
    """``data[p0][p1]... = value``, making the mappings on the way."""
    for key in path[:-1]:
        if isinstance(data, dict) and key not in data:
            data[key] = {}
        data = data[key]
    data[path[-1]] = value


def dotted(path: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in path)


# ================================================================================================ finite numbers
#: Number fields of every kind: float, float | list, float | 'estimate', float | 'cv', optional floats whose
#: default is None (the fields that silently became None), dict values, tuple and nested-list items, ints.
NUMBER_PATHS: list[tuple[Any, ...]] = [
    ("subsystems", 0, "lipschitz", "safety_factor"),
    ("subsystems", 0, "lipschitz", "delta"),
    ("subsystems", 0, "lipschitz", "x"),
    ("subsystems", 0, "lipschitz", "w"),
    ("subsystems", 0, "state", "lb"),
    ("subsystems", 0, "state", "eta"),
    ("subsystems", 0, "input", "origin"),
    ("subsystems", 0, "samples"),
    ("interconnection", "lipschitz"),
    ("interconnection", "intermediate_eta"),
    ("interconnection", "alpha"),
    ("interconnection", "internal", "ub"),
    ("parameters", "N"),
    ("specification", "target", "consensus", "radius"),
    ("specification", "target", "consensus", "centers", 2),
    ("options", "task_timeout"),
    ("options", "initial_states", 0, 1),
    ("options", "seed"),
]


def _json_with(path: tuple[Any, ...], literal: str) -> str:
    """small.yaml as JSON text with the number at ``path`` written as ``literal`` (e.g. ``1e999``)."""
    data = small()
    put(data, path, "@@NUMBER@@")
    return json.dumps(data).replace('"@@NUMBER@@"', literal)


@pytest.mark.parametrize("literal", ["1e999", "-1e999"])
@pytest.mark.parametrize("path", NUMBER_PATHS, ids=dotted)
def test_json_overflowing_number_is_422_naming_the_field(client, path, literal):
    r = post(client, _json_with(path, literal), "application/json")
    assert r.status_code == 422, r.text
    assert dotted(path) in r.json()["detail"] and "finite" in r.json()["detail"], r.text


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan], ids=["inf", "-inf", "nan"])
@pytest.mark.parametrize("path", NUMBER_PATHS, ids=dotted)
def test_yaml_non_finite_is_422_naming_the_field(client, path, value):
    data = small()
    put(data, path, value)
    text = yaml.safe_dump(data, sort_keys=False)
    assert re.search(r"-?\.(inf|nan)\b", text)
    r = post(client, text, "application/yaml")
    assert r.status_code == 422, r.text
    assert dotted(path) in r.json()["detail"], r.text
    assert client.get("/jobs", headers=AUTH).json() == {"jobs": []}  # nothing stored


@pytest.mark.parametrize("path", NUMBER_PATHS, ids=dotted)
def test_cli_spec_readers_refuse_non_finite(tmp_path, path):
    """``parse_spec`` (text and dict) and ``load_spec`` (a file), as ``compabs run``/``validate`` read specs."""
    data = small()
    put(data, path, math.inf)
    text = yaml.safe_dump(data, sort_keys=False)
    file = tmp_path / "spec.yaml"
    file.write_text(text)
    for read in (lambda: parse_spec(text), lambda: parse_spec(data), lambda: load_spec(file)):
        with pytest.raises(SpecError, match=re.escape(dotted(path))):
            read()


def test_set_override_non_finite_is_refused():
    with pytest.raises(SpecError, match=r"parameters\.N: .*finite"):
        parse_spec(SMALL_YAML, overrides={"N": math.inf})


def _number_leaves(data: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    if isinstance(data, dict):
        for k, v in data.items():
            yield from _number_leaves(v, (*path, k))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield from _number_leaves(v, (*path, i))
    elif isinstance(data, (int, float)) and not isinstance(data, bool):
        yield path


@pytest.mark.parametrize("example", EXAMPLE_FILES, ids=lambda p: p.name)
def test_every_number_of_every_example_refuses_non_finite(example):
    """No number anywhere in a spec becomes null or its default: each one, set to inf or nan, is refused by name."""
    base = json.dumps(yaml.safe_load(example.read_text()))  # as JSON: no values shared through YAML aliases
    leaves = list(_number_leaves(json.loads(base)))
    assert leaves
    for path in leaves:
        for value in (math.inf, math.nan):
            data = json.loads(base)
            put(data, path, value)
            with pytest.raises(SpecError) as err:
                parse_spec(data)
            assert dotted(path) in str(err.value), (path, str(err.value))


@pytest.mark.parametrize("example", EXAMPLE_FILES, ids=lambda p: p.name)
def test_examples_round_trip_through_the_job_store_json(example):
    """What the store keeps (``model_dump_json``) validates back to the same spec: no number is lost as null."""
    spec = load_spec(example)
    assert JobSpec.model_validate_json(spec.model_dump_json()) == spec


# ================================================================================================ big integers
@pytest.mark.parametrize("path", [("subsystems", 0, "samples"), ("options", "seed"), ("subsystems", 0, "state", "lb"),
                                  ("parameters", "N")], ids=dotted)
@pytest.mark.parametrize("sign", ["", "-"])
def test_json_big_integer_is_422_naming_the_path(client, path, sign):
    r = post(client, _json_with(path, sign + BIG), "application/json")
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert dotted(path) in detail and "5,000 digits" in detail and f"at most {MAX_INT_DIGITS} digits" in detail


@pytest.mark.parametrize("literal,digits", [
    (BIG, "5,000"), ("-" + BIG, "5,000"), ("0x" + "f" * 5000, None), (":".join(["59"] * 3000), None),
    ("0x" + "f" * 100, "121"), ("1" + "_0" * 101, None),
])
def test_yaml_big_integer_is_422_naming_the_line(client, literal, digits):
    text = SMALL_YAML.replace("  N: 2\n", f"  N: {literal}\n")
    assert text != SMALL_YAML
    line = SMALL_YAML.splitlines().index("  N: 2") + 1
    r = post(client, text, "application/yaml")
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert f"line {line}, column 6" in detail and f"at most {MAX_INT_DIGITS} digits" in detail, detail
    if digits:
        assert f"{digits} digits" in detail
    with pytest.raises(SpecError, match=f"line {line}, column 6"):  # the CLI's reader too
        parse_spec(text)


def test_integers_up_to_the_bound_are_read():
    top = "9" * MAX_INT_DIGITS
    assert load_json(f'{{"a": [{top}, -{top}]}}') == {"a": [int(top), -int(top)]}
    assert load_yaml(f"a: [{top}, -{top}, 0x1F, 1_000]") == {"a": [int(top), -int(top), 31, 1000]}
    with pytest.raises(SpecError, match=r"a\.0: an integer of 101 digits"):
        load_json(f'{{"a": [{top}9]}}')


# ================================================================================================ headers
def _queued_job(c: TestClient) -> str:
    r = post(c, SMALL_YAML, "application/yaml")
    assert r.status_code == 201, r.text
    assert r.json()["status"] == "queued"
    return r.json()["id"]


@pytest.mark.parametrize("value", ["²".encode("latin-1"), str(2**63).encode(), b"9" * 19, b"1" + b"0" * 5000],
                         ids=["sup2", "2^63", "19-digits", "5001-digits"])
def test_last_event_id_on_a_live_job_is_422(client, value):
    job = _queued_job(client)
    r = client.get(f"/jobs/{job}/events", headers={**AUTH, "Last-Event-ID": value})
    assert r.status_code == 422, r.text
    assert "last-event-id" in r.json()["detail"].lower()


@pytest.mark.parametrize("value", [b"-1", b"+1", b"1e3", b"1_0", "１".encode(), "²".encode(), b"0x1", b"1.0", b""])
def test_last_event_id_not_in_decimal_digits_is_422(client, value):
    job = _queued_job(client)
    client.delete(f"/jobs/{job}", headers=AUTH)  # an ended job: the old code answered these with a stream
    r = client.get(f"/jobs/{job}/events", headers={**AUTH, "Last-Event-ID": value})
    assert r.status_code == 422, r.text
    assert "last-event-id" in r.json()["detail"].lower()


def test_last_event_id_in_range_resumes(client):
    job = _queued_job(client)
    client.delete(f"/jobs/{job}", headers=AUTH)
    assert client.app.state.manager.store.get(job).status == JobStatus.CANCELLED
    r = client.get(f"/jobs/{job}/events", headers={**AUTH, "Last-Event-ID": "1"})
    assert r.status_code == 200 and "id: 1\n" not in r.text and "id: 2" in r.text, r.text
    for top in ("999999999999999999", "2"):  # >= the last id of an ended job: nothing more to send
        assert client.get(f"/jobs/{job}/events", headers={**AUTH, "Last-Event-ID": top}).status_code == 204


def _asgi(c: TestClient, headers: list[tuple[bytes, bytes]], chunks: list[bytes],
          disconnect: bool = False) -> tuple[int | None, bytes]:
    """POST /jobs straight to the ASGI app with exactly these headers and body chunks (then, optionally, the client
    disconnects before the last chunk); returns the status and body sent."""
    messages: list[dict[str, Any]] = [{"type": "http.request", "body": b, "more_body": True} for b in chunks]
    if disconnect:
        messages.append({"type": "http.disconnect"})
    else:
        messages.append({"type": "http.request", "body": b"", "more_body": False})
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        return messages.pop(0) if messages else {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": "/jobs", "raw_path": b"/jobs", "query_string": b"", "root_path": "",
             "headers": [(b"host", b"test"), (b"authorization", f"Bearer {TOKEN}".encode()), *headers],
             "client": ("127.0.0.1", 50000), "server": ("127.0.0.1", 80), "state": {}}

    async def call() -> None:
        await c.app(scope, receive, send)

    c.portal.call(call)
    status = next((m["status"] for m in sent if m["type"] == "http.response.start"), None)
    return status, b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")


@pytest.mark.parametrize("value", [b"+5", b" 5", b"5 ", b"1_0", b"-1", b"0x10", "５".encode(), b"9" * 5000])
def test_content_length_must_be_decimal_digits(client, value):
    status, body = _asgi(client, [(b"content-type", b"application/yaml"), (b"content-length", value)], [b"a: 1"])
    assert status == 400, body
    assert "Content-Length" in json.loads(body)["detail"]


def test_content_length_in_digits_is_read(client):
    body = SMALL_YAML.encode()
    status, answer = _asgi(client, [(b"content-type", b"application/yaml"),
                                    (b"content-length", str(len(body)).encode())], [body])
    assert status == 201, answer


@pytest.mark.parametrize("content_type,status", [
    ("application/json; charset=latin-1", 415), ('application/json; charset="iso-8859-1"', 415),
    ("application/yaml; charset=utf-16", 415), ("application/json; charset=UTF-8", 201),
    ('application/json; charset="utf-8"', 201), ("application/json;charset=utf8", 201),
])
def test_charset_other_than_utf8_is_415(client, content_type, status):
    r = post(client, json.dumps(small()), content_type)
    assert r.status_code == status, r.text
    if status == 415:
        assert "UTF-8" in r.json()["detail"]


def test_client_disconnect_mid_body_is_one_info_line(client, caplog):
    caplog.set_level(logging.INFO)
    status, _ = _asgi(client, [(b"content-type", b"application/yaml"), (b"content-length", b"5000")],
                      [SMALL_YAML.encode()[:100]], disconnect=True)
    records = [r for r in caplog.records if r.name.startswith("compabs")]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
    disconnects = [r for r in records if "disconnected" in r.getMessage()]
    assert len(disconnects) == 1 and disconnects[0].levelno in (logging.INFO, logging.WARNING), caplog.text
    assert disconnects[0].exc_info is None and "POST /jobs" in disconnects[0].getMessage()
    assert status != 500
    assert client.get("/jobs", headers=AUTH).json() == {"jobs": []}


# ================================================================================================ /docs, /redoc
XSS = "x';alert(document.domain)//"


@pytest.mark.parametrize("page,file", [("/docs", "docs.html"), ("/redoc", "redoc.html")])
def test_docs_pages_are_static_and_local(client, page, file):
    expected = (ROOT / "service" / "static" / file).read_text()
    for params, headers in (({}, {}), ({"token": XSS}, AUTH), ({"token": TOKEN}, {}), ({"url": XSS}, AUTH)):
        r = client.get(page, params=params, headers=headers)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html"), r.text
        assert r.text == expected  # nothing from the request is in the page
        csp = r.headers["content-security-policy"]
        assert "default-src 'self'" in csp and "script-src 'self'" in csp and "connect-src 'self'" in csp
    assert TOKEN not in expected and "alert(" not in expected and "token=" not in expected
    sources = re.findall(r'(?:src|href)="([^"]*)"', expected)
    assert sources and all(s.startswith("/") and not s.startswith("//") for s in sources), sources
    assert "<script>" not in expected  # no inline script (the CSP would block it anyway)
    for src in re.findall(r'src="([^"]*)"', expected) + re.findall(r'<link rel="stylesheet" href="([^"]*)"', expected):
        asset = client.get(src)
        assert asset.status_code == 200 and asset.content, src
        assert b"cdn.jsdelivr" not in asset.content[:2000], src


def test_openapi_document_still_needs_the_token(client):
    assert client.get("/openapi.json").status_code == 401
    assert client.get("/openapi.json", params={"token": XSS}).status_code == 401
    doc = client.get("/openapi.json", headers=AUTH).json()
    assert "HTTPBearer" in doc["components"]["securitySchemes"]  # the scheme docs.js pre-authorises
    header = [p for p in doc["paths"]["/jobs/{job_id}/events"]["get"]["parameters"] if p["in"] == "header"]
    assert header and header[0]["schema"]["anyOf"][0]["pattern"] == "^[0-9]{1,18}$", header


# ================================================================================================ YAML aliases
def _laughs(levels: int, width: int = 10) -> str:
    lines = ["a0: &a0 [" + ", ".join(["lol"] * width) + "]"]
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]")
    return "\n".join(lines) + "\n"


def test_flagship_example_with_anchors_is_accepted(client):
    text = (EXAMPLES / "tanks.yaml").read_text()
    assert "&tap" in text and "<<: *tap" in text and "*w" in text
    r = post(client, text, "application/yaml")
    assert r.status_code == 201, r.text
    stored = client.app.state.manager.store.get(r.json()["id"]).spec
    assert json.loads(stored) == json.loads(load_spec(EXAMPLES / "tanks.yaml").model_dump_json())
    subsystems = json.loads(stored)["subsystems"]
    assert [s["name"] for s in subsystems] == [f"tank{i}" for i in range(1, 11)]
    assert subsystems[2]["samples"] == 150 and subsystems[2]["input"]["ub"] == 0  # merged from *tank, *tap


def test_billion_laughs_is_422_naming_the_bound(client, tmp_path):
    text = _laughs(10)  # 10^10 values once expanded, 300 bytes
    assert len(text) < 600
    r = post(client, text, "application/yaml")
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "MAX_YAML_NODES" in detail and f"{MAX_YAML_NODES:,}" in detail and "aliases" in detail, detail
    (tmp_path / "lol.yaml").write_text(text)
    with pytest.raises(SpecError, match="MAX_YAML_NODES"):
        load_spec(tmp_path / "lol.yaml")
    # inside a spec too, as JSON-compatible flow YAML
    spec = SMALL_YAML.replace("name: small\n", "name: small\nx-bomb:\n" + "".join(
        "  " + line + "\n" for line in _laughs(8).splitlines()))
    r = post(client, spec, "application/yaml")
    assert r.status_code == 422 and "MAX_YAML_NODES" in r.json()["detail"], r.text


def test_recursive_alias_is_422(client):
    for text in ("a: &x [1, *x]\n", "a: &x {b: *x}\n"):
        r = post(client, text, "application/yaml")
        assert r.status_code == 422 and "recursive alias" in r.json()["detail"], r.text


def test_expanded_size_is_counted_exactly_without_expanding():
    # a0: 1 list + 10 scalars; each next level: 1 list + 10 copies of the previous; plus the mapping and its keys.
    for levels in (1, 3, 5):
        node = yaml.compose(_laughs(levels))
        level = [11]
        for _ in range(1, levels):
            level.append(1 + 10 * level[-1])
        assert expanded_size(node) == 1 + levels + sum(level)
    assert load_yaml(_laughs(5))["a4"][9][9][9][9] == ["lol"] * 10  # 111,111 values: under the bound, read
    with pytest.raises(SpecError, match="line 6"):  # the first value past the bound is on line 6 (a5)
        load_yaml(_laughs(7))


def test_examples_parse_identically_to_pyyaml():
    """The bounded loader reads every example exactly as PyYAML's safe loader does."""
    for example in EXAMPLE_FILES:
        text = example.read_text()
        assert load_yaml(text) == yaml.safe_load(text), example.name


def test_a_query_parameter_given_twice_is_refused(tmp_path):
    """Starlette keeps the last of several values (``?limit=1&limit=360`` listed 360 jobs): schemathesis found it
    accepting a schema-violating request. Every parameter of the API is one value."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    with TestClient(create_app(Settings(data_dir=tmp_path, in_process=True))) as client:
        r = client.get("/jobs?limit=1&limit=360")
        assert r.status_code == 422 and "'limit' is given 2 times" in r.json()["detail"], r.text
        assert client.get("/jobs?limit=1").status_code == 200


def test_an_unknown_key_named_like_a_union_tag_is_named():
    """The error formatter drops pydantic's union tags (``float``, ``none``, ...) from field names; an unknown key a
    user called ``none`` is not a tag and must still be named (found by the trust campaign's mutated specs)."""
    import yaml

    from pipelines.errors import SpecError
    from pipelines.spec.model import parse_spec

    from .conftest import EXAMPLES

    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["none"], data["options"]["float"] = 1, 2
    with pytest.raises(SpecError) as err:
        parse_spec(data)
    assert "\n  none: Extra inputs" in str(err.value) and "options.float: Extra inputs" in str(err.value), err.value
