"""Trust campaign, issue 47: tampered controllers are refused by every entry point, and never crash a process.

Real jobs, small enough to make in seconds: the consensus example (a BDD controller ``controller.json`` +
``controller.dddmp`` and the layered ``controller_reach_safe``) and dcdc.yaml at spacing 0.05 (an array controller,
``controller.npz``), and a JSON export of the first. Each case draws one tampering from ``COMPABS_TRUST_SEED``
(default 23) and the case's number:

* bytes of a header, payload or export flipped, inserted, deleted, replaced by garbage, or the file truncated,
  emptied or removed (a JSON file whose parsed content is unchanged is not tampered, and is drawn again);
* a payload file swapped for another controller's, a controller of another spec (its files consistent among
  themselves, as copied from another spec's job), a value of a header edited, its integrity record stripped;
* a header whose text carries C code (a tampering like any other edit: refused);
* a DDDMP node line made invalid (a child not yet read, a variable outside the support, a name that is not the
  variable's, a child 0) with the checksums recomputed, as a forger would: the structure check must refuse it
  before CUDD reads it.

Each tampered controller is tried against ``load_controller`` and one command of ``compabs export``, ``control``,
``audit`` or ``import`` (``service.cli.main``), in a child process that runs the cases one after another and says
which it starts: a child that dies of a signal is counted as a process crashed, and the cases after it run in a
new child. Every attempt must be refused: a :class:`~pipelines.errors.CompabsError` naming the file, or exit
status 2 with one ``error:`` line. A few cases run through the real ``python -m service.cli`` (exit 2, never a
signal), and through the API's download (``GET /jobs/{id}/controller``: 409 or another 4xx with a JSON body,
never 200 or 5xx) of a job whose files are those of the BDD job, stored as succeeded in the real job store. The
download verifies checksums, the spec hash and each BDD file's structure (a resealed DDDMP file with an invalid
node line is refused there too), and hands nothing to CUDD.

Forged headers whose text carries C and whose checksums are recomputed load (checksums are not signatures:
pipelines/controller_integrity.py); their C export must hold none of that text. They have a row of their own.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import shutil
import subprocess
import sys
import uuid
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from pipelines.controller_integrity import INTEGRITY, canonical_sha256, seal

from .conftest import EXAMPLES
from .trust_log import record

ROOT = Path(__file__).resolve().parents[1]
SEED = int(os.environ.get("COMPABS_TRUST_SEED", "23"))
#: Cases of the fast share and of the slow share (each case: one tampering, two or three attempts).
FAST_CASES, SLOW_CASES = 80, 1000
#: API downloads of tampered controllers, fast and slow share.
FAST_API, SLOW_API = 40, 600
#: Real ``python -m service.cli`` runs, fast and slow share (a second or two each).
FAST_CLI, SLOW_CLI = 4, 8
#: C code a header's text carries.
PAYLOAD = '*/ system("x"); /*\n#include <stdlib.h>\nint evil(void) { return system("x"); }'
#: Names of the states the commands are asked for, per job.
STATE = {"bdd": "3,4", "array": "1.4,5.6"}


# ============================================================================================ the jobs
def make_jobs(base: Path) -> dict[str, Path]:
    """The BDD job, the array job and a JSON export of the BDD job's controller, under ``base``."""
    from pipelines.spec.model import parse_spec
    from service.cli import main
    from workers.executors import Execution
    from workers.job import run_job

    small = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    small["interconnection"]["alpha"] = 0.01  # a fixed penalty: no cross-validation, seconds less
    small["options"].update({"audit_transitions": 0, "closed_loop_runs": 0, "initial_states": []})
    dcdc = yaml.safe_load((EXAMPLES / "dcdc.yaml").read_text())
    dcdc["subsystems"][0]["state"]["eta"] = 0.05
    dcdc["options"].update({"audit_transitions": 0, "closed_loop_runs": 0, "initial_states": []})
    jobs = {"bdd": base / "bdd", "array": base / "array"}
    for data, out in ((small, jobs["bdd"]), (dcdc, jobs["array"])):
        run_job(parse_spec(data), out, Execution(in_process=True), audit=False)
    assert (jobs["array"] / "controller.npz").is_file() and (jobs["bdd"] / "controller_reach_safe.json").is_file()
    jobs["export"] = base / "export.json"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(["export", str(jobs["bdd"]), "--format", "json", "--out", str(jobs["export"])]) == 0
    return jobs


# ============================================================================================ tamperings
@dataclass
class Case:
    """One tampering: what it did (``what``), the job or file it applies to (``target``: bdd, layered, array,
    export), the controller's name, whether it is a resealed C payload (``forged_c``), and the files it changed
    with their original bytes (``None``: the file did not exist), to restore them."""

    number: int
    target: str
    what: str = ""
    name: str = "controller"
    forged_c: bool = False
    saved: dict[Path, bytes | None] = field(default_factory=dict)

    def save(self, path: Path) -> None:
        if path not in self.saved:
            self.saved[path] = path.read_bytes() if path.exists() else None

    def write(self, path: Path, data: bytes) -> None:
        self.save(path)
        path.write_bytes(data)

    def restore(self) -> None:
        for path, data in self.saved.items():
            if data is None:
                path.unlink(missing_ok=True)
            else:
                path.write_bytes(data)


def canonical(data: bytes) -> str | None:
    """The canonical text's hash of a JSON file's bytes (``None``: not JSON)."""
    try:
        return canonical_sha256(json.loads(data))
    except (ValueError, RecursionError):
        return None


def byte_damage(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    """One random damage to a file's bytes, and its description."""
    kind = rng.choice(["flip", "flip", "insert", "delete", "truncate", "garbage", "empty"])
    n = len(data)
    if kind == "flip" and n:
        out = bytearray(data)
        spots = rng.sample(range(n), min(n, rng.randint(1, 3)))
        for k in spots:
            out[k] ^= rng.randint(1, 255)
        return bytes(out), f"bytes {spots} flipped"
    if kind == "insert":
        at = rng.randint(0, n)
        return data[:at] + rng.randbytes(rng.randint(1, 16)) + data[at:], f"bytes inserted at {at}"
    if kind == "delete" and n:
        at = rng.randrange(n)
        return data[:at] + data[at + rng.randint(1, 64):], f"bytes deleted at {at}"
    if kind == "truncate" and n:
        at = rng.randrange(n)
        return data[:at], f"truncated to {at} bytes"
    if kind == "garbage":
        return rng.randbytes(rng.randint(1, 2000)), "garbage"
    return b"", "emptied"


def node_line_forged(rng: random.Random, text: str) -> tuple[str, str]:
    """A DDDMP text with one node line made invalid, and what was done."""
    lines = text.split("\n")
    start, end = lines.index(".nodes") + 1, lines.index(".end")
    k = rng.randrange(start + 1, end)
    ident, name, var, then, other = lines[k].split()
    how = rng.choice(["child not yet read", "variable outside the support", "another name", "child 0"])
    lines[k] = {"child not yet read": f"{ident} {name} {var} {int(ident) + rng.randint(0, 50)} {other}",
                "variable outside the support": f"{ident} {name} {rng.randint(90, 10**6)} {then} {other}",
                "another name": f"{ident} w0_0 {var} {then} {other}",
                "child 0": f"{ident} {name} {var} {then} 0"}[how]
    return "\n".join(lines), f"node line {k - start + 1}: {how}"


def reseal(case: Case, head_path: Path) -> None:
    """Recompute a header's integrity record over the files as they are now (a forger's move)."""
    head = json.loads(head_path.read_text())
    head.pop(INTEGRITY)
    case.write(head_path, json.dumps(seal(head, head_path.parent, head["roots"]), indent=1).encode())


def another_spec(spec: dict[str, Any], rng: random.Random) -> dict[str, Any]:
    """The spec with another seed: another spec hash, the same variables and grids."""
    other = json.loads(json.dumps(spec))
    other.setdefault("options", {})["seed"] = rng.randint(1000, 10**6)
    return other


def scalar_paths(value: Any, path: tuple = ()) -> list[tuple]:
    """The paths of every number and string in a JSON value (the integrity record left out)."""
    if isinstance(value, dict):
        return [p for k, v in value.items() if k != INTEGRITY for p in scalar_paths(v, (*path, k))]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in scalar_paths(v, (*path, i))]
    return [path] if isinstance(value, int | float | str) and not isinstance(value, bool) else []


def edited(value: Any, rng: random.Random, payload: bool) -> tuple[Any, str]:
    """A JSON value with one number or string changed (to C code when ``payload``), and where."""
    out = json.loads(json.dumps(value))
    paths = [p for p in scalar_paths(out) if not payload or isinstance(_at(out, p), str)] or scalar_paths(out)
    path = rng.choice(paths)
    parent = _at(out, path[:-1])
    old = parent[path[-1]]
    if payload:
        parent[path[-1]] = PAYLOAD
    elif isinstance(old, str):
        parent[path[-1]] = old + rng.choice(["x", "\n#include <stdlib.h>", " "])
    else:
        parent[path[-1]] = old + rng.choice([1, -1, 0.5, 1e9])
    return out, "/".join(map(str, path))


def _at(value: Any, path: tuple) -> Any:
    for k in path:
        value = value[k]
    return value


def draw(number: int, jobs: dict[str, Path], targets: tuple[str, ...] = ("bdd", "layered", "array", "export"),
         forged_c: bool = True, forged_nodes: bool = True) -> Case:
    """Apply the tampering of case ``number`` to ``jobs`` (private copies): the case, to restore later
    (``forged_c``, ``forged_nodes``: whether resealed headers carrying C, and resealed invalid node lines, may be
    drawn)."""
    rng = random.Random(f"{SEED}-controllers-{number}")
    target = rng.choice(targets)
    case = Case(number, target, name="controller_reach_safe" if target == "layered" else "controller")
    if target == "export":
        path = jobs["export"]
        data = path.read_bytes()
        kind = rng.choice(["bytes", "bytes", "edit", "edit", "payload", "strip"])
        if kind == "bytes":
            new, case.what = byte_damage(rng, data)
            while canonical(new) == canonical(data) and canonical(data) is not None:
                new, case.what = byte_damage(rng, data)
            case.write(path, new)
        elif kind == "strip":
            body = json.loads(data)
            body.pop(INTEGRITY)
            case.write(path, json.dumps(body).encode())
            case.what = "integrity record stripped"
        else:
            body, where = edited(json.loads(data), rng, payload=kind == "payload")
            case.write(path, json.dumps(body).encode())
            case.what = f"{'C in' if kind == 'payload' else 'edited'} {where}"
        case.what = f"export.json: {case.what}"
        return case
    job = jobs["array" if target == "array" else "bdd"]
    head_path = job / f"{case.name}.json"
    head = json.loads(head_path.read_text())
    files = [head_path, *(job / r for r in head["roots"])]
    kinds = ["bytes", "bytes", "bytes", "missing", "edit", "payload", "strip", "other spec", "swap"]
    if target != "array" and forged_nodes:
        kinds += ["forged node line", "forged node line"]
    if forged_c and target == "bdd" and rng.random() < 0.05:
        kinds = ["forged C"]
    kind = rng.choice(kinds)
    if kind == "bytes":
        path = rng.choice(files)
        data = path.read_bytes()
        new, what = byte_damage(rng, data)
        while path.suffix == ".json" and canonical(new) == canonical(data) and canonical(data) is not None:
            new, what = byte_damage(rng, data)
        case.write(path, new)
        case.what = f"{path.name}: {what}"
    elif kind == "missing":
        path = rng.choice(files)
        case.save(path)
        path.unlink()
        case.what = f"{path.name} removed"
    elif kind in ("edit", "payload"):
        body, where = edited(head, rng, payload=kind == "payload")
        case.write(head_path, json.dumps(body, indent=1).encode())
        case.what = f"{head_path.name}: {'C in' if kind == 'payload' else 'edited'} {where}"
    elif kind == "strip":
        head.pop(INTEGRITY)
        case.write(head_path, json.dumps(head, indent=1).encode())
        case.what = f"{head_path.name}: integrity record stripped"
    elif kind == "other spec":  # consistent in itself, of another spec: as copied from another spec's job
        head["meta"]["spec"] = another_spec(head["meta"]["spec"], rng)
        head.pop(INTEGRITY)
        case.write(head_path, json.dumps(seal(head, job, head["roots"]), indent=1).encode())
        case.what = f"{head_path.name}: a controller of another spec"
    elif kind == "swap":  # a payload file replaced by another controller's (or the other job's)
        path = rng.choice(files[1:])
        others = [p for p in sorted(jobs["bdd"].glob("controller*.dddmp")) + [jobs["array"] / "controller.npz"]
                  if p.name != path.name and p.read_bytes() != path.read_bytes()]
        source = rng.choice(others)
        case.write(path, source.read_bytes())
        case.what = f"{path.name} replaced by {source.parent.name}/{source.name}"
    elif kind == "forged node line":
        path = rng.choice([p for p in files[1:] if p.suffix == ".dddmp"])
        text, what = node_line_forged(rng, path.read_text())
        case.write(path, text.encode())
        reseal(case, head_path)
        case.what = f"{path.name}: {what}, checksums recomputed"
    else:  # forged C: text carrying C in the header, checksums recomputed (it loads: not a signature)
        meta = head["meta"]
        for key in rng.sample(sorted(k for k in ("kind", "fixed_point") if k in meta) or ["kind"], 1):
            meta[key] = PAYLOAD
        head.pop(INTEGRITY)
        case.write(head_path, json.dumps(seal(head, job, head["roots"]), indent=1).encode())
        case.what = f"{head_path.name}: C in its meta, checksums recomputed"
        case.forged_c = True
    return case


# ============================================================================================ attempts
def commands(case: Case, jobs: dict[str, Path], rng: random.Random, out: Path) -> list[list[str]]:
    """The command lines a tampered controller is tried with (one drawn, of those that read it)."""
    if case.target == "export":
        return [["import", str(jobs["export"])] + (["--x", STATE["bdd"]] if rng.random() < 0.5 else [])]
    job = jobs["array" if case.target == "array" else "bdd"]
    x = STATE["array" if case.target == "array" else "bdd"]
    if case.forged_c:
        return [["export", str(job), "--format", "c", "--out", str(out / "ctl")]]
    if case.target == "layered":
        pick = [["control", str(job), "--x", x, "--controller", "reach_safe"],
                ["export", str(job), "--format", "json", "--controller", "reach_safe", "--out", str(out / "e.json")]]
    else:
        pick = [["control", str(job), "--x", x], ["export", str(job), "--format", "c", "--out", str(out / "ctl")],
                ["export", str(job), "--format", "json", "--out", str(out / "e.json")],
                # A header removed is refused too: the job's report records the controller the audit must find.
                ["audit", str(job), "--transitions", "50", "--runs", "0", "--seed", "1"]]
    return [rng.choice(pick)]


def one_error_line(code: int, err: str, out: str = "") -> str | None:
    """Why a refusal is not clean (exit 2, one ``error:`` line, no traceback, not an internal error), or None."""
    lines = [line for line in err.splitlines() if line.strip()]
    if code != 2:
        return f"exit {code}"
    if len(lines) != 1 or not lines[0].startswith("error: "):
        return f"not one error line: {err[-600:]!r}"
    if "internal error" in lines[0] or "Traceback" in err + out:
        return f"not a clean refusal: {lines[0][:300]}"
    return None


def try_case(case: Case, jobs: dict[str, Path], out: Path) -> list[tuple[str, str | None]]:
    """Each attempt on a tampered controller: (entry point, why it went wrong or None)."""
    from pipelines import load_controller
    from pipelines.errors import CompabsError
    from service.cli import main

    rng = random.Random(f"{SEED}-controllers-try-{case.number}")
    results: list[tuple[str, str | None]] = []
    if case.target != "export":
        job = jobs["array" if case.target == "array" else "bdd"]
        try:
            load_controller(job, case.name)
            results.append(("load_controller", None if case.forged_c else "accepted"))
        except CompabsError as exc:  # refused: it must name the file (every file lies in the job's directory)
            bad = "forged C header refused" if case.forged_c else (None if str(job) in str(exc) else
                                                                   f"names no file: {exc}")
            results.append(("load_controller", bad))
        except Exception as exc:  # noqa: BLE001 - anything else is not a clean refusal, and is the finding
            results.append(("load_controller", f"{type(exc).__name__}: {str(exc)[:300]}"))
    for args in commands(case, jobs, rng, out):
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            try:
                code = main(args)
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 2
            except Exception as exc:  # noqa: BLE001 - main must not raise: that is the finding
                code, stderr = -1, io.StringIO(f"raised {type(exc).__name__}: {exc}")
        entry = " ".join(args[:1] + [a for a in args if a in ("c", "json")])
        if case.forged_c:
            results.append((entry, forged_c_ok(code, out / "ctl", stderr.getvalue())))
        else:
            results.append((entry, one_error_line(code, stderr.getvalue(), stdout.getvalue())))
        for f in out.iterdir():
            f.unlink()
    return results


def forged_c_ok(code: int, base: Path, err: str) -> str | None:
    """Why the C export of a resealed header carrying C is wrong (None: exported, none of the text in it)."""
    if code != 0:
        return f"exit {code}: {err[-300:]}"
    for suffix in (".c", ".h"):
        text = base.with_suffix(suffix).read_text()
        if "system" in text or "evil" in text or "stdlib" in text:
            return f"the header's text is in {base.name}{suffix}"
    return None


def child(argv: list[str]) -> None:
    """The child process: run cases ``start`` to ``stop``, one JSON line when each starts and one with its
    attempts when it ends (the parent reads which case a signal killed)."""
    cfg = json.loads(argv[0])
    jobs = {k: Path(v) for k, v in cfg["jobs"].items()}
    out = Path(cfg["out"])
    out.mkdir(exist_ok=True)
    for number in range(cfg["start"], cfg["stop"]):
        print(json.dumps({"start": number}), flush=True)
        case = draw(number, jobs)
        try:
            results = try_case(case, jobs, out)
        finally:
            case.restore()
        print(json.dumps({"case": number, "what": case.what, "target": case.target, "forged_c": case.forged_c,
                          "results": results}), flush=True)


@dataclass
class Outcome:
    """What the children did: attempts, refused, forged C tried / correct, crashes, and the wrong ones."""

    n: Counter[str] = field(default_factory=Counter)
    bad: list[str] = field(default_factory=list)


def run_children(jobs: dict[str, Path], cases: int, scratch: Path) -> Outcome:
    """Run cases 0 .. cases - 1 in child processes, a new child after one that a signal killed."""
    got = Outcome()
    start = 0
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    env.pop("COMPABS_DEBUG", None)
    while start < cases:
        cfg = {"jobs": {k: str(v) for k, v in jobs.items()}, "out": str(scratch / "out"), "start": start,
               "stop": cases}
        proc = subprocess.run([sys.executable, "-m", "tests.test_trust_controllers", json.dumps(cfg)], cwd=ROOT,
                              env=env, capture_output=True, text=True, timeout=3600)
        started, done = None, start
        for line in proc.stdout.splitlines():
            if not line.startswith("{"):
                continue
            msg = json.loads(line)
            if "start" in msg:
                started = msg["start"]
                continue
            done = msg["case"] + 1
            for entry, why in msg["results"]:
                got.n["forged_c" if msg["forged_c"] else "attempts"] += 1
                if why is None:
                    got.n["forged_c_ok" if msg["forged_c"] else "refused"] += 1
                else:
                    got.bad.append(f"case {msg['case']} ({msg['what']}), {entry}: {why}")
        if proc.returncode == 0:
            break
        if proc.returncode < 0 and started is not None:  # a signal: the case it started crashed the process
            got.n["crashed"] += 1
            got.n["attempts"] += 1
            got.bad.append(f"case {started}: the process died of signal {-proc.returncode}")
            start = started + 1
            continue
        raise AssertionError(f"the child failed (exit {proc.returncode}) after case {done - 1}:\n{proc.stderr[-3000:]}")
    return got


def record_children(got: Outcome, share: str) -> None:
    record(f"tampered controllers ({share}): load_controller, export/control/audit/import (issue 47)",
           inputs=got.n["attempts"], tampered=got.n["refused"], crashed=got.n["crashed"],
           wrong=got.n["attempts"] - got.n["refused"] - got.n["crashed"])
    if got.n["forged_c"]:
        record(f"forged headers carrying C, checksums recomputed ({share}): C export holds none of it",
               inputs=got.n["forged_c"], wrong=got.n["forged_c"] - got.n["forged_c_ok"])
    assert not got.bad, f"{len(got.bad)} wrong (seed {SEED}):\n" + "\n".join(got.bad[:10])


# ============================================================================================ the tests
@pytest.fixture(scope="module")
def jobs(tmp_path_factory) -> dict[str, Path]:
    return make_jobs(tmp_path_factory.mktemp("trust-controllers"))


def private(jobs: dict[str, Path], into: Path) -> dict[str, Path]:
    """Copies of the jobs' controller files, specs and reports (what the entry points read) and of the export."""
    copies = {}
    for key in ("bdd", "array"):
        copies[key] = Path(shutil.copytree(jobs[key], into / key))
    copies["export"] = Path(shutil.copy(jobs["export"], into / "export.json"))
    return copies


def test_tampered_controllers_are_refused_and_never_crash(jobs, tmp_path):
    record_children(run_children(private(jobs, tmp_path), FAST_CASES, tmp_path), "fast share")


@pytest.mark.slow
def test_tampered_controllers_many(jobs, tmp_path):
    record_children(run_children(private(jobs, tmp_path), SLOW_CASES, tmp_path), "slow share")


def real_cli(cases: range, jobs: dict[str, Path], out: Path) -> None:
    """Cases through ``python -m service.cli``: exit 2 and one error line, never a signal."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    env.pop("COMPABS_DEBUG", None)
    out.mkdir(exist_ok=True)
    n, bad = Counter[str](), []
    for number in cases:
        case = draw(number, jobs, forged_c=False)
        try:
            for args in commands(case, jobs, random.Random(f"{SEED}-cli-{number}"), out):
                r = subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=ROOT, env=env, text=True,
                                   capture_output=True, timeout=300)
                n["inputs"] += 1
                n["crashed"] += r.returncode < 0
                why = one_error_line(r.returncode, r.stderr, r.stdout)
                if why is None:
                    n["tampered"] += 1
                else:
                    bad.append(f"case {number} ({case.what}), {args[0]}: {why}")
        finally:
            case.restore()
    record("tampered controllers through python -m service.cli (a process each)", inputs=n["inputs"],
           tampered=n["tampered"], crashed=n["crashed"], wrong=n["inputs"] - n["tampered"] - n["crashed"])
    assert not bad, "\n".join(bad)


def test_tampered_controllers_through_the_command_line(jobs, tmp_path):
    real_cli(range(10_000, 10_000 + FAST_CLI), private(jobs, tmp_path), tmp_path / "out")


@pytest.mark.slow
def test_tampered_controllers_through_the_command_line_many(jobs, tmp_path):
    real_cli(range(20_000, 20_000 + SLOW_CLI), private(jobs, tmp_path), tmp_path / "out")


def api_downloads(cases: range, jobs: dict[str, Path], tmp_path: Path) -> None:
    """Tampered controllers of a succeeded job through ``GET /jobs/{id}/controller``: never 200, never 5xx."""
    from fastapi.testclient import TestClient

    from pipelines.spec.model import parse_spec
    from service.app import create_app
    from service.job_store import JobStatus
    from service.manager import new_store
    from service.settings import Settings, token_owner

    token = "trust-controllers"
    settings = Settings(data_dir=tmp_path / "data", in_process=True, token=token)
    job_id = uuid.uuid4().hex[:16]
    job_dir = Path(shutil.copytree(jobs["bdd"], settings.jobs_dir / job_id))
    spec = parse_spec(json.loads((job_dir / "spec.json").read_text()))
    store = new_store(settings)
    try:  # the job as the API stores a succeeded one, before the app starts (it would start a queued one)
        store.create(job_id, spec.name, spec.model_dump_json(), owner=token_owner(token))
        store.set_status(job_id, JobStatus.RUNNING, started=True, attempts_delta=1)
        store.set_status(job_id, JobStatus.SUCCEEDED)
    finally:
        store.close()
    target = {"bdd": job_dir, "array": jobs["array"], "export": jobs["export"]}
    n, bad = Counter[str](), []
    auth = {"Authorization": f"Bearer {token}"}
    with TestClient(create_app(settings)) as client:
        first = client.get(f"/jobs/{job_id}/controller", headers=auth)
        assert first.status_code == 200 and first.content[:2] == b"PK", first.text  # and its archive is made
        for number in cases:
            case = draw(number, target, targets=("bdd",), forged_c=False)
            try:
                r = client.get(f"/jobs/{job_id}/controller", headers=auth)
            finally:
                case.restore()
            n["inputs"] += 1
            n["4xx"] += 400 <= r.status_code < 500
            n["5xx"] += r.status_code >= 500
            detail = r.json().get("detail", "") if r.headers.get("content-type", "").startswith("application/json") \
                else None
            if 400 <= r.status_code < 500 and isinstance(detail, str) and detail and str(tmp_path) not in detail:
                n["tampered"] += 1
            else:
                bad.append(f"case {number} ({case.what}): {r.status_code} {r.text[:200]!r}")
        assert client.get(f"/jobs/{job_id}/controller", headers=auth).status_code == 200  # restored: served again
    record("tampered controllers through the API's download (GET /jobs/{id}/controller)", inputs=n["inputs"],
           **{"4xx": n["4xx"], "5xx": n["5xx"]}, tampered=n["tampered"],
           wrong=n["inputs"] - n["tampered"] - n["5xx"])
    assert not bad, "\n".join(bad[:10])


def test_tampered_controllers_through_the_api(jobs, tmp_path):
    api_downloads(range(30_000, 30_000 + FAST_API), jobs, tmp_path)


@pytest.mark.slow
def test_tampered_controllers_through_the_api_many(jobs, tmp_path):
    api_downloads(range(40_000, 40_000 + SLOW_API), jobs, tmp_path)


def test_a_draw_tampers_and_restores(jobs, tmp_path):
    """Each drawn tampering changes what it names and restoring it gives the files back byte for byte."""
    copies = private(jobs, tmp_path)
    before = {p: p.read_bytes() for key in ("bdd", "array") for p in copies[key].glob("controller*")}
    before[copies["export"]] = copies["export"].read_bytes()
    seen = Counter[str]()
    for number in range(300):
        case = draw(number, copies)
        seen[case.target] += 1
        assert case.saved and case.what, case
        case.restore()
        assert all(p.read_bytes() == data for p, data in before.items()), case.what
    assert set(seen) == {"bdd", "layered", "array", "export"}


def test_an_audit_refuses_a_job_whose_recorded_controller_is_gone(jobs, tmp_path, capsys):
    """Without its header a job would read as one without synthesis: the report's record of the controller makes
    the audit refuse it (exit 2, one line naming the file) instead of vouching for the abstraction alone."""
    from service.cli import main

    copies = private(jobs, tmp_path)
    (copies["bdd"] / "controller.json").unlink()
    assert main(["audit", str(copies["bdd"]), "--transitions", "50", "--runs", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "controller.json is missing" in err[0], err


if __name__ == "__main__":
    child(sys.argv[1:])
