"""Trust campaign, issue 23, the command line and the store (the API's boundary: ``tests/test_trust_boundary.py``).

* integrity: random damage (a chunk deleted, garbage bytes, truncated, two chunks swapped, within an array or
  between ``lo`` and ``hi``) to a small in-process job's ``relations.zarr``: ``compabs audit`` reports exactly
  the damaged chunks (exit 3, each named), a rerun recomputes exactly those and gives a fresh run's relations,
  and the audit then passes;
* CLI: random bad argument vectors and bad spec files (binary, latin-1, UTF-16, NUL bytes, over 1 MiB, FIFOs,
  devices, directories, symlink loops, empty, deep nesting, ...) through ``service.cli.main``: exit 2, one
  ``error:`` line, no traceback, no output directory created.

Nothing runs but the integrity job: the abstraction, the cluster and ``serve`` are guards that count a payload
executed. Cases are drawn from ``COMPABS_TRUST_SEED`` (default 23).
"""

from __future__ import annotations

import json
import os
import random
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from pipelines.spec.model import load_spec
from service.cli import main
from workers.executors import Execution
from workers.job import abstract_job, run_abstraction

from .conftest import EXAMPLES
from .trust_log import Tally

SEED = int(os.environ.get("COMPABS_TRUST_SEED", "23"))
SMALL = EXAMPLES / "small.yaml"
SMALL_TEXT = SMALL.read_text()
EXECUTED: list[str] = []
N_CHUNKS = 9  # small.yaml's 33 state cells in chunks of 4


def rng_for(name: str) -> random.Random:
    return random.Random(f"{SEED}-{name}")


def tally(label: str) -> Tally:
    return Tally(label, EXECUTED, SEED)


def one_error(code: int, out: str, err: str) -> bool:
    lines = [line for line in err.splitlines() if line.strip()]
    return code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in out + err


# ============================================================================================ integrity
@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> tuple[Path, Any, Any]:
    """A finished ``compabs run --in-process --no-synthesis`` of small.yaml in 9 chunks, its spec, a fresh run's
    relations."""
    base = tmp_path_factory.mktemp("boundary-integrity")
    data = yaml.safe_load(SMALL_TEXT)
    data["options"].update(chunk_cells=4, audit_transitions=1000)
    (base / "spec.yaml").write_text(yaml.safe_dump(data))
    assert main(["run", str(base / "spec.yaml"), "--out", str(base / "job"), "--quiet", "--in-process",
                 "--no-synthesis"]) == 0
    spec = load_spec(base / "spec.yaml")
    return base / "job", spec, run_abstraction(spec, audit=False)


def chunk_files(job: Path) -> dict[tuple[str, int], Path]:
    """The data chunk files of the job's one relation group, by (array, chunk)."""
    (group,) = [p for p in (job / "relations.zarr").iterdir() if p.is_dir()]
    return {(f.relative_to(group).parts[0], int(f.relative_to(group).parts[2])): f
            for array in ("lo", "hi", "blocking") for f in sorted((group / array / "c").rglob("*")) if f.is_file()}


def damage(rng: random.Random, job: Path) -> tuple[set[int], list[str]]:
    """One to three random damages; the chunks damaged and what was done."""
    hit, done = set(), []
    for _ in range(rng.randint(1, 3)):
        files = chunk_files(job)
        (array, k), f = rng.choice(sorted(files.items()))
        kind, data = rng.choice(["delete", "garbage", "truncate", "swap", "swap"]), f.read_bytes()
        if kind == "delete":
            f.unlink()
        elif kind == "garbage":
            f.write_bytes(rng.randbytes(rng.randint(1, 400)))
        elif kind == "truncate":
            f.write_bytes(data[:rng.randrange(len(data))])
        else:  # with another chunk of the same array, or of the other bound array (same shape and dtype)
            others = [(key, g) for key, g in sorted(files.items()) if key != (array, k) and g.read_bytes() != data
                      and (key[0] == array or {key[0], array} == {"lo", "hi"})]
            if not others:
                continue
            (other, j), g = rng.choice(others)
            f.write_bytes(g.read_bytes())
            g.write_bytes(data)
            hit.add(j)
            kind += f" with {other}[{j}]"
        hit.add(k)
        done.append(f"{kind} {array}[{k}]")
    return hit, done


def same_relations(a: Any, b: Any) -> bool:
    return a.relations.keys() == b.relations.keys() and all(
        np.array_equal(getattr(ra, f), getattr(b.relations[key], f)) and getattr(ra, f).dtype == getattr(
            b.relations[key], f).dtype for key, ra in a.relations.items() for f in ("lo", "hi", "blocking"))


def audit(job: Path, seed: int, capsys) -> tuple[int, str, str, dict[str, Any]]:
    code = main(["audit", str(job), "--transitions", "300", "--seed", str(seed), "--runs", "0"])
    out, err = capsys.readouterr()
    return code, out, err, json.loads((job / "audit.json").read_text())


def test_random_chunk_damage(finished, tmp_path, capsys):
    stored, spec, fresh = finished
    rng = rng_for("integrity")
    audited, rerun = tally("integrity: random chunk damage (compabs audit names the chunks)"), \
        tally("integrity: random chunk damage (rerun recomputes them, identical)")
    for i in range(24):
        job = Path(shutil.copytree(stored, tmp_path / f"job{i}"))
        hit, done = damage(rng, job)
        code, out, err, result = audit(job, i, capsys)
        found = sorted(d["chunk"] for d in result["relation_store"]["damaged"])
        named = all(f"chunk {k} (state cells" in result["parts"]["relation store"]["first_violation"] + out
                    for k in found[:1])
        audited.check(code == 3 and found == sorted(hit) and named and "Traceback" not in out + err,
                      f"{done}: exit {code}, damaged {found}, expected {sorted(hit)}: {err[-300:]}")
        try:
            again, info = abstract_job(spec, job, execution=Execution(in_process=True), audit=False)
            ok = (info["chunks_computed"], info["chunks_reused"]) == (len(hit), N_CHUNKS - len(hit)) and \
                same_relations(fresh, again)
            outcome = f"computed {info['chunks_computed']}, reused {info['chunks_reused']}"
        except Exception as exc:
            ok, outcome = False, f"{type(exc).__name__}: {exc}"
        code, out, err, result = audit(job, i, capsys)
        rerun.check(ok and code == 0 and result["relation_store"]["damaged"] == [], f"{done}: {outcome}; audit "
                    f"after: exit {code}, {result['relation_store']['damaged']}")
    audited.done(cases="faults", ok_as="failed_cleanly")
    rerun.done(cases="faults", ok_as="identical")


# ============================================================================================ the command line
@pytest.fixture
def cli(monkeypatch, capsys, tmp_path) -> Callable[[list[Any]], tuple[bool, str]]:
    """``main(argv)`` with nothing runnable (a guard counts what would have run): (exit 2 with one error line and
    no traceback, what it printed)."""
    for target in ("workers.job.run_abstraction", "workers.cluster.connect", "service.serve.cmd_serve"):
        def refuse(*args: Any, _what: str = target, **kwargs: Any) -> Any:
            EXECUTED.append(_what)
            raise AssertionError(f"{_what} ran")

        monkeypatch.setattr(target, refuse)
    monkeypatch.chdir(tmp_path)

    def run(argv: list[Any]) -> tuple[bool, str]:
        before = len(EXECUTED)
        code = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        ran = EXECUTED[before:]
        return one_error(code, out, err) and not ran, f"{[str(a)[:60] for a in argv]}: exit {code}, ran {ran}: " \
            f"{(out + err)[-300:]!r}"

    return run


#: Integer options and their least value (serve's are plain integers: only non-integers are wrong there).
INT_OPTIONS: dict[str, dict[str, int | None]] = {"run": {"--workers": 1, "--audit-transitions": 0}, "audit": {"--transitions": 0, "--seed": 0,
               "--runs": 0}, "simulate": {"--steps": 1, "--seed": 0}, "serve": {"--port": None, "--workers": None}}
BAD_SETS = ["N", "N=abc", "N=inf", "N=-inf", "N=nan", "N=1e999", "M=3", "=3", "N=", "N=2.5", "N=-2", "N=0", "n=2",
            "N=1e6", "N=²", "N=0x10", "N==2", "N=2=3"]


def bad_int(rng: random.Random, least: int | None) -> str:
    """A value ``int`` refuses, or one below ``least``."""
    while True:
        text = rng.choice(["", "abc", "1.5", "1e3", "²", "0x10", "+-1", "9" * rng.randint(4301, 6000), "1_0_", "nan",
                           "٣.", str(-rng.randint(1, 10**30)), "-0", "0", "inf", "--1"])
        try:
            value = int(text)
        except ValueError:
            return text
        if least is not None and value < least:
            return text


def bad_argv(rng: random.Random, d: Path) -> list[Any]:
    sub = rng.choice(["validate", "run", "run", "audit", "simulate", "serve", "schema", "unknown"])
    bases: dict[str, list[Any]] = {"validate": ["validate", SMALL], "run": ["run", SMALL, "--out", d / "out", "--quiet"],
                       "audit": ["audit", d], "simulate": ["simulate", d, "--x0", "1,2"],
                       "serve": ["serve", "--in-process", "--data", d / "data"], "schema": ["schema"],
                       "unknown": [rng.choice(["runn", "Validate", "", "-x", "audit2", "--run", "help", "rUn"])]}
    argv = bases[sub]
    defects = ["option"] + ["int"] * (sub in INT_OPTIONS) + ["set", "missing"] * (sub in ("validate", "run")) + \
        ["missing"] * (sub in ("audit", "simulate")) + ["audit-bound"] * (sub == "run")
    defect = rng.choice(defects)
    if defect == "option":  # unknown (never a prefix argparse would complete: --no-such-...)
        return argv + ["--no-such-" + "".join(rng.choices("abcxyz-", k=rng.randint(1, 12)))]
    if defect == "int":
        option, least = rng.choice(sorted(INT_OPTIONS[sub].items()))
        return argv + [option, bad_int(rng, least)]
    if defect == "set":
        return argv + [x for s in rng.sample(BAD_SETS, rng.randint(1, 3)) for x in ("--set", s)]
    if defect == "audit-bound":  # over options.audit_transitions' bound (10^8): refused before anything runs
        return argv + ["--audit-transitions", str(rng.randint(10**8 + 1, 10**4000))]
    required = [a for a in argv if a in (SMALL, d, "--x0", "1,2", "--out", d / "out")]
    gone = rng.sample(required, rng.randint(1, len(required))) if required else []
    return [a for a in argv if a not in gone] if gone else argv[:1]


def test_random_bad_argument_vectors(cli, tmp_path):
    rng, row = rng_for("argv"), tally("CLI: random bad argument vectors")
    (tmp_path / "empty").mkdir()
    for _ in range(1500):
        argv = bad_argv(rng, tmp_path / "empty")
        ok, said = cli(argv)
        row.check(ok and not (tmp_path / "empty" / "out").exists(), said)
    row.done(ok_as="failed_cleanly")


def bad_file(rng: random.Random, d: Path, i: int) -> Path:
    """A spec path that is not a readable, valid spec (the kinds of the module docstring)."""
    p = d / f"spec{i}.yaml"
    text = SMALL_TEXT
    at = rng.randrange(len(text))
    kind = rng.randrange(13)
    if kind == 0:
        p.write_bytes(rng.randbytes(rng.randint(0, 3000)) + b"\xff")
    elif kind == 1:  # latin-1: bytes >= 0xC0 are never continuation bytes, so never valid UTF-8
        p.write_bytes((text[:at] + "".join(rng.choices("ÀÉÖßéñöÿ", k=rng.randint(1, 5))) + text[at:]).encode("latin-1"))
    elif kind == 2:
        p.write_bytes(text.encode(rng.choice(["utf-16", "utf-32", "utf-16-be"])))
    elif kind == 3:
        p.write_text(text[:at] + "\x00" + text[at:])
    elif kind == 4:
        p.write_bytes(b"# " + b"x" * (2**20 + rng.randint(0, 2**18)) + b"\n" + text.encode())
    elif kind == 5:
        os.mkfifo(p)
    elif kind == 6:
        p.mkdir()
    elif kind == 7:
        return Path(rng.choice(["/dev/null", "/dev/zero", "/dev/urandom", "/dev/full"]))
    elif kind == 8:
        return d / "missing" / p.name
    elif kind == 9:
        p.symlink_to(p if rng.random() < 0.5 else d)  # a loop, or a directory
    elif kind == 10:
        p.write_text(rng.choice(["", "  \n", "- 1\n- 2\n", "42\n", "just text\n", "null\n", "[]\n", "{}\n"]))
    elif kind == 11:
        depth = rng.randint(200, 20_000)
        p.write_text(rng.choice(["[" * depth + "]" * depth, "{a: " * depth + "1" + "}" * depth, rng.choice(
            ["\t", "]", "{[", "*nowhere ", "&a &b ", "- ", "!!python/object/apply:os.system ['true']\n", "%YAML 9\n",
             "--- 1\n--- 2\n"]) + text]))
    else:
        p.write_text(text.replace("N: 2", rng.choice(["N: " + "9" * 5000, "N: .inf", "N: .nan", "N: 1e999"])))
    return p


def test_random_bad_spec_files(cli, tmp_path):
    rng, row = rng_for("spec-files"), tally("CLI: random bad spec files (validate, run)")
    for i in range(180):
        d = tmp_path / str(i)
        d.mkdir()
        path = bad_file(rng, d, i)
        for command in (["validate", path], ["run", path, "--out", d / "out", "--quiet"]):
            ok, said = cli(command)
            row.check(ok and not (d / "out").exists(), said)
    row.done(ok_as="failed_cleanly")


def stand_in(calls: list[Any]) -> Callable[..., Any]:
    """A function that notes its call and fails (what it stands in for must not have been reached)."""
    def reached(*args: Any, **kwargs: Any) -> Any:
        calls.append(args)
        raise RuntimeError("reached")

    return reached


def test_workers_beyond_any_machine_are_refused(tmp_path, capsys, monkeypatch):
    started: list[Any] = []
    monkeypatch.setattr("workers.cluster.connect", stand_in(started))
    code = main(["run", str(SMALL), "--out", str(tmp_path / "out"), "--quiet", "--workers", "100000"])
    assert one_error(code, *capsys.readouterr()) and not started, started


def test_audit_transitions_beyond_the_cap_are_refused(finished, tmp_path, capsys, monkeypatch):
    started: list[Any] = []
    monkeypatch.setattr("workers.job_audit.audit_abstraction", stand_in(started))
    job = Path(shutil.copytree(finished[0], tmp_path / "job"))
    code = main(["audit", str(job), "--transitions", str(10**11), "--runs", "0"])
    assert one_error(code, *capsys.readouterr()) and not started


def test_a_thousand_subsystems_validate_without_internal_error(tmp_path, capsys):
    data = yaml.safe_load(SMALL_TEXT)
    data["options"]["initial_states"] = []
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(data))
    code = main(["validate", str(tmp_path / "spec.yaml"), "--set", "N=1000"])
    out, err = capsys.readouterr()
    assert "internal error" not in err and (code == 0 or one_error(code, out, err)), err
