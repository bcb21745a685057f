"""The audit in a child process beside synthesis (``workers.processes.audit_beside``): the same report as in the job's
process, errors of the child as clear errors, nothing left behind when a job stops."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest

import workers.processes.audit_beside as audit_beside
from pipelines.errors import BlackBoxError, CompabsError
from pipelines.spec.model import load_spec
from workers.job import run_abstraction
from workers.job_session import JobSession
from workers.processes.audit_beside import BackgroundAudit

from .conftest import EXAMPLES


def small(**options):
    spec = load_spec(EXAMPLES / "small.yaml")
    return spec.model_copy(update={"options": spec.options.model_copy(update={"audit_transitions": 20_000, **options})})


def test_audit_beside_equals_the_audit_in_this_process():
    here = run_abstraction(small())
    session = JobSession()
    beside = run_abstraction(small(), session=session)
    assert beside.report["audit"].get("pending") and session.pending_audit is not None
    seen = []
    session.finish_audit(beside, lambda *a: seen.append(a))
    got = beside.report["audit"]
    assert got["beside_synthesis"] and got["waited_seconds"] >= 0 and session.pending_audit is None
    assert {k: v for k, v in got.items() if k not in ("beside_synthesis", "waited_seconds")} == here.report["audit"]
    assert got["transitions_checked"] > 20_000 and got["violations"] == 0
    assert seen[-1][:3] == ("audit", 1, 1) and beside.report["stage_seconds"]["audit"] > 0
    session.finish_audit(beside)  # nothing pending: nothing happens
    assert beside.report["audit"] == got


def test_the_child_imports_this_package_from_any_working_directory(tmp_path, monkeypatch):
    """``python -m`` puts its working directory first on sys.path: a job run from a directory holding another
    ``pipelines`` (an older checkout) must still audit with this one."""
    spec = small()
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "__init__.py").write_text("raise ImportError('the decoy pipelines package')\n")
    monkeypatch.chdir(tmp_path)
    session = JobSession()
    beside = run_abstraction(spec, session=session)
    session.finish_audit(beside)
    assert beside.report["audit"]["transitions_checked"] > 20_000 and beside.report["audit"]["violations"] == 0


def test_a_child_that_fails_is_a_clear_error_and_leaves_no_files():
    r = run_abstraction(small(), audit=False)
    bad = BackgroundAudit(r.network, {}, r.interconnection, 1000, None)  # no relations: the child fails
    folder = bad._dir
    with pytest.raises(CompabsError, match="audit's child process exited with status 1"):
        bad.result()
    assert not folder.exists()


def test_a_users_error_in_the_child_is_raised_as_it_is(tmp_path, monkeypatch):
    """A CompabsError in the child (say a black box that returns NaN on an audit sample) reaches the caller with
    its class and message; the child side is ``main``, run here with the audit replaced by one that fails."""
    import pipelines.verification.audit

    def failing(*args, **kwargs):
        raise BlackBoxError("subsystem 'agent' returned NaN at x=[3.5]")

    monkeypatch.setattr(pipelines.verification.audit, "audit_abstraction", failing)
    src, dst = tmp_path / "in.pickle", tmp_path / "out.pickle"
    src.write_bytes(pickle.dumps((None, {}, None, 10, None)))
    assert audit_beside.main([str(src), str(dst)]) == 0
    kind, exc = pickle.loads(dst.read_bytes())
    assert kind == "error" and isinstance(exc, BlackBoxError) and "NaN at x=[3.5]" in str(exc)


def test_cancel_stops_the_child_and_removes_its_files():
    session = JobSession()
    run_abstraction(small(audit_transitions=2_000_000), session=session)
    pending = session.pending_audit
    assert pending is not None
    folder: Path = pending._dir
    session.cancel_audit()
    assert pending._proc.poll() is not None and not folder.exists() and session.pending_audit is None
    session.cancel_audit()  # idempotent


def test_leaving_the_session_stops_the_child():
    """A job that fails or is cancelled during synthesis leaves its session (``with``): the audit stops with it."""
    with pytest.raises(RuntimeError, match="synthesis failed"), JobSession() as session:
        run_abstraction(small(audit_transitions=2_000_000), session=session)
        pending = session.pending_audit
        assert pending is not None
        raise RuntimeError("synthesis failed")
    assert pending._proc.poll() is not None and not pending._dir.exists() and session.pending_audit is None


PARENT_THAT_DIES = """
import os, signal, sys
from pathlib import Path
sys.path.insert(0, {root!r})
from tests.test_audit_beside import small
from workers.job import run_abstraction
from workers.job_session import JobSession
s = JobSession()
run_abstraction(small(audit_transitions=50_000_000), session=s)
p = s.pending_audit
print(p._proc.pid, p._dir, flush=True)
os.kill(os.getpid(), signal.SIGKILL)  # no cancel, no finally: as when the job's process is killed
"""


def test_the_child_stops_and_cleans_up_when_its_parent_is_killed():
    """A job's process killed outright cannot cancel its audit: the child notices the death of its parent, stops
    and removes its folder, instead of finishing an audit nobody reads (50 M transitions: about a minute)."""
    import subprocess
    import sys
    import time

    import psutil

    root = str(Path(__file__).resolve().parent.parent)
    run = subprocess.run([sys.executable, "-c", PARENT_THAT_DIES.format(root=root)], capture_output=True,
                         text=True, timeout=300, cwd=root)
    assert run.returncode == -9, run.stderr[-2000:]
    pid, folder = run.stdout.split()
    try:
        deadline = time.monotonic() + 30
        while psutil.pid_exists(int(pid)) and psutil.Process(int(pid)).status() != psutil.STATUS_ZOMBIE:
            assert time.monotonic() < deadline, "the audit's child outlived its parent by 30 s"
            time.sleep(0.1)
        assert not Path(folder).exists()
    finally:
        # On failure, stop the orphaned child here rather than let it audit on beside the next tests (its command
        # line names its folder, so a reused pid is left alone).
        try:
            child = psutil.Process(int(pid))
            if folder in " ".join(child.cmdline()):
                child.kill()
        except psutil.Error:
            pass
