"""A run of the same spec into the same directory reads back the interconnection and the audit the first run
stored (workers/resume.py), instead of computing them again; anything else is computed as before."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

import workers.job
import workers.resume
from pipelines.spec.model import parse_spec
from workers import jobdir, resume
from workers.executors import Execution
from workers.job import abstract_job, run_job

from .conftest import EXAMPLES


def _spec(**options):
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"] = {**data["options"], "audit_transitions": 3_000, "closed_loop_runs": 2, **options}
    return parse_spec(data)


def _refuse(what):
    def refuse(*args, **kwargs):
        raise AssertionError(f"{what} computed again on a resumed run")
    return refuse


@pytest.mark.parametrize("synthesis", [False, True], ids=["audit in process", "audit beside synthesis"])
def test_a_resumed_run_reads_back_the_interconnection_and_the_audit(tmp_path, monkeypatch, synthesis):
    spec, out = _spec(), tmp_path / "job"
    first = run_job(spec, out, execution=Execution(in_process=True), synthesis=synthesis)
    assert first["audit"]["transitions_checked"] > 0 and "read_back" not in first["interconnection"]
    monkeypatch.setattr(workers.resume, "abstract_interconnection", _refuse("the interconnection"))
    monkeypatch.setattr(workers.job, "audit_abstraction", _refuse("the audit"))
    monkeypatch.setattr("workers.processes.audit_beside.BackgroundAudit", _refuse("the audit"))
    again = run_job(spec, out, execution=Execution(in_process=True), synthesis=synthesis)
    assert again["interconnection"].pop("read_back") is True
    assert json.loads(json.dumps(again["interconnection"])) == json.loads(json.dumps(first["interconnection"]))
    assert again["audit"]["stored"] is True
    for key in ("transitions_checked", "violations", "parts"):
        assert again["audit"][key] == first["audit"][key]
    assert again["runner"]["chunks_computed"] == 0
    if synthesis:
        assert again["domain_states"] == first["domain_states"]


def test_the_generator_resumes_where_the_interconnection_left_it(tmp_path):
    """The audit after a read-back interconnection draws what it draws after a computed one."""
    spec, out = _spec(), tmp_path / "job"
    result, _ = abstract_job(spec, out, execution=Execution(in_process=True), audit=False)
    # small.yaml's constants are given (no draws): the interconnection is the first to use the job's generator.
    computed = np.random.default_rng(spec.options.seed)
    ia, read_back = resume.interconnection(None, spec, result.network, computed)
    assert not read_back
    other = np.random.default_rng(123)
    ia_back, read_back = resume.interconnection(out, spec, result.network, other)
    assert read_back and other.bit_generator.state == computed.bit_generator.state
    assert np.array_equal(ia_back.M_bar, ia.M_bar) and len(ia_back.nodes) == len(ia.nodes)


def test_an_audit_is_read_back_only_where_it_checked_the_same_relations(tmp_path):
    spec, out = _spec(), tmp_path / "job"
    run_job(spec, out, execution=Execution(in_process=True), synthesis=False)
    assert resume.stored_audit(out, spec, interconnection_read_back=True, chunks_computed=0) is not None
    assert resume.stored_audit(out, spec, interconnection_read_back=True, chunks_computed=1) is None
    assert resume.stored_audit(out, spec, interconnection_read_back=False, chunks_computed=0) is None
    other = _spec(audit_transitions=4_000)  # another spec hash: nothing of the first run is read back
    assert resume.stored_audit(out, other, interconnection_read_back=True, chunks_computed=0) is None
    # A damaged resume file is no resume file.
    (out / jobdir.RESUME).write_text("{not json")
    assert resume.stored_audit(out, spec, interconnection_read_back=True, chunks_computed=0) is None
    again = run_job(spec, out, execution=Execution(in_process=True), synthesis=False)
    assert "read_back" not in again["interconnection"] and "stored" not in again["audit"]


def test_overwrite_removes_the_resume_file(tmp_path):
    spec, out = _spec(), tmp_path / "job"
    run_job(spec, out, execution=Execution(in_process=True), synthesis=False)
    assert (out / jobdir.RESUME).is_file()
    other = _spec(seed=5)
    report = run_job(other, out, execution=Execution(in_process=True), synthesis=False, overwrite=True)
    assert "read_back" not in report["interconnection"]
    assert json.loads(Path(out / jobdir.RESUME).read_text())["spec_hash"] == report["spec_hash"]


def test_an_edited_interconnection_is_computed_again_not_reused(tmp_path, monkeypatch):
    """A stored node shrunk after the first run: the resumed run computes the interconnection and the audit again."""
    spec, out = _spec(), tmp_path / "job"
    first = run_job(spec, out, execution=Execution(in_process=True), synthesis=False)
    arrays = dict(np.load(out / jobdir.INTERCONNECTION_ARRAYS))
    arrays["node0_hi"] = np.maximum(arrays["node0_lo"], arrays["node0_hi"] - 1)
    np.savez_compressed(out / jobdir.INTERCONNECTION_ARRAYS, **arrays)
    again = run_job(spec, out, execution=Execution(in_process=True), synthesis=False)
    assert "read_back" not in again["interconnection"] and "stored" not in again["audit"]
    assert again["audit"]["parts"] == first["audit"]["parts"]
