"""The ``workers`` case (c): the per-cell stage on one Dask worker against two.

:func:`workers.job.abstract_job` (the abstraction stages into a fresh job directory, audit off) on an embedded
cluster of 1 and of 2 workers, on ``examples/stress.yaml`` (``--quick``: the same spec with 16 samples per cell and
input spacing 1). Ratio = per-cell stage wall seconds with 1 worker / with 2 workers; with it the stage's CPU
seconds, the cores it kept busy and the CPU the machine's other processes used meanwhile.
"""

from __future__ import annotations

import tempfile
from typing import Any

from bench.harness import (
    EXAMPLES,
    Emit,
    Put,
    StageClock,
    baseline,
    baseline_lines,
    case_record,
    fmt,
    jsonable,
    limits,
    progress,
    ratio,
    run_child,
    with_samples,
)

#: Issue 6's target: two workers at least this much faster than one.
TARGET = 1.7


def child_workers(p: dict, emit: Emit) -> None:
    """(c) The per-cell stage on an embedded Dask cluster of ``p['workers']`` workers, fresh store."""
    from pipelines.spec.model import load_spec
    from workers.executors import Execution
    from workers.job import abstract_job

    spec = load_spec(p["spec"], p.get("set"))
    if p.get("samples"):
        spec = with_samples(spec, p["samples"], p.get("input_eta"))
    clock = StageClock(emit)
    with tempfile.TemporaryDirectory(prefix="compabs-bench-") as out:
        r, info = abstract_job(spec, out, execution=Execution(workers=p["workers"]), audit=False, progress=clock)
        clock.mark("other")  # cluster shutdown and the store's consolidation
    emit({"type": "info", "stage_seconds": r.report["stage_seconds"], "abstract_states": r.report["abstract_states"],
          "runner": jsonable({k: info.get(k) for k in ("workers", "chunks_total", "chunks_computed",
                                                        "task_compute_seconds")})})


CHILDREN = {"workers": child_workers}


def run(args: Any) -> dict:
    """One worker, then two, each in a child of its own."""
    spec = EXAMPLES / "stress.yaml"
    params: dict[str, Any] = {"spec": str(spec)}
    if args.quick:
        params.update(samples=16, input_eta=1.0)
    runs, children = {}, []
    for w in (1, 2):
        rec = case_record(f"workers={w}", run_child("workers", {**params, "workers": w}, *limits(args)), workers=w,
                          spec=spec.name)
        children.append(rec)
        runs[w] = rec
        progress(rec)
    t1 = runs[1]["stages"].get("subsystems", {}).get("wall")
    t2 = runs[2]["stages"].get("subsystems", {}).get("wall")
    c1 = runs[1]["stages"].get("subsystems", {}).get("cpu")
    c2 = runs[2]["stages"].get("subsystems", {}).get("cpu")
    return baseline("workers", children, ratio=ratio(t1, t2),
                    ratio_meaning="per-cell stage wall, 1 worker / 2 workers (target >= 1.7)",
                    one_worker_seconds=t1, two_workers_seconds=t2, one_worker_cpu=c1, two_workers_cpu=c2,
                    # CPU of the stage (runner, scheduler and workers): how much work a second worker adds, and
                    # the speed-up two otherwise idle cores would give if that work were the only limit.
                    cpu_overhead_two_workers=ratio(c2, c1),
                    cpu_bound_speedup=2 * c1 / c2 if c1 and c2 else None,
                    cpu_share={w: ratio(r["stages"].get("subsystems", {}).get("cpu"),
                                        r["stages"].get("subsystems", {}).get("wall")) for w, r in runs.items()},
                    others_cores={w: r["others_cores"] for w, r in runs.items()},
                    quick_spec=("stress.yaml with samples=16, input eta=1" if args.quick else None))


def lines(c: dict) -> list[str]:
    return baseline_lines("workers", c, [
        f"    per-cell stage wall: 1 worker {fmt(c['one_worker_seconds'])} s, 2 workers "
        f"{fmt(c['two_workers_seconds'])} s; CPU {fmt(c['one_worker_cpu'])} s vs {fmt(c['two_workers_cpu'])} s "
        f"(cores busy for the stage {', '.join(f'{k}w {fmt(v, 2)}' for k, v in c['cpu_share'].items())}; other "
        f"processes' busy cores {', '.join(f'{k}w {fmt(v, 2)}' for k, v in c['others_cores'].items())}); "
        f"CPU-bound speed-up 2 x cpu1/cpu2 = {fmt(c['cpu_bound_speedup'])}"])


def targets(c: dict, put: Put) -> None:
    v = c["ratio"]
    put("two workers / one", v, f">= {TARGET}", v is not None and v >= TARGET)
