"""A run stopped by a time limit (``SIGTERM`` to its process group, as ``timeout`` sends it) unwinds: its embedded
cluster is closed and its children stopped and reaped, so no ``resource_tracker: … leaked semaphore objects``
warning and no process of it is left; the audit's child is reaped as soon as it exits (no zombie during
synthesis)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from service.termination import SIGNALS, Terminated, terminate_as_interrupt
from workers.worker_signals import IGNORED, dask_setup

from .conftest import EXAMPLES
from .processes import clean_env

#: Bounds of the waits below (polls, not timings: a loaded machine only makes them take longer).
WAIT = 300.0


def _until(condition, what: str) -> None:
    end = time.monotonic() + WAIT
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"still waiting for {what} after {WAIT:.0f} s")
        time.sleep(0.2)


def test_sigterm_raises_terminated_in_the_main_thread_and_the_handlers_come_back():
    before = {s: signal.getsignal(s) for s in SIGNALS}
    with pytest.raises(Terminated) as caught, terminate_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs between bytecodes
            time.sleep(0.001)
    assert caught.value.status == 128 + signal.SIGTERM and str(caught.value) == "stopped by SIGTERM"
    assert isinstance(caught.value, KeyboardInterrupt)  # unwinds like Ctrl-C, never caught as an Exception
    assert {s: signal.getsignal(s) for s in SIGNALS} == before


def test_outside_the_main_thread_nothing_changes():
    seen = []

    def run():
        with terminate_as_interrupt():
            seen.append(signal.getsignal(signal.SIGTERM))

    before = signal.getsignal(signal.SIGTERM)
    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert seen == [before]


def test_embedded_workers_ignore_the_groups_signals():
    before = {s: signal.getsignal(s) for s in IGNORED}
    try:
        dask_setup(None)
        assert all(signal.getsignal(s) is signal.SIG_IGN for s in IGNORED)
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


def _slow_spec(directory: Path) -> Path:
    """small.yaml with a per-cell stage of tens of seconds on one thread (finer grids, many samples): stopped while
    it runs."""
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    sub = data["subsystems"][0]
    sub.update(state={"lb": 0, "ub": 32, "eta": 0.125}, samples=5000)
    data["interconnection"]["internal"] = {"lb": 0, "ub": 32, "eta": 0.125}
    path = directory / "slow.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_run_stopped_by_a_time_limit_leaves_no_leak_and_no_process(tmp_path):
    out = tmp_path / "job"
    log = tmp_path / "stderr"
    with open(log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "run", str(_slow_spec(tmp_path)), "--out",
                                 str(out), "--workers", "1"], stdout=subprocess.DEVNULL, stderr=err,
                                env=clean_env(COMPABS_HUGE_PAGES="0"), start_new_session=True)
    try:
        # The per-cell stage's first progress line (in process, the relation store appears only at its end).
        _until(lambda: b"subsystems" in log.read_bytes() or proc.poll() is not None, "the per-cell stage")
        assert proc.poll() is None, log.read_text()[-2000:]
        os.killpg(proc.pid, signal.SIGTERM)  # what `timeout` does: the whole group
        code = proc.wait(WAIT)
        _until(lambda: not _group_alive(proc.pid), "the run's processes to end")
    finally:
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    text = log.read_text()
    assert code == 128 + signal.SIGTERM, text[-2000:]
    assert "error: stopped by SIGTERM" in text
    assert "leaked semaphore" not in text and "Restarting worker" not in text, text[-2000:]


def test_the_audits_child_is_reaped_when_it_exits():
    from pipelines.spec.model import parse_spec
    from workers.job import run_abstraction
    from workers.processes.audit_beside import BackgroundAudit

    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"]["audit_transitions"] = 0
    a = run_abstraction(parse_spec(data), audit=False)
    pending = BackgroundAudit(a.network, a.relations, a.interconnection, 1_000, np.random.default_rng(0))
    try:
        pid = pending._proc.pid
        # Gone from the process table once it exited, without result() being called (a zombie stays listed).
        _until(lambda: not Path(f"/proc/{pid}").exists(), "the audit's child to be reaped")
        report, _, _ = pending.result()
        assert report["violations"] == 0
    finally:
        pending.cancel()
