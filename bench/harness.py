"""What every case shares: measuring a child process, the records it leaves, and the table's formatting.

**Measurement.** Every case (every N, every worker count) runs in a fresh child process (:func:`run_child`:
``python -m bench --child KIND`` in the repository root), whose events are written to a JSON-lines file as they
happen, so a case killed at its timeout still reports the stages it finished. Per stage: wall seconds (the
pipeline's ``report["stage_seconds"]`` where it reports the stage, else this harness's :class:`StageClock`) and CPU
seconds (:func:`tree_cpu`: the child's ``time.process_time`` plus the CPU of its descendants, e.g. Dask workers).
Peak memory: the larger of the child's own peak RSS (``getrusage``, exact) and the polled (:data:`POLL_SECONDS`)
peak of the summed RSS of its process tree. The machine may be small and shared: absolute seconds are noisy,
ratios measured in the same run are what to read; the CPU that other processes used during each child is reported
(``others_cores``: their average number of busy cores). Single-process comparisons (floor, scp, bdd) use CPU
seconds, the worker comparison wall seconds.

**Records.** :func:`case_record` turns a child's events into the fields every case reports (the ones
``tests/test_bench.py`` checks); :func:`baseline` groups the children of a baseline case under its ratio.

**Reporting.** :func:`fmt` formats a figure for the table, :func:`progress` prints a case's one-line progress to
stderr, :func:`jsonable` cuts a report down to what the JSON output keeps.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
STAGE_ORDER = ("startup", "plan", "lipschitz", "subsystems", "interconnection", "audit", "composition",
               "synthesis", "closed_loop", "other")

Emit = Callable[[dict], None]
"""How a child case reports: one JSON-able event at a time (``type``: ``stage``, ``info``, ``row``, ``error``,
``done``)."""
Child = Callable[[dict, Emit], None]
"""A child case: its parameters (JSON) and where to emit its events."""
Put = Callable[[str, Any, str, bool], None]
"""How a case states a target: ``put(name, measured, target, met)``."""


# ====================================================================================== measurement (child side)
def tree_cpu() -> float:
    """CPU seconds of this process plus those of its descendants (Dask workers, synthesis helpers, ...).

    Descendants that have exited and were reaped count exactly (``RUSAGE_CHILDREN``: helpers that start and
    stop between two calls included); live ones with their CPU so far. A descendant reaped by another
    descendant that is still alive is missed until that one is reaped too.
    """
    live = 0.0
    try:
        import psutil

        for c in psutil.Process().children(recursive=True):
            try:
                t = c.cpu_times()
                live += t.user + t.system
            except psutil.Error:
                pass
    except ImportError:  # pragma: no cover - psutil is a test dependency
        pass
    reaped = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + reaped.ru_utime + reaped.ru_stime + live


def self_peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class StageClock:
    """A ``progress`` callback that times stages by their completion events.

    A stage is complete at its first event with ``done >= total``; it is charged the wall and CPU time since the
    previous completion (the first event of the run closes a ``startup`` segment). ``mark(name)`` closes a
    segment by hand. Each closed segment is emitted at once (so a killed child has reported it).

    Only events from the thread that made the clock count: an audit beside synthesis reports from its relay
    thread, and its segments would both race this thread's (a negative wall) and steal the time of the stage
    running meanwhile. Such a stage is charged where the main thread waits for it (``JobSession.finish_audit``).
    """

    def __init__(self, emit: Emit) -> None:
        self.emit = emit
        self.thread = threading.get_ident()
        self.last = (time.perf_counter(), tree_cpu())
        self.started = False
        self.closed: set[str] = set()
        self.stages: dict[str, dict[str, float]] = {}
        self.segments: list[tuple[str, float, float]] = []

    def mark(self, stage: str) -> None:
        now = (time.perf_counter(), tree_cpu())
        wall, cpu = now[0] - self.last[0], now[1] - self.last[1]
        self.last = now
        self.started = True
        self._charge(stage, wall, cpu)

    def move(self, wall: float, source: str, target: str) -> None:
        """Move the first ``wall`` seconds of the last segment charged to ``source`` to ``target`` (its CPU in
        proportion): for a segment that ended at one event but held two things the events do not separate."""
        last = next((s for s in reversed(self.segments) if s[0] == source), None)
        if last is None or last[1] <= 0 or wall <= 0:
            return
        wall = min(wall, last[1])
        cpu = last[2] * wall / last[1]
        self._charge(source, -wall, -cpu)
        self._charge(target, wall, cpu)

    def _charge(self, stage: str, wall: float, cpu: float) -> None:
        s = self.stages.setdefault(stage, {"wall": 0.0, "cpu": 0.0})
        s["wall"] += wall
        s["cpu"] += cpu
        self.segments.append((stage, wall, cpu))
        self.emit({"type": "stage", "stage": stage, "wall": wall, "cpu": cpu, "self_peak_mb": self_peak_mb()})

    def __call__(self, stage: str, done: int, total: int, message: str = "") -> None:
        if threading.get_ident() != self.thread:
            return
        if not self.started:
            self.mark("startup")
        if done >= total and stage not in self.closed:
            self.closed.add(stage)
            self.mark(stage)


def jsonable(obj: Any, depth: int = 0) -> Any:
    """Numbers, strings and small containers only (reports carry arrays and BDD sizes per layer). Deep enough for
    ``synthesis.results.<name>.local_games.groups`` (the lists of each group's subsystems)."""
    if isinstance(obj, (bool, int, float, str)) or obj is None:
        return obj
    if depth > 8:
        return None
    if isinstance(obj, dict):
        return {str(k): jsonable(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)) and len(obj) <= 32:
        return [jsonable(v, depth + 1) for v in obj]
    try:
        return float(obj)
    except (TypeError, ValueError):
        return None


def child_main(kind: str, params: str, events: str, children: Mapping[str, Child]) -> int:
    """Run the child case ``kind`` (one of ``children``) with its JSON ``params``, its events appended to the file
    ``events``; an exception is reported as an ``error`` event (the parent decides what it means)."""
    with open(events, "a", buffering=1) as fh:
        def emit(rec: dict) -> None:
            fh.write(json.dumps(rec, default=jsonable) + "\n")

        t0, c0 = time.perf_counter(), time.process_time()
        try:
            children[kind](json.loads(params), emit)
        except BaseException as exc:  # reported to the parent, which decides
            emit({"type": "error", "error": f"{type(exc).__name__}: {exc}",
                  "traceback": traceback.format_exc(limit=12)[-4000:]})
            return 1
        emit({"type": "done", "wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
              "self_peak_mb": self_peak_mb()})
    return 0


# ====================================================================================== what the cases measure on
def with_samples(spec: Any, samples: int, input_eta: float | None = None) -> Any:
    """The spec with every subsystem's samples (and optionally input spacing) replaced: smaller quick runs."""
    subs = []
    for s in spec.subsystems:
        upd: dict[str, Any] = {"samples": samples}
        if input_eta is not None:
            upd["input"] = s.input.model_copy(update={"eta": input_eta})
        subs.append(s.model_copy(update=upd))
    return spec.model_copy(update={"subsystems": subs})


def given_constants(sub: Any) -> tuple[float, float]:
    """A subsystem's Lipschitz constants ``(L_x, L_w)`` as its spec gives them (``L_w`` 0 without internal input)."""
    lip = sub.spec.lipschitz
    if lip.x == "estimate" or lip.w == "estimate":
        raise ValueError(f"{sub.name}: the benchmark needs given Lipschitz constants")
    return float(lip.x), float(lip.w) if sub.internal_grid is not None else 0.0


class Recorder:
    """Wraps a black box; keeps the arrays and results of its sample calls (``abstract_cells`` evaluates a chunk's
    samples in one call per block of triples, in order, and the cells' centres in calls of their own)."""

    def __init__(self, box: Any) -> None:
        self.box = box
        self.calls: list[tuple[tuple, Any]] = []

    def __call__(self, *arrays: Any, describe: Any = None) -> Any:
        out = self.box(*arrays, describe=describe)
        if getattr(describe, "__name__", "") == "where_sample":
            self.calls.append((arrays, out))
        return out


# ====================================================================================== running children (parent)
def _busy_cpu() -> float:
    import psutil

    t = psutil.cpu_times()
    return sum(getattr(t, f, 0.0) for f in ("user", "nice", "system", "irq", "softirq", "steal"))


POLL_SECONDS = 0.1
"""Seconds between two reads of the child tree's memory and CPU (its peak RSS is the largest sum seen)."""

TREE_LIST_SECONDS = 1.0
"""Seconds between two listings of the child's descendants. Listing them reads every process's ``/proc`` entry
(~1 ms of CPU, 1 % of a core at every poll); the measured processes keep the cores busy, so the harness lists
them once a second and reads only the known ones in between. A descendant that lives less than a second may be
missed in the peak RSS (none of the cases starts one that matters: Dask workers and synthesis helpers live for
their stage)."""


def run_child(kind: str, params: dict, timeout: float, mem_limit_mb: float, env: dict[str, str] | None = None) -> dict:
    """Run one child case in a fresh process (own session); poll its process tree; collect its events.

    ``env``: variables added to this process's environment for the child (e.g. the workers' malloc settings).

    Returns a record: ``status`` (ok | error | timeout | memory), ``error``, ``events``, ``wall`` (process
    lifetime), ``cpu`` (the tree's CPU), ``peak_rss_mb``, ``others_cores`` (average busy cores of other processes).
    """
    import psutil

    with tempfile.NamedTemporaryFile("w", suffix=".jsonl", prefix="compabs-bench-", delete=False) as fh:
        events_path = fh.name
    cmd = [sys.executable, "-m", "bench", "--child", kind, "--params", json.dumps(params), "--events", events_path]
    busy0, t0 = _busy_cpu(), time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=str(ROOT), start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **env} if env else None)
    stderr_lines: list[str] = []
    reader = threading.Thread(target=lambda: stderr_lines.extend(proc.stderr or ()), daemon=True)
    reader.start()
    status, peak_tree, cpu_seen = "ok", 0.0, {}
    root = psutil.Process(proc.pid)
    tree: list = [root]
    listed = -TREE_LIST_SECONDS
    while True:
        try:
            pid, wstatus, ru = os.wait4(proc.pid, os.WNOHANG)
        except ChildProcessError:  # pragma: no cover
            pid, wstatus, ru = proc.pid, 0, None
        if pid == proc.pid:
            break
        rss = 0
        try:
            if time.perf_counter() - listed >= TREE_LIST_SECONDS:
                tree, listed = [root] + root.children(recursive=True), time.perf_counter()
            for q in tree:
                try:
                    rss += q.memory_info().rss
                    t = q.cpu_times()
                    cpu_seen[q.pid] = t.user + t.system
                except psutil.Error:
                    pass
        except psutil.Error:
            pass
        peak_tree = max(peak_tree, rss / 2**20)
        elapsed = time.perf_counter() - t0
        if elapsed > timeout or peak_tree > mem_limit_mb:
            status = "timeout" if elapsed > timeout else "memory"
            kill_group(proc.pid)
            pid, wstatus, ru = os.wait4(proc.pid, 0)
            break
        time.sleep(POLL_SECONDS)
    proc.returncode = os.waitstatus_to_exitcode(wstatus) if ru is not None else None
    wall = time.perf_counter() - t0
    busy = _busy_cpu() - busy0
    kill_group(proc.pid)  # leftovers of the session (a worker that outlived its parent)
    reader.join(timeout=5)
    events = []
    with open(events_path) as fh:
        for line in fh:
            try:
                events.append(json.loads(line))
            except json.JSONDecodeError:  # a line cut by a kill
                pass
    os.unlink(events_path)
    rusage_cpu = (ru.ru_utime + ru.ru_stime) if ru is not None else 0.0
    cpu = max(rusage_cpu, sum(cpu_seen.values()))
    error = next((e["error"] for e in events if e["type"] == "error"), None)
    if status == "ok" and (error or proc.returncode):
        status = "error"
        error = error or f"exit status {proc.returncode}: {''.join(stderr_lines)[-2000:]}"
    if status == "timeout":
        error = f"did not finish within {timeout:.0f} s"
    elif status == "memory":
        error = f"process tree exceeded {mem_limit_mb:.0f} MB RSS"
    peak_self = (ru.ru_maxrss / 1024.0) if ru is not None else 0.0
    return {"status": status, "error": error, "events": events, "wall": wall, "cpu": cpu,
            "peak_rss_mb": max(peak_self, peak_tree), "others_cores": max(0.0, (busy - cpu) / wall) if wall else 0.0,
            "traceback": next((e.get("traceback") for e in events if e["type"] == "error"), None)}


def kill_group(pid: int) -> None:
    """SIGKILL the session a child leads (the child and everything it started)."""
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def limits(args: Any) -> tuple[float, float]:
    """``(timeout, memory limit in MB)`` of a child that is one point or one baseline run."""
    return args.point_timeout, args.mem_limit_gb * 1024


# ====================================================================================== records
def stages_of(child: dict) -> dict[str, dict[str, float]]:
    """Per-stage wall and CPU: the pipeline's own stage seconds where it reports them, the harness clock else."""
    stages: dict[str, dict[str, float]] = {}
    for e in child["events"]:
        if e["type"] == "stage":
            s = stages.setdefault(e["stage"], {"wall": 0.0, "cpu": 0.0})
            s["wall"] += e["wall"]
            s["cpu"] += e["cpu"]
    for e in child["events"]:
        if e["type"] == "info":
            for k, v in (e.get("stage_seconds") or {}).items():
                if k in stages:
                    stages[k]["wall"] = v
    if not stages:  # a baseline child: one segment, the whole case function
        for e in child["events"]:
            if e["type"] == "done":
                stages["run"] = {"wall": e["wall"], "cpu": e["cpu"]}
    return {k: stages[k] for k in sorted(stages, key=lambda k: STAGE_ORDER.index(k) if k in STAGE_ORDER else 99)}


def info_of(child: dict) -> dict:
    """The child's ``info`` events merged (later ones win), without their stage seconds."""
    out: dict[str, Any] = {}
    for e in child["events"]:
        if e["type"] == "info":
            out.update({k: v for k, v in e.items() if k not in ("type", "stage_seconds")})
    return out


def case_record(name: str, child: dict, **extra: Any) -> dict:
    """The common fields of a case."""
    stages = stages_of(child)
    info = info_of(child)
    return {
        "case": name,
        "status": child["status"],
        "error": child["error"],
        "stages": stages,
        "total_wall": sum(s["wall"] for s in stages.values()),
        "total_cpu": sum(s["cpu"] for s in stages.values()),
        "process_wall": child["wall"],
        "process_cpu": child["cpu"],
        "peak_rss_mb": child["peak_rss_mb"],
        "others_cores": child["others_cores"],
        "abstract_states": info.get("abstract_states"),
        "domain_states": info.get("domain_states"),
        "paper": None,
        "vs_paper": {},
        "details": {k: v for k, v in info.items() if k not in ("abstract_states", "domain_states")},
        **extra,
    }


def baseline(name: str, children: list[dict], **fields: Any) -> dict:
    """A baseline case: its child runs, its ratio (``fields['ratio']``; none measured is an error) and details."""
    bad = [c for c in children if c["status"] != "ok"]
    return {
        "case": name,
        "status": "ok" if not bad and fields.get("ratio") is not None else "error",
        "error": "; ".join(f"{c['case']}: {c['error']}" for c in bad) or None,
        "runs": children,
        "peak_rss_mb": max((c["peak_rss_mb"] for c in children), default=None),
        **{"others_cores": max((c["others_cores"] for c in children), default=None), **fields},
    }


def ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b not in (None, 0) else None


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ``ys`` against ``xs``."""
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx


# ====================================================================================== reporting
def fmt(v: Any, digits: int = 3) -> str:
    """A figure for the table: ``-`` for none, yes/no, large counts in exponent form, floats to ``digits``."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int) and abs(v) >= 10**7:
        return f"{v:.3e}" if v < 1e300 else f"1e{len(str(v)) - 1}"
    if isinstance(v, float):
        if v != 0 and (abs(v) >= 1e6 or abs(v) < 1e-3):
            return f"{v:.2e}"
        return f"{v:.{digits}g}"
    return str(v)


def stage_line(stages: dict) -> str:
    return "  ".join(f"{k} {s['wall']:.2f}/{s['cpu']:.2f}" for k, s in stages.items())


def baseline_lines(name: str, c: dict, rows: list[str]) -> list[str]:
    """A baseline's lines in the table: its ratio and what it means, its rows, its error if any."""
    out = [f"  {name}: ratio {fmt(c.get('ratio'))}  ({c.get('ratio_meaning')})", *rows]
    if c.get("error"):
        out.append(f"    error: {c['error'][:300]}")
    return out


def progress(rec: dict) -> None:
    """One line on stderr: a case (or a point of one) finished."""
    print(f"  .. {rec['case']}: {rec['status']} in {rec.get('process_wall', 0):.1f} s"
          + (f" ({rec['error'][:200]})" if rec.get("error") else ""), file=sys.stderr, flush=True)


def baseline_progress(rec: dict) -> None:
    """:func:`progress` for a case of several child runs: their summed lifetime."""
    progress({**rec, "process_wall": sum(r["process_wall"] for r in rec["runs"])})
