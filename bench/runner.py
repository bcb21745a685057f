"""Benchmark of the distributed runner: per-cell stage time with 1 and 2 workers, and the per-task overhead.

    python bench/runner.py                 # the tank case (examples/tanks.yaml); or python -m bench.runner
    python bench/runner.py --stress 10     # samples x 10: tasks of default size (~2e6 evaluations)
    python bench/runner.py --overhead-only

Prints ratios, asserts nothing: the machine is shared and small; trust ratios, not absolute times.

* ``subsystems`` stage seconds in-process, with 1 worker and with 2 workers (embedded LocalCluster), and their
  ratios. The tank case's per-cell stage is ~0.05-0.2 s in-process, two tasks, so the cluster cannot help
  there; ``--stress K`` multiplies every subsystem's samples by K to give the stage real work.
* per-task overhead: one task at a time, round trip (submit -> task computes and writes chunk + marker ->
  result -> chunk read back from the store) minus the compute time the task measured itself; over tasks of
  one state cell (compute ~1-3 ms), median and 90th percentile. Also the compute time of one default-sized
  chunk, and the overhead as a fraction of it. And pipelined: a job of one-cell tasks on 2 workers,
  (stage seconds x workers - compute seconds) / tasks.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from pipelines.abstraction.cells import CellTask, abstract_cells
from pipelines.abstraction.relation import chunk_ranges
from pipelines.network import build_network
from pipelines.spec.model import JobSpec, load_spec
from workers.executors import Execution
from workers.job import run_abstraction

ROOT = Path(__file__).resolve().parents[1]


def stressed(spec: JobSpec, factor: int) -> JobSpec:
    """The spec with every subsystem's samples multiplied by ``factor`` (and no audit: not measured here)."""
    subs = [s.model_copy(update={"samples": min(100_000, s.samples * factor)}) for s in spec.subsystems]
    options = spec.options.model_copy(update={"audit_transitions": 0})
    return spec.model_copy(update={"subsystems": subs, "options": options})


def stage_seconds(spec: JobSpec, workers: int | None) -> tuple[float, dict]:
    """Seconds of the per-cell stage in-process (``workers=None``) or on an embedded cluster."""
    if workers is None:
        r = run_abstraction(spec, audit=False)
        return r.report["stage_seconds"]["subsystems"], {}
    from workers.job import abstract_job

    with tempfile.TemporaryDirectory() as out:
        r, info = abstract_job(spec, out, execution=Execution(workers=workers), audit=False)
    return r.report["stage_seconds"]["subsystems"], info


def task_overhead(spec: JobSpec, n_tasks: int = 40) -> dict[str, float]:
    """Round trip minus compute of single-cell tasks, one at a time, on a 2-worker cluster (seconds)."""
    from workers.cluster import connect
    from workers.jobdir import relations_url
    from workers.relation_store import RelationStore, group_name
    from workers.tasks import abstract_chunk

    network = build_network(spec, None)
    sub = max((m[0] for m in network.unique_subsystems().values()), key=lambda s: s.triples)
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
    n = min(n_tasks, sub.state_grid.size)
    with tempfile.TemporaryDirectory() as out, connect(workers=2) as (client, _):
        store = RelationStore.open(relations_url(out), spec, network)
        group = group_name(sub, L_x, L_w, sub.spec.growth_bound, sub.spec.scp_objective, 1)
        store.prepare(group, sub, [sub.name], 1, {})
        over, comp = [], []
        for i in range(n + 2):
            t0 = time.perf_counter()
            cell = i % sub.state_grid.size
            task = CellTask(sub, cell, cell + 1, L_x, L_w, sub.spec.growth_bound, sub.spec.scp_objective)
            fut = client.submit(abstract_chunk, store.url, group, task, pure=False)
            meta = fut.result()
            store.read(group, meta)
            dt = time.perf_counter() - t0
            if i >= 2:  # the first tasks of a worker import and open the store
                over.append(dt - meta["seconds"])
                comp.append(meta["seconds"])
        # One default-sized chunk of the same subsystem, computed here.
        a, b = chunk_ranges(sub, None)[0]
        t0 = time.perf_counter()
        abstract_cells(sub, a, b, L_x, L_w, sub.spec.growth_bound, sub.spec.scp_objective)
        default_task = time.perf_counter() - t0
    over.sort()
    # Throughput: many one-cell tasks on both workers at once; worker time not spent computing, per task.
    tiny = spec.model_copy(update={"options": spec.options.model_copy(update={"chunk_cells": 1})})
    with tempfile.TemporaryDirectory() as out:
        from workers.executors import Execution
        from workers.job import abstract_job

        r, info = abstract_job(tiny, out, execution=Execution(workers=2), audit=False)
    stage = r.report["stage_seconds"]["subsystems"]
    pipelined = (stage * info["workers"] - info["task_compute_seconds"]) / info["chunks_computed"]
    return {
        "pipelined": pipelined,
        "pipelined_tasks": info["chunks_computed"],
        "subsystem": sub.name,
        "median": statistics.median(over),
        "p90": over[int(0.9 * (len(over) - 1))],
        "single_cell_compute": statistics.median(comp),
        "default_chunk_cells": b - a,
        "default_chunk_evaluations": (b - a) * sub.input_grid.size * sub.n_w_cells * sub.spec.samples,
        "default_task_compute": default_task,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--spec", default=str(ROOT / "examples" / "tanks.yaml"))
    p.add_argument("--stress", type=int, default=1, metavar="K", help="multiply samples by K")
    p.add_argument("--overhead-only", action="store_true")
    args = p.parse_args(argv)
    spec = stressed(load_spec(args.spec), args.stress)

    if not args.overhead_only:
        t_in, _ = stage_seconds(spec, None)
        t_1, info1 = stage_seconds(spec, 1)
        t_2, info2 = stage_seconds(spec, 2)
        print(f"spec {spec.name}, samples x{args.stress}: {info2.get('chunks_total')} tasks")
        print(f"  subsystems stage  in-process {t_in:8.3f} s")
        print(f"  subsystems stage  1 worker   {t_1:8.3f} s   (1 worker / in-process  {t_1 / t_in:5.2f})")
        print(f"  subsystems stage  2 workers  {t_2:8.3f} s   (2 workers / 1 worker   {t_2 / t_1:5.2f}, speed-up {t_1 / t_2:4.2f})")
    o = task_overhead(spec)
    print(f"per-task overhead ({o['subsystem']}, one-cell tasks, one at a time): median {1e3 * o['median']:.1f} ms, "
          f"p90 {1e3 * o['p90']:.1f} ms (one-cell compute {1e3 * o['single_cell_compute']:.1f} ms)")
    print(f"per-task overhead, {o['pipelined_tasks']} one-cell tasks on 2 workers (worker time not computing, "
          f"per task): {1e3 * o['pipelined']:.1f} ms")
    print(f"default chunk: {o['default_chunk_cells']} cells, {o['default_chunk_evaluations']:.3g} evaluations, "
          f"compute {o['default_task_compute']:.3f} s -> overhead {100 * o['median'] / o['default_task_compute']:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
