"""Hostile black boxes and faults on a real two-worker LocalCluster (issue 7).

Every test ends in one of two outcomes, never a third: a completed job whose relations are bit-identical to an
undisturbed in-process run (arrays compared), or a failed job with a clear error (type and message checked) and a
store that resumes to the identical result.

Not repeated here, see ``tests/test_workers.py``: a worker SIGKILLed while the per-cell stage runs
(``test_worker_killed_mid_job``), the runner SIGKILLed mid-job (``test_runner_killed_mid_job_resumes``), a task
that kills every worker it lands on (``test_task_that_kills_its_workers_is_a_clear_error``). The API process
SIGKILLed mid-job and restarted is the service's test (``tests/test_service_e2e.py``). The stages after the
per-cell one (Lipschitz constants, interconnection, synthesis, closed loop) run in the runner's process, the audit
in a child process beside synthesis, so a worker killed during them costs nothing but its restart;
``test_worker_killed_in_every_runner_stage`` checks exactly that.
"""

from __future__ import annotations

import errno
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from pipelines.errors import BlackBoxError, LipschitzError
from pipelines.spec.model import parse_spec
from service.cli import main
from workers.cluster import credentials_env
from workers.errors import StoreError, TaskTimeoutError
from workers.executors import Execution
from workers.job import abstract_job, run_abstraction, run_job

from .conftest import EXAMPLES, ROOT, wait_idle
from .test_workers import assert_same_relations, marker_counts, store_of
from .trust_log import record


def spec_of(dynamics: str | None = None, chunk_cells: int | None = 4, sub: dict | None = None, **options: Any):
    """small.yaml with a cheap tail; ``dynamics`` replaces the agent's, ``options`` are added."""
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    if dynamics is not None:
        data["subsystems"][0]["dynamics"] = dynamics
    data["subsystems"][0].update(sub or {})
    data["options"] = {**data.get("options", {}), "chunk_cells": chunk_cells, "audit_transitions": 0,
                       "closed_loop_runs": 3, **options}
    return parse_spec(data)


@pytest.fixture(scope="module")
def reference():
    """small.yaml's relations in-process, chunks of 4 cells (the undisturbed run)."""
    return run_abstraction(spec_of(), audit=False)


def same_as_reference(result, reference) -> bool:
    assert_same_relations(reference, result)  # raises with the array named if not
    return True


# ================================================================================================ black boxes
HOSTILE = [
    ("nan_above_20", r"returned \[nan\] \(not finite\) at x=\[2\d\.\d*\].* \(state cell 2\d, input \d, internal cell \d+\)"),
    ("inf_above_20", r"returned \[inf\] \(not finite\) at x=.*\(state cell 2\d, input \d, internal cell \d+\)"),
    ("wrong_shape", r"returned shape \(\d+, 2\), expected \(\d+, 1\) on the batch from state cell \d+, input 0, internal cell 0 to state cell \d+, input 4, internal cell 32"),
    ("flat_shape", r"returned shape \(\d+,\), expected \(\d+, 1\) on the batch from state cell \d+, input 0, internal cell 0 to state cell \d+"),
    ("raises", r"raised RuntimeError: the simulator crashed on the batch from state cell 2\d, input 0, internal cell 0 to state cell 2\d"),
]


@pytest.mark.parametrize("box,pattern", HOSTILE, ids=[h[0] for h in HOSTILE])
def test_hostile_black_box_fails_the_job_naming_subsystem_and_cell(tmp_path, client, box, pattern):
    spec = spec_of(f"tests.hostile_boxes:{box}")
    with pytest.raises(BlackBoxError) as err:
        abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    message = str(err.value)
    assert message.startswith("subsystem 'agent[0]' dynamics: "), message
    assert re.search(pattern, message), message
    wait_idle(client)
    done, total = marker_counts(tmp_path)
    assert total == 9 and done < total  # chunks before the bad cells may be done; the store stays valid
    record(f"black box: {box} (cluster)", inputs=1, failed_cleanly=1, wrong=0)


@pytest.mark.parametrize("box", ["hangs", "spins"])
def test_hung_black_box_times_out_while_another_job_completes(tmp_path, client, reference, box):
    """A black box that never returns: the job fails after ``options.task_timeout``, naming the subsystem and the
    cells; a job running at the same time on the same cluster completes, identical to the undisturbed run.

    No duration is asserted: the boxes never return (``hangs`` sleeps an hour, ``spins`` forever), so the
    TaskTimeoutError and the unmarked chunk can only come from the timeout; were it not enforced, the job would
    hang and the test fail at pytest-timeout's limit."""
    hung = spec_of(f"tests.hostile_boxes:{box}", chunk_cells=33, task_timeout=3)
    other: dict[str, Any] = {}

    def run_other() -> None:
        try:
            other["result"], other["info"] = abstract_job(spec_of(), tmp_path / "other", execution=Execution(client=client), audit=False)
        except BaseException as exc:  # reported by the assertion below
            other["error"] = exc

    pids = set(client.run(os.getpid).values())
    thread = threading.Thread(target=run_other, daemon=True)
    thread.start()
    try:
        with pytest.raises(TaskTimeoutError) as err:
            abstract_job(hung, tmp_path / "hung", execution=Execution(client=client), audit=False)
    finally:
        thread.join(300)
    assert not thread.is_alive(), "the other job did not end within 300 s of the hung one"
    message = str(err.value)
    assert "subsystem 'agent[0], agent[1]', chunk 0 (state cells 0..32)" in message, message
    assert "did not finish state cells 0..32 within options.task_timeout = 3 s" in message, message
    assert "error" not in other, other.get("error")
    assert same_as_reference(other["result"], reference)
    # Nothing was stored, so the failed run leaves no directory behind (jobdir.discard_unused).
    assert not (tmp_path / "hung").exists()
    client.wait_for_workers(2, timeout=240)
    after = set(client.run(os.getpid).values())
    if box == "spins":
        assert after == pids  # a Python loop is stopped in place: no worker restarted
    else:
        assert len(after - pids) == 1  # a thread blocked in C cannot be: its worker was restarted
    # The cluster still works: a third job completes.
    again, _ = abstract_job(spec_of(), tmp_path / "third", execution=Execution(client=client), audit=False)
    assert same_as_reference(again, reference)
    record(f"black box: {box} (cluster, task_timeout, 2 other jobs)", inputs=1, failed_cleanly=1, identical=2, wrong=0)


def test_task_timeout_is_not_part_of_the_spec_hash():
    from pipelines.spec.model import spec_hash

    assert spec_hash(spec_of(task_timeout=3)) == spec_hash(spec_of(task_timeout=600)) == spec_hash(spec_of(task_timeout=None))


# ================================================================================================ faults
def test_worker_killed_in_every_runner_stage(tmp_path, client, reference, capsys):
    """SIGKILL a worker at the start of each stage that runs in the runner's process: the job completes, its
    relations identical to the undisturbed run, its controller audited clean; then its stored Zarr relation is
    corrupted and ``compabs audit`` catches it."""
    spec = spec_of(audit_transitions=20_000)
    stages = ("lipschitz", "interconnection", "audit", "synthesis", "closed_loop")
    killed: list[tuple[str, int]] = []

    def two_live_workers() -> list[int]:
        # The audit starts (beside synthesis) right after the interconnection and synthesis right after it, so a
        # kill can follow the previous one within milliseconds: wait until two workers answer, not only until the
        # scheduler lists two (it may still list the one just killed).
        deadline = time.monotonic() + 240
        while True:
            pids = client.run(os.getpid, on_error="ignore")
            if len(pids) >= 2:
                return sorted(pids.values())
            assert time.monotonic() < deadline, (
                f"the cluster did not get back to two workers within 240 s of killing {killed[-1:]}")
            time.sleep(0.2)

    lock = threading.Lock()  # the audit's relay thread reports its parts while this thread reports synthesis

    def progress(stage: str, done: int, total: int, message: str) -> None:
        with lock:
            if stage in stages and stage not in {s for s, _ in killed}:
                victim = two_live_workers()[len(killed) % 2]
                os.kill(victim, signal.SIGKILL)
                killed.append((stage, victim))

    out = tmp_path / "job"
    report = run_job(spec, out, execution=Execution(client=client), progress=progress)
    assert [s for s, _ in killed] == list(stages)
    client.wait_for_workers(2, timeout=240)
    assert not {v for _, v in killed} & set(client.run(os.getpid).values())  # each victim died, was replaced
    assert report["audit"]["violations"] == 0 and report["closed_loop"]["violations"] == 0
    assert report["runner"]["chunks_computed"] == 9

    from workers.jobdir import load_job

    arts = load_job(out)
    assert arts.relation_source == "zarr"
    (key,) = reference.relations
    for field in ("lo", "hi", "blocking"):
        assert np.array_equal(getattr(arts.relations[key], field), getattr(reference.relations[key], field)), field
    record("faults: worker SIGKILLed in each runner-process stage", faults=len(stages), identical=1, wrong=0)

    # The audit of the stored (Zarr) abstraction passes; with one interval shrunk it fails, naming the cell.
    assert main(["audit", str(out), "--transitions", "50000", "--seed", "3", "--runs", "3"]) == 0
    capsys.readouterr()
    import zarr

    from .test_audit import shrink_one_interval

    (group,) = arts.relation_files.values()
    g = zarr.open_group(str(out / "relations.zarr"), path=group, mode="r+", use_consolidated=False)
    arrays = {k: g[k][:] for k in ("lo", "hi", "blocking")}
    x, u, w, c = shrink_one_interval(arrays, arts.network.subsystems[0])
    g["lo"][x, u, w] = arrays["lo"][x, u, w]
    g["hi"][x, u, w] = arrays["hi"][x, u, w]
    assert main(["audit", str(out), "--transitions", "100000", "--seed", "3", "--runs", "0"]) == 3
    audit = json.loads((out / "audit.json").read_text())
    first = audit["parts"]["subsystem agent[0]"]["first_violation"]
    assert f"agent[0]: state cell {x}, input {u}, internal cell {w}" in first and f"in cell [{c}]" in first
    assert audit["relation_source"] == "zarr"
    record("audit: shrunk stored relation interval (Zarr)", faults=1, failed_cleanly=1, wrong=0)


class _Abandoned(Exception):
    """Raised on a worker by a chunk paused by :func:`_pause_after_data` when it is released."""


def _pause_after_data(flag: str, release: str, start: int, limit: float) -> None:
    """On a worker: the first task to reach the done-marker of the chunk starting at ``start`` creates ``flag``
    (its pid inside) and waits there, between the chunk's data and its marker, until ``release`` exists (at most
    ``limit`` seconds); then it gives up without writing the marker, as if its worker had died there."""
    import workers.relation_store as store

    original = store.marker

    def marker(result, seconds):
        if result.start == start:
            try:
                fd = os.open(flag, os.O_CREAT | os.O_EXCL | os.O_WRONLY)  # once, whichever worker gets there first
            except FileExistsError:
                return original(result, seconds)
            os.write(fd, str(os.getpid()).encode())
            os.close(fd)
            deadline = time.monotonic() + limit
            while not os.path.exists(release) and time.monotonic() < deadline:
                time.sleep(0.05)
            raise _Abandoned(f"chunk {start} abandoned between its data and its marker")
        return original(result, seconds)

    store._original_marker = getattr(store, "_original_marker", original)
    store.marker = marker


def _unpause() -> None:
    """On a worker: undo :func:`_pause_after_data`."""
    import workers.relation_store as store

    store.marker = getattr(store, "_original_marker", store.marker)
    store.__dict__.pop("_original_marker", None)


def test_runner_killed_between_chunk_data_and_marker(tmp_path, client, reference):
    """A chunk's data is in the store, its marker is not, and the runner dies: resuming recomputes that chunk.

    The chunk's task is held between its two writes while the runner is SIGKILLed, then abandoned without its
    marker (as its worker's death would leave it). The task is not stopped by killing its worker: that made the
    test wait for a worker restart, which on a loaded machine once never came (see ``LOST_WORKER_TIMEOUT`` in
    ``tests/conftest.py``); worker kills are this module's and test_workers.py's other tests."""
    spec = spec_of()
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(spec.model_dump_json())
    out, flag, release, k = tmp_path / "out", tmp_path / "paused", tmp_path / "release", 5
    code = ("import sys; from pipelines.spec.model import load_spec; from workers.job import Execution, abstract_job; "
            "abstract_job(load_spec(sys.argv[1]), sys.argv[2], Execution(scheduler=sys.argv[3]), audit=False)")
    client.run(_pause_after_data, str(flag), str(release), 4 * k, 300.0)
    proc = None
    log = tmp_path / "runner.log"
    try:
        with open(log, "wb") as log_file:
            proc = subprocess.Popen([sys.executable, "-c", code, str(spec_file), str(out), client.scheduler.address],
                                    cwd=ROOT, stdout=log_file, stderr=subprocess.STDOUT,
                                    env={**os.environ, **credentials_env(client)})  # the cluster's TLS credentials
        deadline = time.monotonic() + 120
        while not (flag.exists() and flag.read_text()):
            if proc.poll() is not None:
                raise AssertionError("the runner ended before chunk 5 was written:\n"
                                     + log.read_text(errors="replace")[-3000:])
            assert time.monotonic() < deadline, "chunk 5 was not written within 120 s"
            time.sleep(0.05)
        proc.kill()  # SIGKILL
        proc.wait(timeout=30)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
        release.touch()  # the held task gives up, its marker unwritten
        client.run(_unpause)
    wait_idle(client)
    (group,) = [name for name, _ in store_of(out).groups()]
    assert (out / "relations.zarr" / group / "lo" / "c" / str(k)).exists()  # the chunk's data were written ...
    done = store_of(out)[group]["done"][:].tolist()
    assert done[k] == ""  # ... its marker was not
    done_before = sum(1 for t in done if t)

    result, info = abstract_job(spec, out, execution=Execution(client=client), audit=False)
    assert info["chunks_computed"] == 9 - done_before and info["chunks_reused"] == done_before
    assert store_of(out)[group]["done"][k] != ""
    assert same_as_reference(result, reference)
    record("faults: runner SIGKILLed between a chunk's data and its marker", faults=1, identical=1, wrong=0)


# ------------------------------------------------------------------------------------------ full / read-only
@contextmanager
def small_filesystem(path: Path, size: str = "4m") -> Iterator[Path]:
    """A tmpfs of ``size`` at ``path`` (root only), unmounted afterwards."""
    path.mkdir(parents=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a small filesystem needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True, text=True)
    if r.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["mount", "-o", "remount,rw", str(path)], capture_output=True)
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _partial_job(spec, out: Path, client, chunks: int) -> int:
    """Run ``spec`` into ``out`` and stop it after ``chunks`` chunks; return the chunks marked done."""

    class Stop(Exception):
        pass

    def progress(stage, done, total, message):
        if stage == "subsystems" and done >= chunks:
            raise Stop

    with pytest.raises(Stop):
        abstract_job(spec, out, execution=Execution(client=client), audit=False, progress=progress)
    wait_idle(client)
    return marker_counts(out)[0]


def _fill(directory: Path) -> Path:
    """Write a file into ``directory`` until its filesystem is full."""
    filler = directory / "filler"
    block = b"\0" * (1 << 16)
    with open(filler, "wb") as fh:
        try:
            while True:
                fh.write(block)
                fh.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
    return filler


def _snapshot(out: Path) -> dict[str, bytes]:
    root = out / "relations.zarr"
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("fault", ["full", "read-only"])
def test_store_full_or_read_only_fails_cleanly_and_resumes(tmp_path, client, reference, fault):
    """A store that cannot be written mid-job: StoreError naming the store, nothing in it damaged; once it can
    be written again the job resumes to the identical relations."""
    spec = spec_of("tests.test_workers:slow_agent", chunk_cells=2)  # 17 chunks of ~0.2 s
    ref = run_abstraction(spec, audit=False)
    with small_filesystem(tmp_path / "mnt") as mnt:
        out = mnt / "job"
        done_before = _partial_job(spec, out, client, 4)
        assert 4 <= done_before < 17
        before = _snapshot(out)
        filler = mnt / "filler"
        try:
            if fault == "full":
                _fill(mnt)
            else:
                subprocess.run(["mount", "-o", "remount,ro", str(mnt)], check=True)
            with pytest.raises(StoreError) as err:
                abstract_job(spec, out, execution=Execution(client=client), audit=False)
            wait_idle(client)
        finally:
            if fault == "full":
                filler.unlink(missing_ok=True)
            else:
                subprocess.run(["mount", "-o", "remount,rw", str(mnt)], check=True)
        message = str(err.value)
        print(message)
        # A full disk is found by the store's next write; a read-only one already when the job claims its
        # directory, before any stage runs. Either way the message names the place and what to do.
        assert str(out) in message, message
        expected = "No space left on device" if fault == "full" else "Read-only file system"
        assert expected in message and ("run the job again" in message or "fix its permissions" in message), message
        after = _snapshot(out)
        # Intact: every file that was there is unchanged; chunks finished meanwhile are whole (marker last).
        assert {k: v for k, v in after.items() if k in before} == before
        assert marker_counts(out)[0] >= done_before
        result, info = abstract_job(spec, out, execution=Execution(client=client), audit=False)
        assert info["chunks_computed"] + info["chunks_reused"] == 17
        assert_same_relations(ref, result)
    record(f"faults: store {fault} mid-job", faults=1, failed_cleanly=1, identical=1, wrong=0)


# ================================================================================================ constants
def test_contradicted_constant_fails_on_the_cluster_too(tmp_path, client):
    spec = spec_of(sub={"lipschitz": {"x": 1.0, "w": 0.16}})
    with pytest.raises(LipschitzError) as err:
        run_job(spec, tmp_path, execution=Execution(client=client))
    message = str(err.value)
    assert "the given L_x = 1 is contradicted by the data" in message and "state cell" in message, message
    assert not (tmp_path / "controller.json").exists() and not (tmp_path / "report.json").exists()
    record("constants: contradicted L_x (cluster)", inputs=1, failed_cleanly=1, wrong=0)
