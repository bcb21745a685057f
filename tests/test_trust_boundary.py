"""Trust campaign, issue 23: generated hostile inputs against the boundary, one trust-table row per class and way in.

* numbers: inf/nan/overflowing floats and 100+ digit integers in every numeric field of every example, as JSON
  and YAML, through ``POST /jobs`` (422 naming the field or its line) and ``parse_spec`` (SpecError, same);
* costs: random values over each cap of :mod:`pipelines.spec.costs`, through ``POST /jobs`` (422 naming the knob,
  the cap and the value, computed here) and ``compabs validate`` with the server's caps (exit 2, one line);
* headers: random ``Last-Event-ID``, ``Content-Length``, ``Content-Type`` and duplicated query parameters, sent
  as exact bytes to the ASGI app (the 4xx each must give, never a 5xx);
* YAML: alias bombs of random shape and recursive aliases (refused, the bound named), benign anchors and merge
  keys in every example (accepted, the same spec stored), and the expanded-size bound exact to one value.

The store's integrity and the command line: ``tests/test_trust_boundary_cli.py``. Nothing runs: the API's queue
never starts a job and starting a job process is a guard that counts a payload executed. Cases are drawn from
``COMPABS_TRUST_SEED`` (default 23); every wrong outcome is listed, with the seed, after the row is recorded.
"""

from __future__ import annotations

import json
import math
import os
import random
import re
from collections import Counter
from collections.abc import Callable, Iterator, MutableMapping
from typing import Any

import anyio
import pytest
import yaml
from fastapi.testclient import TestClient

from pipelines.errors import SpecError
from pipelines.spec.costs import Caps
from pipelines.spec.loader import EXPONENT_FLOAT, MAX_YAML_NODES, load_yaml
from pipelines.spec.model import load_spec, parse_spec
from service.app import create_app
from service.cli import main
from service.job_store import JobStatus
from service.settings import Settings

from .conftest import EXAMPLES
from .trust_log import Tally

SEED = int(os.environ.get("COMPABS_TRUST_SEED", "23"))
TOKEN = "boundary-token"
SMALL_TEXT = (EXAMPLES / "small.yaml").read_text()
EXAMPLE_FILES = sorted(EXAMPLES.glob("*.yaml"))
#: Every example as plain JSON data (nothing shared through YAML aliases).
DATA = {p.name: json.loads(json.dumps(load_yaml(p.read_text()))) for p in EXAMPLE_FILES}
SERVER = Caps()
KNOBS = list(SERVER.values())
EXECUTED: list[str] = []
MARK = "@@NUMBER@@"
UNICODE_DIGITS = "²³¹٠١٢٣٤٥٦٧٨٩۰۱۲३४५१२３９𝟎𝟗߀߁①⑨"


def rng_for(name: str) -> random.Random:
    return random.Random(f"{SEED}-{name}")


def tally(label: str) -> Tally:
    return Tally(label, EXECUTED, SEED)


def guard(what: str) -> Callable[..., Any]:
    def refuse(*args: Any, **kwargs: Any) -> Any:
        EXECUTED.append(what)
        raise AssertionError(f"{what} ran: a hostile input was executed")

    return refuse


# ============================================================================================ the app, over ASGI
@pytest.fixture(scope="module")
def api(tmp_path_factory) -> Iterator[TestClient]:
    """The real app (SQLite store, in-process jobs); its queue never starts a job."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("service.manager.JobProcess", guard("a job process (API)"))
        settings = Settings(data_dir=tmp_path_factory.mktemp("boundary"), in_process=True, token=TOKEN,
                            max_concurrent_jobs=10**9)
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            c.app.state.manager._kick = lambda: None  # type: ignore[attr-defined]
            yield c


def call(c: TestClient, method: str, path: str, query: bytes = b"", headers: list[tuple[bytes, bytes]] | None = None,
         body: bytes = b"") -> tuple[int | None, str]:
    """One request with exactly these header bytes (as a server hands them over): the status and the body."""
    sent: list[MutableMapping[str, Any]] = []
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method, "scheme": "http",
             "path": path, "raw_path": path.encode(), "query_string": query, "root_path": "", "state": {},
             "headers": [(b"host", b"test"), (b"authorization", f"Bearer {TOKEN}".encode()), *(headers or [])],
             "client": ("127.0.0.1", 50000), "server": ("127.0.0.1", 80)}

    async def run() -> None:
        done, pending = anyio.Event(), [{"type": "http.request", "body": body, "more_body": False}]

        async def receive() -> dict[str, Any]:
            if pending:
                return pending.pop()
            with anyio.move_on_after(10):  # a stream that does not end is cut here (and its status judged)
                await done.wait()
            return {"type": "http.disconnect"}

        async def send(message: MutableMapping[str, Any]) -> None:
            sent.append(message)
            if message["type"] == "http.response.body" and not message.get("more_body"):
                done.set()

        await c.app(scope, receive, send)

    assert c.portal is not None
    try:
        c.portal.call(run)
    except Exception as exc:  # escaped the app: a real server answers 500
        return 500, repr(exc)
    status = next((m["status"] for m in sent if m["type"] == "http.response.start"), None)
    return status, b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body").decode(errors="replace")


def post(c: TestClient, body: str, content_type: str = "application/json") -> tuple[int | None, str]:
    return call(c, "POST", "/jobs", headers=[(b"content-type", content_type.encode())], body=body.encode())


def detail(text: str) -> str:
    try:
        return str(json.loads(text).get("detail", ""))
    except (ValueError, AttributeError):
        return ""


# ============================================================================================ numbers
def number_leaves(data: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else None
    if items is not None:
        for k, v in items:
            yield from number_leaves(v, (*path, k))
    elif isinstance(data, (int, float)) and not isinstance(data, bool):
        yield path


LEAVES = [(name, path) for name, data in DATA.items() for path in number_leaves(data)]


def with_value(name: str, path: tuple[Any, ...], value: Any) -> Any:
    data = json.loads(json.dumps(DATA[name]))
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return data


def dotted(path: tuple[Any, ...]) -> str:
    return ".".join(str(p) for p in path)


def big_int(rng: random.Random) -> str:
    return rng.choice(["", "-"]) + str(rng.randint(1, 9)) + "".join(rng.choices("0123456789", k=rng.randint(100, 6000)))


def json_literal(rng: random.Random) -> str:
    """A JSON number that is no finite float, or an integer of more than 100 digits."""
    return rng.choice([
        lambda: rng.choice(["1e999", "-1e999", "1.8e308", "-1.8e308", "1e309", "2E+308", "-0.5e400"]),
        lambda: f"{rng.choice(['', '-'])}{rng.randint(1, 9)}.{rng.randint(0, 999)}e{rng.randint(309, 10**6)}",
        lambda: big_int(rng), lambda: big_int(rng)])()


def yaml_literal(rng: random.Random) -> str:
    return rng.choice([
        lambda: rng.choice([".inf", "-.inf", "+.inf", ".Inf", "-.INF", ".nan", ".NaN", ".NAN", "1e999", "-1e999"]),
        lambda: f"{rng.choice(['', '-', '+'])}{rng.randint(1, 9)}.{rng.randint(0, 99)}e+{rng.randint(309, 10**5)}",
        lambda: rng.choice(["", "-"]) + "0x" + "".join(rng.choices("0123456789abcdef", k=rng.randint(84, 2000))),
        lambda: str(rng.randint(1, 9)) + "_0" * rng.randint(101, 400), lambda: big_int(rng)])()


def names_it(message: str, path: tuple[Any, ...], line: int | None) -> bool:
    return dotted(path) in message or (line is not None and re.search(rf"\bline {line}\b", message) is not None)


def texts(rng: random.Random, name: str, path: tuple[Any, ...], indent: int | None = None) -> Iterator[tuple[str, str, int]]:
    """(format, spec text with a hostile literal at ``path``, its line): JSON then YAML."""
    for fmt, text, quoted, literal in (
            ("json", json.dumps(with_value(name, path, MARK), indent=indent), f'"{MARK}"', json_literal(rng)),
            ("yaml", yaml.safe_dump(with_value(name, path, MARK), sort_keys=False), f"'{MARK}'", yaml_literal(rng))):
        yield fmt, text.replace(quoted, literal), text[:text.index(quoted)].count("\n") + 1


def test_numbers_through_post_jobs(api):
    rng = rng_for("numbers-api")
    rows = {fmt: tally(f"numbers: inf/nan/overflow/100+ digits, every field of every example (POST /jobs, {fmt})")
            for fmt in ("json", "yaml")}
    for name, path in LEAVES:
        for _ in range(2):
            for fmt, text, line in texts(rng, name, path):
                status, body = post(api, text, "application/json" if fmt == "json" else "application/yaml")
                ok = status == 422 and names_it(detail(body), path, None if fmt == "json" else line)
                rows[fmt].check(ok, f"{fmt} {name} {dotted(path)}: {status} {body[:300]}", status)
    for row in rows.values():
        row.done(api=True)


def test_numbers_through_parse_spec():
    """The CLI's reader: dicts with inf/nan, YAML text and indented JSON text (which it reads as YAML)."""
    rng, row = rng_for("numbers-parser"), tally("numbers: inf/nan/overflow/100+ digits, every field of every example "
                                                "(parse_spec)")
    for name, path in LEAVES:
        cases: list[tuple[Any, int | None]] = [(with_value(name, path, v), None)
                                               for v in rng.sample([math.inf, -math.inf, math.nan], 2)]
        cases += [(text, line) for _, text, line in texts(rng, name, path, indent=1)]
        for spec, line in cases:
            try:
                parse_spec(spec)
                outcome, ok = "accepted", False
            except SpecError as exc:
                outcome, ok = str(exc), names_it(str(exc), path, line)
            except Exception as exc:  # a crash of the reader
                outcome, ok = f"{type(exc).__name__}: {exc}", False
            row.check(ok, f"{name} {dotted(path)} ({type(spec).__name__}, line {line}): {outcome[:300]}")
    row.done()


def test_json_nan_constant_names_the_field(api):
    status, body = post(api, json.dumps(with_value("small.yaml", ("options", "seed"), MARK)).replace(f'"{MARK}"', "NaN"))
    assert status == 422 and "options.seed" in detail(body), body


# ============================================================================================ costs
def small(**options: Any) -> dict[str, Any]:
    data = json.loads(json.dumps(DATA["small.yaml"]))
    data["options"].update(options)
    return data


def with_n(data: dict[str, Any], n: int) -> dict[str, Any]:
    data["parameters"]["N"] = n
    data["options"]["initial_states"] = data["options"]["initial_states"] if n == 2 else []
    return data


def audit_evaluations(count: int, subsystems: int) -> int:
    """As documented: ``count`` for the one distinct subsystem and for the interconnection, plus max(min(count,
    10^4), count // 10) composed transitions, each evaluating every subsystem and the map."""
    return 2 * count + max(min(count, 10_000), count // 10) * (subsystems + 1)


def over_cap(rng: random.Random, knob: str) -> tuple[dict[str, Any], str, int | None]:
    """small.yaml (33 state cells x 5 inputs x 33 internal cells, 100 samples) with ``knob`` over the server's cap
    and the knobs checked before it within theirs: the spec, the knob's field path, its value (None: not exact)."""
    d, s = small(), SERVER
    agent = d["subsystems"][0]

    def n_at_least(least: int) -> int:  # subsystems: mostly up to 64 (quick to build), up to the server's 256
        return rng.randint(least, 256 if rng.random() < 0.1 else max(least, 64))
    if knob == "max_subsystems":
        n = rng.randint(s.max_subsystems + 1, 10 ** rng.randint(3, 90))
        if rng.random() < 0.5:  # through the parameter (a float: shown rounded)
            return with_n(d, n), "subsystems[0].replicate", None
        agent["replicate"] = n
        return d, "subsystems[0].replicate", n if n < 2**53 else None
    if knob == "max_expression_length":
        where, node, key = rng.choice([("subsystems[0].dynamics", agent, "dynamics"),
                                       ("interconnection.map", d["interconnection"], "map")])
        node[key] += " + 0 * x[0]" * rng.randint(200, 6000)
        return d, where, len(node[key])
    if knob == "max_cells":  # m + 1 points: [0, m] (input [-2, m - 2]), eta 1 (exact while m << 1 / SNAP_RTOL)
        m, grid = rng.randint(10**7 // 165, 10 ** rng.randint(6, 8)), rng.choice(["state", "input", "internal"])
        (d["interconnection"]["internal"] if grid == "internal" else agent[grid])["ub"] = m - 2 * (grid == "input")
        return d, "subsystems[0].state × subsystems[0].input", (m + 1) * (33 if grid == "input" else 5) * 33
    if knob == "max_evaluations":
        m = rng.randint(6_061, 60_605)  # (m + 1) x 165 triples, in (10^6, 10^7]
        agent["state"]["ub"], agent["samples"] = m, rng.randint(s.max_evaluations // ((m + 1) * 165) + 1, 10**5)
        return d, "subsystems[*].samples", (m + 1) * 165 * agent["samples"]
    if knob == "max_tasks":
        m = rng.randint(10_002, 60_605)
        agent["state"]["ub"], chunk = m, rng.randint(1, m // s.max_tasks)
        d["options"]["chunk_cells"] = chunk
        return d, "options.chunk_cells", -(-(m + 1) // chunk)
    if knob == "max_lipschitz_pairs":
        batches = rng.randint(3, 10 ** rng.randint(1, 40))
        pairs = rng.randint(max(2, s.max_lipschitz_pairs // (5 * batches) + 1), 10 ** rng.randint(7, 45))
        agent["lipschitz"].update({rng.choice(["x", "w"]): "estimate", "batches": batches, "pairs": pairs})
        return d, "subsystems[0].lipschitz.batches × subsystems[0].lipschitz.pairs", batches * pairs * 5
    if knob == "max_sample_values":
        n, which = n_at_least(21), rng.choice(["samples", "holdout"])
        k = with_n(d, n)["interconnection"][which] = rng.randint(s.max_sample_values // n + 1, 10**6)
        return d, f"interconnection.{which} × state dimension", k * n
    if knob == "max_interconnection_values":  # n x (samples x 2 + holdout x (n + 6)), 20 samples, 1 internal
        n = n_at_least(50)
        h = rng.randint((s.max_interconnection_values // n - 40) // (n + 6) + 1, s.max_sample_values // n)
        with_n(d, n)["interconnection"]["holdout"] = h
        return d, "interconnection.samples, interconnection.holdout", n * (40 + h * (n + 6))
    if knob == "max_audit_evaluations":
        n, lo, hi = n_at_least(2), 1, 10**8
        while lo < hi:  # the least count over the cap
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if audit_evaluations(mid, n) > s.max_audit_evaluations else (mid + 1, hi)
        count = with_n(d, n)["options"]["audit_transitions"] = rng.randint(lo, 10**8)
        return d, "options.audit_transitions", audit_evaluations(count, n)
    assert knob == "max_closed_loop_steps"  # (runs + initial states) x steps x subsystems
    steps = rng.choice([None, rng.randint(51, 100_000)])
    n = rng.randint(4, 64) if steps is None else rng.choice([2, rng.randint(2, 64)])
    per_run, initial = (steps or 30) * n, int(n == 2)
    runs = rng.randint(max(0, s.max_closed_loop_steps // per_run + 1 - initial), 100_000)
    with_n(d, n)["options"].update(closed_loop_runs=runs, closed_loop_steps=steps)
    return d, "options.closed_loop_runs × options.closed_loop_steps", (runs + initial) * per_run


def cost_named(message: str, knob: str, field: str, value: int | None) -> bool:
    value_named = value is None or str(value) in message
    if knob == "max_cells" and "exceed options.max_cells" in message:  # compabs validate: the spec's own cap first
        return value_named
    return field in message and f"cap {knob} is {getattr(SERVER, knob)}" in message and value_named


def test_costs_through_post_jobs(api):
    rng, row = rng_for("costs-api"), tally("costs: random over-cap values of each knob (POST /jobs)")
    for _ in range(24):  # each a full estimate of a job's costs (seconds for some): CI's 30 minutes bound the count
        for knob in KNOBS:
            data, field, value = over_cap(rng, knob)
            status, body = post(api, json.dumps(data))
            row.check(status == 422 and cost_named(detail(body), knob, field, value),
                      f"{knob} {field} = {value}: {status} {body[:400]}", status)
    row.done(api=True)


def one_error(code: int, out: str, err: str) -> bool:
    lines = [line for line in err.splitlines() if line.strip()]
    return code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in out + err


def test_costs_through_compabs_validate(tmp_path, capsys, monkeypatch):
    """The command line's caps set to the server's through ``COMPABS_MAX_*``, as an operator may. The target is
    one box: ``compabs validate`` counts the target's abstract states before the caps, which for the consensus
    target of 256 subsystems takes seconds (reported; the count is not what is tried here)."""
    for knob in KNOBS:
        monkeypatch.setenv(f"COMPABS_{knob.upper()}", str(getattr(SERVER, knob)))
    rng, row = rng_for("costs-cli"), tally("costs: random over-cap values of each knob (compabs validate)")
    for i in range(20):
        for knob in KNOBS:
            data, field, value = over_cap(rng, knob)
            data["specification"]["target"] = {"boxes": [{"lb": 0, "ub": 32}]}
            (tmp_path / f"{i}{knob}.json").write_text(json.dumps(data))
            code = main(["validate", str(tmp_path / f"{i}{knob}.json")])
            out, err = capsys.readouterr()
            row.check(one_error(code, out, err) and cost_named(err, knob, field, value),
                      f"{knob} {field} = {value}: exit {code}: {err[:400]}")
    row.done(ok_as="failed_cleanly")


# ============================================================================================ headers
def event_id(rng: random.Random) -> bytes:
    digits = "".join(rng.choices("0123456789", k=rng.randint(1, 18)))
    i = rng.randint(0, len(digits))
    return rng.choice([
        lambda: (digits[:i] + rng.choice(UNICODE_DIGITS) + digits[i:]).encode(rng.choice(["utf-8", "utf-16-le"])),
        lambda: rng.choice([str(2**63 + rng.randint(-9, 9)), str(10**18 + rng.randint(0, 99)), "9" * rng.randint(19, 6000),
                            str(rng.randint(1, 9)) + "0" * rng.randint(18, 400)]).encode(),
        lambda: (rng.choice("+-") + digits).encode(),
        lambda: rng.choice([" " + digits, "\t" + digits, digits + " ", digits[:i] + " " + digits[i:]]).encode(),
        lambda: rng.choice([b"", b"0x1f", b"1.0", b"1e3", b"1_000", b"-0", b"NaN", b"\xff\xfe", b"1,2", b"one"]),
        lambda: digits.encode(), lambda: digits.encode()])()


def test_last_event_id(api):
    rng, row = rng_for("last-event-id"), tally("headers: Last-Event-ID (unicode digits, huge, signs, spaces)")
    live, ended = (json.loads(post(api, SMALL_TEXT, "application/yaml")[1])["id"] for _ in range(2))
    assert call(api, "DELETE", f"/jobs/{ended}")[0] == 200
    for _ in range(1500):
        value = event_id(rng)
        valid = re.fullmatch(rb"[0-9]{1,18}", value) is not None  # a live job's stream would not end: never sent
        job = rng.choice([ended, "0123456789abcdef"] + ([] if valid else [live]))
        status, body = call(api, "GET", f"/jobs/{job}/events", headers=[(b"last-event-id", value)])
        if job not in (live, ended):
            ok = status in (404, 422)
        else:  # valid on an ended job: its events after the id (200) or nothing more to send (204)
            ok = status in (200, 204) if valid else status == 422 and "last-event-id" in detail(body).lower()
        row.check(ok, f"Last-Event-ID {value[:60]!r} on {'live' if job == live else job}: {status} {body[:200]}",
                  status)
    row.done(api=True)


def content_length(rng: random.Random, size: int) -> tuple[bytes, str]:
    """A Content-Length and what it must give: 'bad' (400), 'large' (413, or 400) or 'read' (the body is read)."""
    digits = list(str(size))
    digits[rng.randrange(len(digits))] = rng.choice(UNICODE_DIGITS)
    value, want = rng.choice([
        (str(size), "read"), ("0" * rng.randint(1, 18) + str(rng.randint(0, size)), "read"),
        (str(rng.randint(2**20 + 1, 10 ** rng.randint(7, 60))), "large"), ("".join(digits), "bad"),
        (rng.choice([f"+{size}", f" {size}", f"{size} ", f"-{size}", f"1_{size}", hex(size), f"{size}.0", "",
                     f"{size}, {size}", "0x0", f"{size}e0"]), "bad"), ("9" * rng.randint(65, 6000), "bad")])
    return value.encode(), want


def test_zero_padded_content_length_is_read(api):
    status, text = call(api, "POST", "/jobs", headers=[(b"content-type", b"application/json"),
                                                      (b"content-length", b"0" * 25 + b"14")], body=b'{"name": "cl"}')
    assert status == 422, text


def test_content_length(api):
    rng, row = rng_for("content-length"), tally("headers: Content-Length oddities")
    body = json.dumps({"name": "cl"}).encode()  # parses, then 422 naming the missing fields: nothing stored
    for _ in range(1000):
        value, want = content_length(rng, len(body))
        headers = [(b"content-type", b"application/json"), (b"content-length", value)]
        if rng.random() < 0.2:  # and a second, different one
            headers.append((b"content-length", str(rng.randint(0, 10**6)).encode()))
        status, text = call(api, "POST", "/jobs", headers=headers, body=body)
        ok = {"bad": status == 400 and "Content-Length" in detail(text), "large": status in (400, 413),
              "read": status is not None and 400 <= status < 500 and status not in (413, 415)}[want]
        row.check(ok, f"Content-Length {value[:60]!r} ({want}): {status} {text[:200]}", status)
    row.done(api=True)


SUPPORTED = ["application/json", "application/yaml", "application/x-yaml", "text/yaml", "text/x-yaml", "text/plain",
             "application/vnd.compabs+json", "APPLICATION/JSON", "Application/Yaml"]
UNSUPPORTED = ["text/html", "application/xml", "multipart/form-data; boundary=x", "application/x-www-form-urlencoded",
               "image/png", "application/octet-stream", "*/*", "application/*", "json", "yaml", "text", "application/"]


def content_type(rng: random.Random) -> tuple[bytes, str]:
    """A Content-Type and what it must give: 'read' (the body is parsed), '415', or 'any' (415 or 422)."""
    media, sep = rng.choice(SUPPORTED), rng.choice([";", "; ", " ; "])
    junk = bytes(rng.randrange(32, 256) for _ in range(rng.randint(0, 300)))
    utf8 = rng.choice(["utf-8", "UTF-8", "utf8", '"utf-8"', "us-ascii"])
    other = rng.choice(["latin-1", "iso-8859-1", "utf-16", "UTF-16LE", "cp1252", "utf-32", "utf-9"])
    cases: list[tuple[str | bytes, str]] = [
        (media, "read"), (f"{media}{sep}charset={utf8}", "read"), (f"{media}{sep}charset={other}", "415"),
        (rng.choice(UNSUPPORTED), "415"),
        (rng.choice([junk, media.encode() + b";" + junk, b";" * rng.randint(1, 50), b"a" * 10_000]), "any")]
    value, want = rng.choice(cases)
    return (value if isinstance(value, bytes) else value.encode()), want


def test_content_type(api):
    rng, row = rng_for("content-type"), tally("headers: Content-Type oddities")
    for _ in range(700):
        value, want = content_type(rng)
        body = json.dumps({"name": "ct"}).encode()
        if want == "read" and rng.random() < 0.15:  # UTF-8 claimed or implied, UTF-16 sent
            body, want = body.decode().encode("utf-16"), "undecodable"
        status, text = call(api, "POST", "/jobs", headers=[(b"content-type", value)], body=body)
        said = detail(text)
        ok = {"read": status == 422 and "subsystems" in said, "undecodable": status == 422 and "UTF-8" in said,
              "415": status == 415, "any": status in (415, 422)}[want]
        row.check(ok, f"Content-Type {value[:80]!r} ({want}): {status} {text[:200]}", status)
    row.done(api=True)


ROUTES = [("GET", "/jobs"), ("POST", "/jobs"), ("GET", "/jobs/{id}"), ("DELETE", "/jobs/{id}"),
          ("GET", "/jobs/{id}/events"), ("GET", "/jobs/{id}/report"), ("GET", "/jobs/{id}/figures/x.png"),
          ("GET", "/jobs/{id}/controller"), ("GET", "/schema"), ("GET", "/health"), ("GET", "/openapi.json"),
          ("GET", "/docs"), ("GET", "/redoc"), ("GET", "/")]


def test_duplicated_query_parameters(api):
    rng, row = rng_for("query"), tally("headers: duplicated query parameters")
    live = json.loads(post(api, SMALL_TEXT, "application/yaml")[1])["id"]  # a duplicate must neither cancel nor stream it
    for _ in range(1500):
        method, route = rng.choice(ROUTES)
        name = rng.choice(["limit", "name", "token", "x", "", "Last-Event-ID", "limit[]", "é"])
        params = [f"{name}={rng.choice(['1', '0', '-1', 'abc', '', TOKEN, '9' * 40, '%FF'])}"
                  for _ in range(rng.randint(2, 5))] + rng.sample(["a=1", "b=2", "c"], rng.randint(0, 2))
        rng.shuffle(params)
        status, text = call(api, method, route.format(id=live), query="&".join(params).encode(),
                            headers=[(b"content-type", b"application/yaml")], body=SMALL_TEXT.encode())
        row.check(status == 422 and "given" in detail(text), f"{method} {route}?{'&'.join(params)[:120]}: {status} "
                  f"{text[:200]}", status)
    assert api.app.state.manager.store.get(live).status == JobStatus.QUEUED
    row.done(api=True)


# ============================================================================================ YAML anchors
def bomb(rng: random.Random, least: int) -> tuple[str, int]:
    """Levels of aliases (lists, mappings, merge keys) expanding to more than ``least`` values; the size counted
    here: a list is 1 + its items, a mapping 1 + its keys and values, an alias what it names."""
    width = rng.randint(2, 40)
    lines, sizes = [f"b0: &b0 [{', '.join(['lol'] * width)}]"], [1 + width]
    while 1 + len(sizes) + sum(sizes) <= least:
        i, kind, last = len(sizes), rng.choice(["seq", "map", "merge"]), sizes[-1]
        if kind == "seq":
            lines.append(f"b{i}: &b{i} [" + ", ".join([f"*b{i - 1}"] * width) + "]")
            sizes.append(1 + width * last)
        else:
            merge = [f"<<: {{m: *b{i - 1}}}"] if kind == "merge" else []
            lines.append(f"b{i}: &b{i} {{" + ", ".join([f"k{j}: *b{i - 1}" for j in range(width)] + merge) + "}")
            sizes.append(1 + width * (1 + last) + (3 + last if merge else 0))
    return "\n".join(lines) + "\n", 1 + len(sizes) + sum(sizes)


def recursive(rng: random.Random) -> str:
    inner = "*x"
    for _ in range(rng.randint(0, 6)):
        inner = rng.choice(["[%s]", "{k: %s}", "[1, %s, 2]"]) % inner
    return f"top: &x {rng.choice(['[%s]', '{a: %s}'])}\n" % inner


def test_yaml_bombs_and_recursive_aliases(api, tmp_path):
    rng = rng_for("yaml-bombs")
    rows = [tally(f"YAML: alias bombs of random shape, recursive aliases ({way})")
            for way in ("POST /jobs", "spec file reader")]
    for i in range(300):
        if rng.random() < 0.2:
            text, want = recursive(rng), "recursive alias"
        else:
            text, want = bomb(rng, MAX_YAML_NODES * rng.choice([1, 1, 10, 10**6, 10**30]))[0], "MAX_YAML_NODES"
            text += SMALL_TEXT if rng.random() < 0.5 else ""  # before a spec's fields
        status, body = post(api, text, rng.choice(["application/yaml", "text/yaml", "text/plain"]))
        rows[0].check(status == 422 and want in detail(body), f"{text[:200]!r}: {status} {body[:200]}", status)
        (tmp_path / f"{i}.yaml").write_text(text)
        try:
            load_spec(tmp_path / f"{i}.yaml")
            outcome = "accepted"
        except Exception as exc:
            outcome = f"{type(exc).__name__}: {exc}"
        rows[1].check(outcome.startswith("SpecError") and want in outcome, f"{text[:200]!r}: {outcome[:200]}")
    rows[0].done(api=True)
    rows[1].done()


def anchored(rng: random.Random, data: Any, merges: bool = True) -> str:
    """``data`` as flow YAML with anchors on random repeated values (the later ones aliases) and merge keys."""
    def values(v: Any) -> Iterator[str]:
        yield json.dumps(v, sort_keys=True)
        for x in v.values() if isinstance(v, dict) else v if isinstance(v, list) else ():
            yield from values(x)

    chosen = {k for k, n in Counter(values(data)).items() if n > 1 and rng.random() < 0.6}
    anchors: dict[str, str] = {}

    def emit(v: Any) -> str:
        key, prefix = json.dumps(v, sort_keys=True), ""
        if key in anchors:
            return f"*{anchors[key]}"
        if key in chosen:
            anchors[key] = f"a{len(anchors)}"
            prefix = f"&{anchors[key]} "
        if isinstance(v, list):
            return prefix + "[" + ", ".join(emit(x) for x in v) + "]"
        if not isinstance(v, dict):
            return prefix + json.dumps(v)
        pairs = [f"{json.dumps(k)}: {emit(x)}" for k, x in v.items()]
        if merges and len(pairs) > 1 and rng.random() < 0.3:  # the first keys merged in: the same mapping
            cut = rng.randint(1, len(pairs) - 1)
            pairs = ["<<: {" + ", ".join(pairs[:cut]) + "}"] + pairs[cut:]
        return prefix + "{" + ", ".join(pairs) + "}"

    return emit(data) + "\n"


def test_benign_anchors_are_accepted(api):
    """Every example with random anchors, aliases and merge keys: accepted, the same spec stored as without them."""
    rng, row = rng_for("yaml-benign"), tally("YAML: benign anchors, aliases, merge keys (POST /jobs, accepted)")
    store = api.app.state.manager.store
    for i in range(60):
        name = EXAMPLE_FILES[i % len(EXAMPLE_FILES)].name
        text = anchored(rng, DATA[name])
        for _ in range(20):  # an example with few repeated values may draw no anchor: draw again
            if "&a0" in text:
                break
            text = anchored(rng, DATA[name])
        status, body = post(api, text, "application/yaml")
        ok = status == 201 and "&a0" in text
        if status == 201:
            job = json.loads(body)["id"]
            ok = ok and json.loads(store.get(job).spec) == json.loads(parse_spec(DATA[name]).model_dump_json())
            call(api, "DELETE", f"/jobs/{job}")
        row.check(ok, f"{name} as {text[:300]!r}: {status} {body[:200]}", status)
    row.done(api=True)


def expanded(v: Any) -> int:
    items = list(v.values()) if isinstance(v, dict) else v if isinstance(v, list) else None
    return 1 if items is None else 1 + sum(expanded(x) for x in items) + (len(items) if isinstance(v, dict) else 0)


class _PyYAMLWithExponents(yaml.SafeLoader):
    """PyYAML's safe loader reading ``1e-06`` as a number, as the spec loader does (YAML 1.2, JSON)."""


_PyYAMLWithExponents.add_implicit_resolver("tag:yaml.org,2002:float", EXPONENT_FLOAT, list("-+.0123456789"))


def test_expanded_size_bound_is_exact():
    """Random anchored documents: read as PyYAML reads them (numbers with exponents as numbers) within their size,
    refused one value below it."""
    rng, row = rng_for("yaml-exact"), tally("YAML: random anchored documents, expanded-size bound exact (loader)")
    for _ in range(600):
        text, size = bomb(rng, rng.randint(10, 2000))
        if rng.random() < 0.5:
            text = anchored(rng, rng.choice(list(DATA.values())), merges=False)
            size = expanded(yaml.safe_load(text))
        ok = False
        try:
            ok = load_yaml(text, max_nodes=size) == yaml.load(text, Loader=_PyYAMLWithExponents)
            load_yaml(text, max_nodes=size - 1)
            outcome, ok = "read past the bound", False
        except SpecError as exc:
            outcome, ok = str(exc), ok and "MAX_YAML_NODES" in str(exc)
        except Exception as exc:
            outcome, ok = f"{type(exc).__name__}: {exc}", False
        row.check(ok, f"size {size} {text[:200]!r}: {outcome[:200]}")
    row.done()
