"""Issue 25: ``compabs run`` prints a summary people read (states, relations, domain, closed loop, audit, times,
the files), ``--json`` the report, warnings on stderr, ``--fail-on-empty-domain`` exit 4; ``compabs --version``;
progress bars that move (the audit beside synthesis relays its progress; an open-ended stage counts iterations).
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from pipelines.verification.audit import composition_transitions
from service.cli import EMPTY_DOMAIN_STATUS, _Bars, main, seconds_text, share_text

from .conftest import EXAMPLES

#: Options that keep an in-process run of small.yaml to a few seconds.
QUICK = {"closed_loop_runs": 2, "audit_transitions": 2_000}


def spec_file(directory: Path, name: str = "spec.yaml", **changes) -> Path:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"] = {**data.get("options", {}), **QUICK}
    data.update(changes)
    path = directory / name
    path.write_text(yaml.safe_dump(data))
    return path


def run(*args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def small_job(tmp_path_factory) -> tuple[Path, str, str, dict]:
    base = tmp_path_factory.mktemp("summary")
    job = base / "job"
    code, out, err = run("run", spec_file(base), "--out", job, "--in-process", "--quiet")
    assert code == 0, err
    return job, out, err, json.loads((job / "report.json").read_text())


def _labelled(out: str) -> dict[str, str]:
    """The summary's lines by label, continuation lines joined to theirs."""
    lines: dict[str, str] = {}
    label = ""
    for line in out.splitlines()[1:]:
        if line.startswith("  ") and line[2] != " ":
            label, text = line[2:16].strip(), line[16:]
            lines[label] = text
        else:
            lines[label] += " " + line.strip()
    return lines


def test_the_summary_names_states_domain_times_and_files(small_job):
    job, out, err, report = small_job
    first = out.splitlines()[0]
    assert first == f"small: {report['abstract_states']:,} abstract states, 2 subsystems"
    lines = _labelled(out)
    domain = report["domain_states"]
    share = 100 * domain / report["abstract_states"]
    assert lines["domain"].startswith(f"{domain:,} states ({share:.3g}% of the states)")
    sub = report["subsystems"][0]
    assert lines["agent[0] ×2"].startswith(f"{sub['triples']:,} (x, u, w) triples")
    assert lines["audit"].startswith(f"{report['audit']['transitions_checked']:,} transitions, 0 violations")
    assert lines["closed loop"].startswith(f"{report['closed_loop']['runs']} runs, 0 violations")
    assert re.fullmatch(r"[\d.]+ s|\d+ min \d\d s", lines["time"]), lines["time"]
    for stage in ("subsystems", "interconnection", "synthesis", "closed loop", "audit"):
        assert re.search(rf"\b{stage} (<1 ms|[\d.]+ s)", lines["stages"]), (stage, lines["stages"])
    assert lines["report"] == str(job / "report.json")
    named = [Path(p.split(" (")[0]) for key in ("report", "relations", "controller", "figures")
             for p in lines[key].split(", ")]
    assert len(named) >= 5 and all(p.exists() for p in named), named
    # Numbers for people: no 17-digit floats, no dashboard URL (the cluster closed with the command).
    decimals = re.findall(r"\d+\.\d+", out)
    assert decimals and all(len(d.replace(".", "").lstrip("0")) <= 3 for d in decimals), decimals
    assert "http" not in out and "dashboard" not in out
    assert err == ""  # nothing to warn about; --quiet: no bars


def test_json_prints_the_report(small_job, tmp_path):
    job, _, _, report = small_job
    code, out, err = run("run", spec_file(job.parent), "--out", job, "--in-process", "--quiet", "--json")
    assert code == 0, err
    again = json.loads(out)
    assert again == json.loads((job / "report.json").read_text())
    assert again["runner"]["chunks_reused"] >= 1 and again["domain_states"] == report["domain_states"]


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"compabs {version('compabs')}\n"


def test_an_empty_domain_warns_and_fails_only_when_asked(tmp_path):
    """A drifting agent (3 cells a step) and a safe set of one composed cell: no controller keeps it there."""
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    sub = data["subsystems"][0]
    sub.update(dynamics="x[0] + 3 + 0.1 * u[0] + 0 * w[0]", lipschitz={"x": 1.01, "w": 0.01})
    spec = spec_file(tmp_path, subsystems=[sub], specification={"kind": "safe", "safe": {"boxes": [{"lb": 9.5, "ub": 10.5}]}})
    options = yaml.safe_load(spec.read_text())["options"]
    spec.write_text(yaml.safe_dump({**yaml.safe_load(spec.read_text()),
                                    "options": {**options, "initial_states": [[10.0, 10.0]]}}))
    code, out, err = run("run", spec, "--out", tmp_path / "job", "--in-process", "--quiet", "--fail-on-empty-domain")
    assert code == EMPTY_DOMAIN_STATUS == 4, err
    assert _labelled(out)["domain"].startswith("0 states (0% of the states)")
    lines = err.splitlines()
    assert any(line.startswith("warning: the winning domain is empty") for line in lines), err
    assert lines[-1] == "error: the winning domain is empty (--fail-on-empty-domain)"
    code, out, err = run("run", spec, "--out", tmp_path / "job", "--in-process", "--quiet")
    assert code == 0 and "warning: the winning domain is empty" in err and "error" not in err


# ============================================================================================ formatting
@given(st.floats(1e-3, 59.9))
def test_seconds_keep_three_significant_digits(seconds):
    text = seconds_text(seconds)
    assert text.endswith(" s") and len(text.replace(".", "").lstrip("0").rstrip(" s")) <= 3
    assert abs(float(text[:-2]) - seconds) <= 0.005 * seconds


def test_seconds_and_shares_for_people():
    assert [seconds_text(s) for s in (1e-5, 0.4547, 12.34, 125.4, 3725)] == [
        "<1 ms", "0.455 s", "12.3 s", "2 min 05 s", "1 h 02 min"]
    assert [share_text(p, w) for p, w in ((629, 1089), (0, 5), (1, 10**6), (5, 5), (1, 0))] == [
        "57.8%", "0%", "<0.01%", "100%", "-"]


# ============================================================================================ progress
def test_bars_count_an_open_ended_stage_and_keep_the_audit_beside(capsys):
    bars = _Bars(True)
    try:
        bars("interconnection", 1, 1, "done")
        bars("audit", 0, 1, "beside synthesis")
        for k, total in ((0, 1), (1, 2), (2, 3), (3, 4)):  # synthesis: iterations, their number unknown
            bars("synthesis", k, total, f"iteration {k}")
        synthesis, audit, inter = (bars._bars[s] for s in ("synthesis", "audit", "interconnection"))
        assert synthesis.total is None and synthesis.n == 3 and synthesis.unit == "it"
        assert inter.disable and not audit.disable  # the finished stage closed, the audit's bar stays
        bars("audit", 50, 100, "agent checked")
        bars("synthesis", 1, 1, "done")  # its last event: the count reached is the total
        assert synthesis.n == synthesis.total == 3 and audit.n == 50
        bars("subsystems", 2, 5, "chunk 2")
        bars("subsystems", 3, 5, "chunk 3")  # a fixed total stays one
        assert bars._bars["subsystems"].total == 5 and bars._bars["subsystems"].n == 3
        bars("audit", 100, 100, "composition checked")
        bars("audit", 1, 1, "100 transitions, 0 violations")  # finish_audit's closing event keeps the counts
        assert audit.n == audit.total == 100
    finally:
        bars.close()
    assert "synthesis" in capsys.readouterr().err


@pytest.fixture(scope="module")
def abstraction():
    from pipelines.spec.model import load_spec
    from workers.job import run_abstraction

    return run_abstraction(load_spec(EXAMPLES / "small.yaml"), audit=False)


def test_the_audit_beside_synthesis_reports_its_progress(abstraction):
    from workers.processes.audit_beside import BackgroundAudit

    count, seen = 5_000, []
    pending = BackgroundAudit(abstraction.network, abstraction.relations, abstraction.interconnection, count,
                              np.random.default_rng(0), progress=lambda *event: seen.append(event))
    report, _, _ = pending.result()
    total = 2 * count + composition_transitions(count)  # one distinct subsystem, the interconnection, composition
    assert [event[:2] for event in seen] == [(0, total), (count, total), (2 * count, total), (total, total)]
    assert seen[-1][2] == "composition checked" and report["violations"] == 0
    assert not pending._dir.exists()


def test_a_failing_progress_callback_stops_the_relay_not_the_audit(abstraction):
    from workers.processes.audit_beside import BackgroundAudit

    seen = []

    def cancelled(*event):
        seen.append(event)
        raise RuntimeError("job cancelled")

    pending = BackgroundAudit(abstraction.network, abstraction.relations, abstraction.interconnection, 1_000,
                              np.random.default_rng(0), progress=cancelled)
    report, _, _ = pending.result()
    assert len(seen) == 1 and report["transitions_checked"] > 1_000


def test_the_summary_says_when_synthesis_resumed_from_a_checkpoint(small_job):
    from service.cli import summary_lines

    job, out, _, report = small_job
    assert "resumed" not in _labelled(out)
    report = {**report, "synthesis": {**report["synthesis"],
                                      "checkpoints": {"resumed_at_iteration": {"reach_safe/safe": 9}}}}
    text = "\n".join(summary_lines(report, job))
    assert _labelled(text)["resumed"].strip() == "reach_safe/safe from iteration 9"


def test_the_summary_says_a_domain_from_a_quotient_is_not_maximal(small_job):
    from service.cli import summary_lines

    job, out, _, report = small_job
    assert "quotient" not in _labelled(out)["domain"]
    report = {**report, "synthesis": {**report["synthesis"], "quotient": {"level": 1, "cells_per_block": 2},
                                      "domain_bound": {"domain_states_at_most": 123_456}}}
    domain = _labelled("\n".join(summary_lines(report, job)))["domain"]
    assert "from the quotient of level 1, not maximal (the maximal one has at most 123,456)" in domain
    report["synthesis"]["quotient"]["refine_rounds"] = 2
    domain = _labelled("\n".join(summary_lines(report, job)))["domain"]
    assert "from the quotient of level 1, grown on the fine grid (2 rounds at most), not maximal" in domain



def test_the_summary_names_an_array_controllers_files(tmp_path):
    """An explicit game's controller is a header and its arrays, and the summary says so."""
    from service.cli import _file_lines

    report = {"controller": {"form": "array", "files": ["controller.npz", "controller.json"]}}
    text = "\n".join(str(row) for row in _file_lines(report, tmp_path))
    assert "controller.json (and 1 array file beside it)" in text and "BDD file" not in text
