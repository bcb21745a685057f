"""The distributed runner on a real 2-worker LocalCluster: identical relations, resume, faults, errors.

One cluster serves the whole module (starting one costs seconds). Fault tests use small.yaml with its dynamics
given as ``tests.test_workers:slow_agent``: the same map, but sleeping inside Dask workers, so that a kill
lands while tasks run; in this process (the in-process reference) it does not sleep.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np
import pytest
import yaml
import zarr

from pipelines.errors import BlackBoxError
from pipelines.spec.model import load_spec, parse_spec, spec_hash
from workers.cluster import connect, credentials_env
from workers.errors import ClusterError, StoreError, StoreMismatchError
from workers.executors import Execution
from workers.job import abstract_job, run_abstraction
from workers.jobdir import relations_url
from workers.relation_store import code_version, marker, result_from, write_chunk

from .conftest import EXAMPLES, ROOT, wait_idle

#: Seconds slow_agent sleeps per call inside a worker (two calls per chunk: samples and cell centres).
SLEEP = 0.1


def _in_worker() -> bool:
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


def slow_agent(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """small.yaml's agent dynamics, shapes (B, 1) -> (B, 1); sleeps inside Dask workers."""
    if x.shape[0] > 1 and _in_worker():
        time.sleep(SLEEP)
    return 32 / (1 + np.exp(-0.2 * (x + u + 0.1 * (x - w) - 16)))


def killer_agent(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Kills the worker process that evaluates it (a black box that crashes its interpreter)."""
    if x.shape[0] > 1 and _in_worker():
        os.kill(os.getpid(), signal.SIGKILL)
    return slow_agent(x, u, w)


# ----------------------------------------------------------------------------------------------- helpers
def small_spec(chunk_cells: int | None = 1, dynamics: str | None = "tests.test_workers:slow_agent", **sub):
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    if dynamics is not None:
        data["subsystems"][0]["dynamics"] = dynamics
    data["subsystems"][0].update(sub)
    data["options"] = {**data.get("options", {}), "chunk_cells": chunk_cells, "audit_transitions": 0}
    return parse_spec(data)


def assert_same_relations(a, b) -> None:
    assert a.relations.keys() == b.relations.keys()
    for key, ra in a.relations.items():
        rb = b.relations[key]
        for field in ("lo", "hi", "blocking"):
            x, y = getattr(ra, field), getattr(rb, field)
            assert x.dtype == y.dtype and x.shape == y.shape, (key, field)
            assert np.array_equal(x, y), (key, field)


def without_timings(report):
    if isinstance(report, dict):
        return {k: without_timings(v) for k, v in report.items() if k not in ("stage_seconds", "seconds", "runner")}
    if isinstance(report, list):
        return [without_timings(v) for v in report]
    return report


def store_of(out: Path):
    return zarr.open_group(str(out / "relations.zarr"), mode="r", use_consolidated=False)


def marker_counts(out: Path) -> tuple[int, int]:
    """(chunks marked done, chunks) over all groups of a store; (0, 0) before it exists."""
    try:
        root = store_of(out)
    except (FileNotFoundError, zarr.errors.BaseZarrError):
        return 0, 0
    done = total = 0
    for _, g in root.groups():
        if "done" not in g:
            continue
        d = g["done"][:]
        done += int(sum(1 for t in d.tolist() if t))
        total += d.size
    return done, total


# ----------------------------------------------------------------------------------------------- fixtures
# cluster and client (one cluster per module, checked whole and idle around every test), wait_idle: tests/conftest.py
@pytest.fixture(scope="module")
def small_reference():
    spec = small_spec()
    return spec, run_abstraction(spec, audit=False)


# ----------------------------------------------------------------------------------------------- store units
def test_marker_round_trip_is_exact():
    from pipelines.abstraction.cells import abstract_cells
    from pipelines.network import build_network

    spec = small_spec(dynamics=None)
    sub = build_network(spec, None).subsystems[0]
    r = abstract_cells(sub, 3, 5, 1.76, 0.16, "scp", "paper")
    back = result_from(json.loads(json.dumps(marker(r, 0.1))), r.lo, r.hi, r.blocking)
    assert (back.start, back.stop, back.successors) == (3, 5, r.successors)
    assert back.slope_x == r.slope_x and back.slope_w == r.slope_w  # floats exact through JSON


def test_group_left_half_created_is_made_again(tmp_path):
    import shutil

    from pipelines.network import build_network
    from workers.relation_store import RelationStore, group_name

    spec = small_spec(chunk_cells=4, dynamics=None)
    net = build_network(spec, None)
    sub = net.subsystems[0]
    store = RelationStore.open(relations_url(tmp_path), spec, net)
    group = group_name(sub, 1.76, 0.16, "scp", "paper", 4)
    store.prepare(group, sub, [sub.name], 4, {})
    shutil.rmtree(tmp_path / "relations.zarr" / group / "done")  # the runner died before creating it
    store.prepare(group, sub, [sub.name], 4, {})
    assert store.markers(group) == {} and store.groups() == [group]
    assert RelationStore.open(relations_url(tmp_path), spec, net).attrs()["grids"]["agent[0]"]["groups"] == [group]


def test_connect_to_nowhere_fails_clearly(monkeypatch, cluster):
    from workers import cluster as cluster_mod

    monkeypatch.setattr(cluster_mod, "CONNECT_TIMEOUT", 1.0)
    for var, value in credentials_env(cluster.client).items():
        monkeypatch.setenv(var, value)
    with pytest.raises(ClusterError, match="cannot reach the Dask scheduler at tls://127.0.0.1:9"):
        connect("tls://127.0.0.1:9")


def test_connect_from_environment(monkeypatch, cluster):
    monkeypatch.setenv("COMPABS_SCHEDULER", cluster.info["scheduler"])
    for var, value in credentials_env(cluster.client).items():  # the cluster's TLS credentials
        monkeypatch.setenv(var, value)
    with connect() as (client, info):
        assert info["scheduler"] == cluster.info["scheduler"] and not info["embedded"]
        assert info["workers"] == 2
    assert cluster.client.status == "running"  # closing a joined client leaves the cluster alone


def _announce_unknown_worker_removed(dask_scheduler) -> None:
    # What the scheduler sends when a worker dies while it registers: a 'remove' for a worker never added.
    dask_scheduler.plugins["worker-status"].bcomm.send(["remove", "tcp://127.0.0.1:9"])


def test_embedded_cluster_survives_the_removal_of_a_worker_it_never_saw(caplog):
    """A worker that dies while it registers is announced as removed without having been added; distributed's
    LocalCluster watcher would die on that (KeyError) and its close() would fail and leave the cluster half
    closed. The embedded cluster logs and skips it, and closes cleanly."""
    with caplog.at_level("WARNING", logger="workers.cluster"):
        conn = connect(workers=1)
        try:
            cluster = conn.client.cluster
            conn.client.run_on_scheduler(_announce_unknown_worker_removed)
            deadline = time.monotonic() + 30
            while "never announced" not in caplog.text:
                assert not cluster._watch_worker_status_task.done(), "the cluster's worker-status watcher died"
                assert time.monotonic() < deadline, "the scheduler's message never reached the cluster"
                time.sleep(0.05)
            assert conn.client.submit(sum, [1, 2]).result(timeout=30) == 3  # the cluster works on
        finally:
            conn.close()
    assert conn.client.status == "closed" and cluster.status.name == "closed"
    assert cluster.scheduler.status.name == "closed"


def _loaded_kernels() -> list[str]:
    import pipelines.abstraction.kernels as compiled

    return sorted(name for name in ("scalar_block", "scalar_sample_pass", "pair_maxima_batch_last",
                                    "scp_parameters_batch_last", "hull_and_bound")
                  if getattr(compiled, name).signatures)


def test_workers_load_the_compiled_kernels_when_they_connect():
    """A fresh worker has the per-cell kernels compiled (from numba's disk cache) before its first task: the
    first task of each worker no longer pays ~0.3 s of CPU for them."""
    with connect(workers=1) as (client, _):
        loaded = client.run(_loaded_kernels)
    assert list(loaded.values()) == [["hull_and_bound", "pair_maxima_batch_last", "scalar_block",
                                      "scalar_sample_pass", "scp_parameters_batch_last"]]


def _allocator_settings() -> dict[str, str | None]:
    import os

    return {k: os.environ.get(k) for k in ("MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_",
                                            "MALLOC_TOP_PAD_", "GLIBC_TUNABLES")}


def _huge_pages_of_a_malloc() -> tuple[int, int]:
    """This process's AnonHugePages (kB) before and after 64 MB from malloc are written (then freed): what CUDD's
    tables get (numpy asks the kernel for huge pages itself, so a numpy array would not tell)."""
    import ctypes

    def anon_huge_kb() -> int:
        with open("/proc/self/smaps_rollup") as f:
            return next((int(line.split()[1]) for line in f if line.startswith("AnonHugePages:")), 0)

    libc = ctypes.CDLL("libc.so.6")
    libc.malloc.restype = ctypes.c_void_p
    size = 64 << 20
    before = anon_huge_kb()
    block = libc.malloc(size)
    try:
        ctypes.memset(block, 1, size)
        return before, anon_huge_kb()
    finally:
        libc.free(ctypes.c_void_p(block))


def _transparent_huge_pages_offered() -> bool:
    """THP on for malloc's asking (``always`` or ``madvise``) and a glibc that asks (2.35 on: ``glibc.malloc.hugetlb``)."""
    import platform

    try:
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as f:
            mode = f.read()
    except OSError:
        return False
    lib, version = platform.libc_ver()
    major, minor = (int(v) for v in (version.split(".") + ["0"])[:2]) if lib == "glibc" and version else (0, 0)
    return "[never]" not in mode and (major, minor) >= (2, 35)


def test_embedded_workers_get_the_allocator_settings(client):
    """The worker processes run with workers/dask.yaml's environment (not Dask's MALLOC_TRIM_THRESHOLD_=65536),
    and a large temporary of a task comes from the heap, not from a fresh mmap (measured with the defaults:
    321 MB mmapped)."""
    from workers.cluster import DASK_CONFIG_FILE, worker_environ

    want = worker_environ()
    assert set(want) == {"MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                         "GLIBC_TUNABLES"}
    assert want["GLIBC_TUNABLES"] == "glibc.malloc.hugetlb=1"
    got = client.run(_allocator_settings)
    assert len(got) == 2 and all(env == want for env in got.values()), got
    if _transparent_huge_pages_offered():  # what malloc hands a task (CUDD's tables) comes in huge pages
        before, after = client.submit(_huge_pages_of_a_malloc, pure=False).result(timeout=120)
        assert after - before >= 32 * 1024, f"64 MB from malloc got {after - before} kB of huge pages"

    def mmapped_bytes_with_a_large_array() -> int:
        import ctypes

        import numpy as np

        class MallInfo2(ctypes.Structure):
            _fields_ = [(name, ctypes.c_size_t) for name in (
                "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                "keepcost")]

        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = MallInfo2
        a = np.ones(40_000_000)  # 320 MB: above glibc's default mmap threshold (at most 32 MB)
        held = libc.mallinfo2().hblkhd  # bytes in mmapped blocks
        del a
        return held

    # In the task thread, where the per-cell stage runs (its own arena by default, which cannot hold 320 MB).
    mmapped = client.submit(mmapped_bytes_with_a_large_array, pure=False).result(timeout=120)
    assert mmapped < 320_000_000, f"a 320 MB array was mmapped: {DASK_CONFIG_FILE} not in effect?"


def _periodic_ms(dask_worker=None, dask_scheduler=None) -> dict[str, float]:
    server = dask_worker if dask_worker is not None else dask_scheduler
    return {k: pc.callback_time for k, pc in server.periodic_callbacks.items() if k in ("tick", "monitor", "profile")}


def test_embedded_cluster_runs_dasks_periodic_work_as_the_config_says(client):
    """workers/dask.yaml's intervals (not Dask's 20 ms tick and 10 ms profiler) reach the scheduler and each
    worker process: they decide how much of two cores Dask's own periodic work takes from the tasks."""
    from dask.utils import parse_timedelta

    from workers.cluster import worker_config

    cfg = worker_config()
    tick = 1000 * parse_timedelta(cfg["distributed.admin.tick.interval"])
    monitor = 1000 * parse_timedelta(cfg["distributed.admin.system-monitor.interval"])
    profile = 1000 * parse_timedelta(cfg["distributed.worker.profile.interval"])
    assert tick >= 1000 and profile >= 100  # the measured settings, not Dask's 20 ms and 10 ms
    got = client.run(_periodic_ms)
    assert len(got) == 2 and all(v == {"tick": tick, "monitor": monitor, "profile": profile} for v in got.values()), got
    assert client.run_on_scheduler(_periodic_ms) == {"tick": tick, "monitor": monitor}


def _worker_ttl(dask_scheduler) -> float | None:
    return dask_scheduler.worker_ttl


def test_embedded_scheduler_waits_for_workers_that_hold_the_gil(client):
    """A worker running one CUDD operation sends no heartbeat until it returns (workers/dask_cpre.py's parts run
    for minutes on the tanks at 1.25): the scheduler must not declare it dead after Dask's 5 minutes."""
    ttl = client.run_on_scheduler(_worker_ttl)
    assert ttl is not None and ttl >= 3600, ttl


def test_image_installs_the_worker_config():
    from workers.cluster import DASK_CONFIG_FILE

    dockerfile = (Path(__file__).resolve().parents[1] / "Dockerfile").read_text()
    assert f"COPY workers/{DASK_CONFIG_FILE.name} /etc/dask/" in dockerfile


# ----------------------------------------------------------------------------------------------- equality
@pytest.mark.slow
def test_tanks_distributed_equals_in_process(tmp_path, client):
    spec = load_spec(EXAMPLES / "tanks.yaml")
    spec = spec.model_copy(update={"options": spec.options.model_copy(update={"audit_transitions": 100_000})})
    reference = run_abstraction(spec)
    events = []
    result, info = abstract_job(spec, tmp_path, execution=Execution(client=client), progress=lambda *e: events.append(e))

    assert_same_relations(reference, result)
    assert without_timings(result.report) == without_timings(reference.report)
    assert info["chunks_total"] == info["chunks_computed"] == 2 and info["chunks_reused"] == 0
    assert info["workers"] == 2 and info["scheduler"].startswith("tls://")
    sub_events = [e for e in events if e[0] == "subsystems"]
    assert [e[1] for e in sub_events] == [1, 2] and all(e[2] == 2 for e in sub_events)

    # The store: root attributes, one group per distinct subsystem, codec and chunking, consolidated metadata.
    root = zarr.open_group(str(tmp_path / "relations.zarr"), mode="r")
    assert root.metadata.consolidated_metadata is not None
    assert root.attrs["spec_hash"] == spec_hash(spec)
    assert root.attrs["code_version"] == code_version()
    assert set(root.attrs["grids"]) == {f"tank{i}" for i in range(1, 11)}
    groups = dict(root.groups())
    assert len(groups) == 2
    for name, g in groups.items():
        key = g.attrs["key"]
        assert name.startswith(key)
        rel = result.relations[key]
        assert g["lo"].shape == rel.lo.shape and g["lo"].dtype == np.int32 and g["blocking"].dtype == bool
        assert g["lo"].chunks[0] == g.attrs["chunk_cells"] == rel.lo.shape[0]
        codec = g["lo"].compressors[0]
        assert type(codec).__name__ == "BloscCodec" and codec.cname.value == "zstd" and codec.shuffle.value == "bitshuffle"
        assert (g.attrs["L_x"], g.attrs["L_w"]) == (0.98, 0.49)

    # Same job again: everything is read back, nothing computed.
    again, info2 = abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    assert info2["chunks_reused"] == 2 and info2["chunks_computed"] == 0
    assert_same_relations(reference, again)


# ----------------------------------------------------------------------------------------------- faults
@pytest.mark.slow
def test_worker_killed_mid_job(tmp_path, client, small_reference):
    spec, reference = small_reference
    pids = client.run(os.getpid)
    victim = sorted(pids.values())[0]
    killed = []

    def progress(stage, done, total, message):
        if stage == "subsystems" and done == 5 and not killed:
            os.kill(victim, signal.SIGKILL)  # both workers are busy: 28 chunks still queued
            killed.append(done)

    result, info = abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False, progress=progress)
    assert killed
    assert_same_relations(reference, result)
    assert info["chunks_computed"] == info["chunks_total"] == 33
    assert marker_counts(tmp_path) == (33, 33)
    client.wait_for_workers(2, timeout=240)
    assert victim not in client.run(os.getpid).values()  # the nanny started a new worker process


@pytest.mark.slow
def test_runner_killed_mid_job_resumes(tmp_path, client, small_reference):
    spec, reference = small_reference
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(spec.model_dump_json())
    code = (
        "import sys; from pipelines.spec.model import load_spec; from workers.job import Execution, abstract_job; "
        "abstract_job(load_spec(sys.argv[1]), sys.argv[2], Execution(scheduler=sys.argv[3]), audit=False)"
    )
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(spec_file), str(out), client.scheduler.address],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, **credentials_env(client)},
    )
    try:
        deadline = time.monotonic() + 60
        while marker_counts(out)[0] < 6:
            assert proc.poll() is None, "the runner ended before it could be killed"
            assert time.monotonic() < deadline, "no chunk done within 60 s"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    # Tasks that were running when the runner died still finish (and mark their chunks): wait for them.
    wait_idle(client)
    done_before, total = marker_counts(out)
    assert total == 33 and 6 <= done_before < total

    result, info = abstract_job(spec, out, execution=Execution(client=client), audit=False)
    assert info["chunks_computed"] == total - done_before
    assert info["chunks_reused"] == done_before
    assert_same_relations(reference, result)
    assert marker_counts(out) == (33, 33)


def test_missing_marker_recomputes_that_chunk(tmp_path, client):
    spec = small_spec(chunk_cells=4, dynamics=None)
    first, info = abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    assert info["chunks_computed"] == 9
    (group,) = [name for name, _ in store_of(tmp_path).groups()]
    # Data written, marker not: what a task killed between its two writes leaves behind.
    marker_file = tmp_path / "relations.zarr" / group / "done" / "c" / "3"
    assert marker_file.exists() and (tmp_path / "relations.zarr" / group / "lo" / "c" / "3").exists()
    marker_file.unlink()
    (marker_file.parent / "4.0123abcd.partial").write_text("{")  # a killed writer's temporary: ignored
    again, info = abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    assert (info["chunks_computed"], info["chunks_reused"]) == (1, 8)
    assert_same_relations(first, again)
    assert marker_file.exists()


def test_changed_spec_is_refused_then_overwritten(tmp_path, client):
    spec = small_spec(chunk_cells=8, dynamics=None)
    abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    changed = small_spec(chunk_cells=8, dynamics=None, samples=90)
    with pytest.raises(StoreMismatchError, match="another job") as err:
        abstract_job(changed, tmp_path, execution=Execution(client=client), audit=False)
    assert "--overwrite" in str(err.value) and spec_hash(changed) in str(err.value)
    assert marker_counts(tmp_path) == (5, 5)  # refused: nothing deleted

    result, info = abstract_job(changed, tmp_path, execution=Execution(client=client), audit=False, overwrite=True)
    assert info["chunks_reused"] == 0 and info["chunks_computed"] == info["chunks_total"] == 5
    assert store_of(tmp_path).attrs["spec_hash"] == spec_hash(changed)
    assert_same_relations(run_abstraction(changed, audit=False), result)


def test_raised_lipschitz_constant_gets_its_own_group(tmp_path, client):
    # L_x = 1.0 is below the data's slope: the stage runs twice, the second time with the raised constant.
    spec = small_spec(chunk_cells=8, dynamics=None, lipschitz={"x": 1.0, "w": 0.16, "on_violation": "raise"})
    reference = run_abstraction(spec, audit=False)
    result, info = abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    assert_same_relations(reference, result)
    assert without_timings(result.report) == without_timings(reference.report)
    assert reference.report["subsystems"][0]["lipschitz"]["x"]["source"] == "raised"
    groups = dict(store_of(tmp_path).groups())
    assert len(groups) == 2 and sorted(g.attrs["L_x"] for g in groups.values())[0] == 1.0
    assert info["chunks_computed"] == info["chunks_total"] == 10
    again, info = abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    assert (info["chunks_reused"], info["chunks_computed"]) == (10, 0)
    assert_same_relations(reference, again)


def test_not_a_store_is_refused(tmp_path, client):
    (tmp_path / "relations.zarr").mkdir()
    (tmp_path / "relations.zarr" / "notes.txt").write_text("mine")
    with pytest.raises(StoreMismatchError, match="not a compabs relation store"):
        abstract_job(small_spec(dynamics=None), tmp_path, execution=Execution(client=client), audit=False)
    assert (tmp_path / "relations.zarr" / "notes.txt").exists()


# ----------------------------------------------------------------------------------------------- errors
def test_black_box_error_surfaces_unchanged(tmp_path, client):
    spec = small_spec(chunk_cells=4, dynamics="sqrt(x[0] - 16)")  # NaN below x = 16
    with pytest.raises(BlackBoxError) as err:
        abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    message = str(err.value)
    assert "subsystem 'agent[0]' dynamics" in message and "not finite" in message and "state cell" in message
    text = "".join(traceback.format_exception(err.value))
    assert "distributed" not in text and "During handling" not in text
    with pytest.raises(BlackBoxError) as in_process:
        run_abstraction(small_spec(chunk_cells=4, dynamics="sqrt(x[0] - 16)"), audit=False)
    assert type(in_process.value) is type(err.value)
    wait_idle(client)  # cancelled tasks leave nothing running


@pytest.mark.slow
def test_task_that_kills_its_workers_is_a_clear_error(tmp_path, client):
    spec = small_spec(chunk_cells=33, dynamics="tests.test_workers:killer_agent")
    with pytest.raises(ClusterError, match=r"subsystem 'agent\[0\], agent\[1\]', chunk 0 \(state cells 0\.\.32\).*KilledWorker"):
        abstract_job(spec, tmp_path, execution=Execution(client=client), audit=False)
    assert marker_counts(tmp_path) == (0, 1)


def test_store_write_outside_a_chunk_is_refused(tmp_path, client):
    from pipelines.abstraction.cells import abstract_cells
    from pipelines.network import build_network
    from workers.relation_store import RelationStore, group_name

    spec = small_spec(chunk_cells=4, dynamics=None)
    net = build_network(spec, None)
    sub = net.subsystems[0]
    store = RelationStore.open(relations_url(tmp_path), spec, net)
    group = group_name(sub, 1.76, 0.16, "scp", "paper", 4)
    store.prepare(group, sub, [sub.name], 4, {})
    with pytest.raises(StoreError, match="not one chunk"):
        write_chunk(store.url, group, abstract_cells(sub, 2, 6, 1.76, 0.16, "scp", "paper"), 0.0)
    assert store.markers(group) == {}


def test_small_jobs_run_in_process_unless_told_otherwise():
    """``in_process=None`` (the CLI's default): a small job skips the embedded cluster, a large one or one given a
    cluster does not, and an explicit choice is kept."""
    from pipelines.network import build_network
    from pipelines.spec.model import load_spec
    from workers.job import runs_in_process

    small = build_network(load_spec(EXAMPLES / "small.yaml"))
    large = build_network(load_spec(EXAMPLES / "consensus.yaml"))
    auto = Execution(in_process=None)
    assert runs_in_process(small, auto) and not runs_in_process(large, auto)
    assert not runs_in_process(small, Execution(scheduler="tls://127.0.0.1:8786", in_process=None))
    assert not runs_in_process(small, Execution(client=object(), in_process=None))
    assert not runs_in_process(small, Execution()) and runs_in_process(large, Execution(in_process=True))


def test_threads_in_process_give_the_same_relations_and_errors(tmp_path):
    """In this process on two threads (the chunks finish in any order) through the store: the same bits as one
    thread in memory, and a black box's NaN is the same error."""
    data = yaml.safe_load((EXAMPLES / "dcdc.yaml").read_text())
    data["subsystems"][0]["state"]["eta"] = 0.005  # 81 x 81 cells
    data["options"] = {"chunk_cells": 500, "audit_transitions": 0}  # 14 chunks
    spec = parse_spec(data)
    reference = run_abstraction(spec, audit=False)
    result, info = abstract_job(spec, tmp_path / "job", execution=Execution(in_process=True, workers=2), audit=False)
    assert info["threads"] == 2 and info["chunks_computed"] == info["chunks_total"] == 14
    assert_same_relations(reference, result)
    assert without_timings(result.report) == without_timings(reference.report)

    nan = small_spec(chunk_cells=4, dynamics="sqrt(x[0] - 16)")  # NaN below x = 16, in several chunks
    with pytest.raises(BlackBoxError) as threaded:
        abstract_job(nan, tmp_path / "nan", execution=Execution(in_process=True, workers=2), audit=False)
    with pytest.raises(BlackBoxError) as alone:
        run_abstraction(nan, audit=False)
    assert "not finite" in str(threaded.value) and type(threaded.value) is type(alone.value)
