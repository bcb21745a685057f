"""The ``synthesis`` case (issue 24; only when named, never under ``--quick``): the consensus fixed point on the job's
Dask workers.

Consensus (``examples/consensus.yaml``, shared ``w``, Reach(Safe)) is abstracted once in this process, then its
synthesis runs in every mode on the same abstraction: in one process (the baseline), in helper processes of this
machine (:mod:`workers.processes.partitioned_cpre`), and on an embedded Dask cluster of 1, 2, 4, ... workers up to
the cores present (:mod:`workers.dask_cpre`), and on oxidd's threads in this process, one and one per core, from
the first call whatever N (:mod:`pipelines.synthesis.engine_cpre`; ``--no-oxidd`` leaves them out). Each row gives
the wall seconds, the speed-up over one process, the parts' summed seconds of the largest call against that call in
one process (what cutting costs), and whether the domain is the one process's (it must be: every mode is exact).

    python bench/synthesis.py [--N 8] [--workers 1,2] [--per-worker 1[,2,...]] [--no-symmetry] [--compare-cuts P]
                              [--rounds R] [--json OUT]          # or: python -m bench.synthesis ...

``bench/run.py --cases synthesis`` runs it (:func:`run`) in a child process with ``--no-symmetry --compare-cuts 8``,
``--N`` from ``--synthesis-N`` (default 8) and ``--rounds`` from ``--synthesis-rounds`` (default 2).

``--per-worker 1,2,3`` runs each cluster once per value: the parts of a call handed out as workers free up
(:mod:`workers.dispatch`), more parts per worker evening out unequal parts at the cost of the sub-results they share.

``--no-symmetry`` adds one process and the largest cluster without the symmetry of the interchangeable agents
(:mod:`pipelines.synthesis.symmetry`): what it buys in each. ``--compare-cuts P`` adds the largest cluster with
``P`` parts per worker, cut in windows and by the split cut (:mod:`workers.dask_cpre`), and prints the parts'
summed seconds of each: what the split cut buys where there are many parts.

The script runs under the workers' allocator settings (``workers/dask.yaml``'s ``pre-spawn-environ``, huge pages
among them), starting itself again under them if need be: its one process is the baseline.

``--rounds R`` runs one process and each cluster ``R`` times, alternating (one process, the clusters, one process,
...), each round's speed-ups against that round's one process; a target is judged on the median of the rounds'
speed-ups. On a shared 2-core machine the same code's two workers vary by several per cent between runs minutes
apart (consensus N = 8), and so does one round's ratio; the extras (helper processes, ``--no-symmetry``,
``--compare-cuts``, more parts per worker than the first round's best) run in the first round only.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from service.arguments import count  # the CLI's own integer type

ROOT = Path(__file__).resolve().parent.parent

#: Issue 24's targets: 2 workers against one process on a 2-core machine; 16 workers on a 16-core one.
TARGETS = {2: 1.8, 16: 8.0}
#: Issue 49's: oxidd on the machine's cores against the fastest CUDD mode before it, two Dask workers.
ENGINE_TARGET = 2.0


def default_workers(cores: int) -> list[int]:
    """1, 2, 4, ... up to the cores present (and the cores themselves)."""
    out, k = [], 1
    while k <= cores:
        out.append(k)
        k *= 2
    if out[-1] != cores:
        out.append(cores)
    return out


def speedups(rec: dict[str, Any], k: int) -> list[float]:
    """Each round's speed-up of ``k`` workers over that round's one process (the best parts per worker), in round
    order (rows without a round are the first)."""
    best: dict[int, float] = {}
    for r in rec["rows"]:
        if r.get("workers") == k and r.get("speedup") is not None:
            rnd = r.get("round", 0)
            best[rnd] = max(best.get(rnd, 0.0), r["speedup"])
    return [best[rnd] for rnd in sorted(best)]


def target_speedup(rec: dict[str, Any], k: int) -> float | None:
    """The speed-up a target of ``k`` workers is judged on: the median of the rounds' (:func:`speedups`)."""
    got = speedups(rec, k)
    return round(statistics.median(got), 2) if got else None


def machine_times() -> dict[str, float]:
    """The machine's CPU seconds so far, all cores together: ``busy`` (every process's, this one's and any
    other's), ``idle`` (and waiting for I/O) and ``steal`` (taken by the hypervisor, where it says so)."""
    import psutil

    t = psutil.cpu_times()
    idle = t.idle + getattr(t, "iowait", 0.0)
    steal = getattr(t, "steal", 0.0)
    return {"busy": sum(t) - idle - steal - getattr(t, "guest", 0.0) - getattr(t, "guest_nice", 0.0),
            "idle": idle, "steal": steal}


def engine_speedups(rec: dict[str, Any]) -> list[float]:
    """Each round's speed-up of oxidd on the machine's cores over that round's two-worker cluster (its best parts
    per worker), in round order."""
    out = []
    for rnd in sorted({r.get("round", 0) for r in rec["rows"]}):
        mine = [r for r in rec["rows"] if r.get("round", 0) == rnd]
        two = [r["wall"] for r in mine if r.get("workers") == 2 and "compare_cut" not in r]
        ox = [r["wall"] for r in mine if r.get("threads") == rec["cores"]]
        if two and ox:
            out.append(round(min(two) / ox[0], 2))
    return out


def measure(N: int, workers: list[int], per_worker: int | list[int], processes: int, quiet: bool = False,
            no_symmetry: bool = False, compare_cuts: int = 0, parallel_after: float = 1.0,
            rounds: int = 1, oxidd: bool = True) -> dict[str, Any]:
    import yaml

    from pipelines.spec.model import parse_spec
    from pipelines.symbolic.oxidd_mirror import oxidd_available
    from pipelines.synthesis.engine_cpre import OnOxidd
    from pipelines.synthesis.options import SynthesisOptions
    from pipelines.synthesis.synthesize import synthesize
    from workers.cluster import connect
    from workers.dask_cpre import on_cluster, parts_for
    from workers.job import run_abstraction
    from workers.processes.partitioned_cpre import PartitionedPredecessors

    data = yaml.safe_load((ROOT / "examples" / "consensus.yaml").read_text())
    data["parameters"]["N"] = N
    data["options"]["initial_states"] = []
    spec = parse_spec(yaml.safe_dump(data))
    t0 = time.perf_counter()
    a = run_abstraction(spec, audit=False)
    abstraction_seconds = time.perf_counter() - t0

    def say(msg: str) -> None:
        if not quiet:
            print(msg, flush=True)

    # the stage clock's count: live workers and reaped helpers (imported here: `python bench/synthesis.py` reads
    # this module before it starts again as `python -m bench.synthesis`, where the package is importable)
    from bench.harness import tree_cpu

    def run(mode: str, partitioned: Any = None, **kw: Any) -> dict[str, Any]:
        """One synthesis; ``kw`` are :class:`SynthesisOptions` fields."""
        c0, m0 = tree_cpu(), machine_times()
        t = time.perf_counter()
        kw.setdefault("parallel_after", parallel_after)
        options = SynthesisOptions(reach_and_stay_methods=("reach_safe",), **kw)
        game, results, report = synthesize(a.network, a.relations, a.interconnection, spec.specification, options,
                                           partitioned=partitioned)
        wall = time.perf_counter() - t
        cpu, machine = tree_cpu() - c0, {k: v - m0[k] for k, v in machine_times().items()}
        parallel = dict(report.get("parallel") or {})
        game.close()
        row = {"mode": mode, "wall": round(wall, 2), "cpu": round(cpu, 2),
               "machine": {k: round(v, 2) for k, v in machine.items()},
               "domain_states": results["reach_safe"].domain_states,
               "iterations": results["reach_safe"].iterations, "parallel": parallel}
        say(f"  {mode:<28} {wall:8.1f} s  domain {row['domain_states']:,}  ({cpu:.1f} s CPU)")
        return row

    say(f"consensus N = {N}: abstraction {abstraction_seconds:.1f} s; synthesis in every mode")
    rows: list[dict[str, Any]] = []
    per_workers = [per_worker] if isinstance(per_worker, int) else list(per_worker)
    per_worker = per_workers[0]
    best_each: dict[int, int] = {}  # per worker count, the parts per worker the later rounds repeat
    for rnd in range(rounds):
        first = rnd == 0  # the extras run once
        tag = "" if rounds == 1 else f" (round {rnd + 1})"
        start = len(rows)
        rows.append(run("one process" + tag, processes=1))
        if first and no_symmetry:  # what the interchangeable subsystems bought (pipelines/synthesis/symmetry.py)
            rows.append(run("one process, no symmetry", processes=1, symmetry=False))
        if first and processes > 1:
            rows.append(run(f"{processes} helper processes", processes=processes, partitioned=PartitionedPredecessors))
        for k in workers:
            conn = connect(None, k)
            try:
                client = conn.client
                for each in per_workers if first else [best_each[k]]:  # more parts than workers (workers.dispatch)
                    label = "" if len(per_workers) == 1 else f", {each} part{'s' if each > 1 else ''} each"
                    rows.append(run(f"cluster, {k} worker{'s' if k > 1 else ''}{label}{tag}", processes="auto",
                                    partitioned=on_cluster(client), auto_parts=parts_for(client, each)))
                    rows[-1]["workers"], rows[-1]["per_worker"] = k, each
                if first and no_symmetry and k == workers[-1]:  # what the symmetry buys on the cluster's parts
                    rows.append(run(f"cluster, {k} workers, no symmetry", processes="auto", symmetry=False,
                                    partitioned=on_cluster(client), auto_parts=parts_for(client, per_worker)))
                if first and compare_cuts and k == workers[-1]:  # many parts: what the split cut buys over windows
                    parts = parts_for(client, compare_cuts)
                    for cut in ("window", "split"):
                        rows.append(run(f"cluster, {k} workers, {parts} parts, {cut}", processes="auto",
                                        partitioned=on_cluster(client, cut=cut), auto_parts=parts))
                        rows[-1]["compare_cut"] = cut
            finally:
                conn.close()
        cores = os.cpu_count() or 1
        threads = ([1] if first and cores > 1 else []) + [cores]  # one thread in the first round only
        for t in threads if oxidd and oxidd_available() else []:
            # from the first call: a job does so from N = 5 on (engine_cpre.AT_ONCE_BITS), later below
            rows.append(run(f"oxidd, {t} thread{'s' if t > 1 else ''}{tag}", partitioned=OnOxidd(t), parallel_after=0.0))
            rows[-1]["threads"] = t
        base = rows[start]  # each round against its own one process
        base["baseline"] = True
        for r in rows[start:]:
            r["round"] = rnd
            r["speedup"] = round(base["wall"] / r["wall"], 2) if r["wall"] else None
            r["same_domain"] = r["domain_states"] == base["domain_states"]
        if first:  # the median compares like with like: each later round runs round 1's best parts per worker
            for k in workers:
                mine = [r for r in rows if r.get("workers") == k and "per_worker" in r]
                best_each[k] = max(mine, key=lambda r: r["speedup"] or 0.0)["per_worker"]
    return {"N": N, "cores": os.cpu_count(), "per_worker": per_worker, "parallel_after": parallel_after,
            "abstraction_seconds": round(abstraction_seconds, 2), "rounds": rounds,
            "rows": rows, "targets": TARGETS}


def lines(rec: dict[str, Any]) -> list[str]:
    """The case's table, with each target's verdict."""
    out = [f"  synthesis: consensus N = {rec['N']} (Reach(Safe)), {rec['cores']} cores, "
           f"{rec['per_worker']} part(s) per worker, the parts from "
           + ("the first step" if rec.get("parallel_after", 1.0) <= 0 else f"a step of {rec.get('parallel_after', 1.0):g} s")]
    out.append(f"    {'mode':<28} {'wall s':>8} {'speed-up':>9}  {'parts':>5}  {'calls':>5}  same domain  "
               f"{'CPU s':>7} {'idle s':>7} {'steal s':>7}")
    for r in rec["rows"]:
        p = r["parallel"]
        m = r.get("machine") or {}
        cpu = "".join(f" {v:7.1f}" if v is not None else f" {'-':>7}"
                      for v in (r.get("cpu"), m.get("idle"), m.get("steal")))
        out.append(f"    {r['mode']:<28} {r['wall']:8.1f} {r['speedup']:9.2f}  {p.get('processes', 1):>5}  "
                   f"{p.get('calls', 0):>5}  {'yes' if r['same_domain'] else 'NO ':<11} {cpu}")
    out.append("    (CPU: this process and its workers; idle and steal: the whole machine's, all cores. One process "
               "computing alone should have CPU = wall: what it lacks, it waited for a core the machine gave elsewhere)")
    if "allocator" in rec:
        from workers.cluster import worker_environ

        same = rec["allocator"] == worker_environ()
        out.append("    one process under the workers' allocator settings (workers/dask.yaml): "
                   + ("yes" if same else f"NO ({rec['allocator']}): the ratios partly measure the allocator"))
    for r in rec["rows"]:
        t = r["parallel"].get("seconds")
        if t:
            cpu = f" ({t['slowest_part_cpu']:.1f} s of CPU)" if "slowest_part_cpu" in t else ""
            out.append(f"    {r['mode']}: of the partitioned calls, {t['slowest_part']:.1f} s the slower part of each{cpu}, "
                       f"{t['after_parts']:.1f} s reading and joining the parts after it"
                       + (f" (of which {t['last_start']:.1f} s until the last part began, {t['after_last']:.1f} s after "
                          "the last part ended)" if "last_start" in t else "")
                       + f", {t['exists_u']:.1f} s the ∃u "
                       f"step, {t['sending']:.1f} s sending the sets (in the job's process)")
    for r in rec["rows"]:  # more workers than cores: what a core per worker would give, from the parts' CPU seconds
        t = r["parallel"].get("seconds") or {}
        if r.get("workers", 0) > rec["cores"] and "slowest_part_cpu" in t:
            est = r["wall"] - t["slowest_part"] + t["slowest_part_cpu"]
            out.append(f"    {r['mode']}: {r['workers']} workers share {rec['cores']} cores; with a core each the slower "
                       f"parts would take their CPU seconds: about {est:.1f} s, "
                       f"{rec['rows'][0]['wall'] / est:.2f}x one process (an estimate: the waiting and the job's "
                       "process are counted as measured here, on shared cores)")
    for r in rec["rows"]:  # where the waiting for the last part to begin went, call by call
        calls = r["parallel"].get("per_call")
        if calls:
            out.append(f"    {r['mode']}: per call, wall / slowest part / until the last part began / until its "
                       "task was entered / most parts on one worker: "
                       + ", ".join(f"{c['wall']:.1f}/{c['slowest_part']:.1f}/{c['last_start']:.1f}/"
                                   f"{c.get('last_entered', 0):.1f}/{c.get('most_on_one_worker', '?')}" for c in calls))
    for r in rec["rows"]:
        w = r["parallel"].get("window_cells")
        if w and w["cells"]:
            total = sum(w["parts"])
            why = ("the split cut: each cell once, then each range's states joined from the ranges they reach"
                   if r["parallel"].get("cut") == "split" else "each window reaches past its range by the spread of M̂")
            out.append(f"    {r['mode']}: the last call's parts ran the chain on {total} cells of ŵ's {w['cells']} "
                       f"({total / w['cells']:.2f}x: {why})")
    summed = {r["compare_cut"]: sum(c["parts_sum"] for c in r["parallel"].get("per_call", []))
              for r in rec["rows"] if r.get("compare_cut")}
    if len(summed) == 2 and summed["window"]:
        out.append(f"    many parts: the parts' seconds summed over the calls, windows {summed['window']:.1f} s, split "
                   f"{summed['split']:.1f} s ({summed['split'] / summed['window']:.2f}x)")
    for r in rec["rows"]:  # what each call waited for: its busiest worker, against the mean (CPU: as on a core each)
        calls = r["parallel"].get("per_call") or []
        if calls and "busiest_worker_cpu" in calls[0] and r.get("workers"):
            busiest = sum(c["busiest_worker_cpu"] for c in calls)
            mean = sum(c["parts_cpu_sum"] for c in calls) / r["workers"]
            out.append(f"    {r['mode']}: CPU seconds summed over the calls, the busiest worker of each {busiest:.1f} s, "
                       f"the mean worker {mean:.1f} s ({busiest / mean if mean else 0:.2f}x), all parts "
                       f"{sum(c['parts_cpu_sum'] for c in calls):.1f} s")
    out += [f"    {line}" for line in where_the_time_went(rec)]
    for k, target in rec["targets"].items():  # keys are strings once read back from JSON
        rows = [r for r in rec["rows"] if r.get("workers") == int(k) and r.get("round", 0) == 0]
        row = max(rows, key=lambda r: r["speedup"], default=None)  # the best parts per worker
        got = speedups(rec, int(k))
        value = target_speedup(rec, int(k))
        if row is not None and value is not None:
            met = value >= target
            how = f", {row['per_worker']} parts per worker" if len(rows) > 1 else ""
            each = (f" (the median of the rounds' {', '.join(f'{v:.2f}' for v in got)})"
                    if len(got) > 1 else "")
            out.append(f"    target: {k} workers >= {target}x one process: {value:.2f}x{each}{how} "
                       f"({'met' if met else 'NOT met'})")
    got = engine_speedups(rec)
    if got:
        value = statistics.median(got)
        each = f" (the median of the rounds' {', '.join(f'{v:.2f}' for v in got)})" if len(got) > 1 else ""
        out.append(f"    target: oxidd on {rec['cores']} threads >= {ENGINE_TARGET}x two Dask workers: {value:.2f}x{each} "
                   f"({'met' if value >= ENGINE_TARGET else 'NOT met'})")
    return out


def where_the_time_went(rec: dict[str, Any]) -> list[str]:
    """Each cluster row's wall seconds against half (a ``k``-th) of its round's one process, in four terms that
    add up: the job's process alone between the calls (symmetry checks, the first call, building, counting), the
    parts' CPU seconds as if spread evenly over the workers, the calls' wait for their busiest worker beyond the
    mean, and the rest of the calls' wall (transfers, and a worker waiting for a core). Below, the parts' CPU
    against the one process's CPU less the same time outside the calls: what cutting cost."""
    out = []
    base: dict[int, dict[str, Any]] = {}
    for r in rec["rows"]:
        if r.get("baseline"):
            base[r.get("round", 0)] = r
    for r in rec["rows"]:
        calls, k = r["parallel"].get("per_call") or [], r.get("workers")
        one = base.get(r.get("round", 0))
        if not calls or not k or "busiest_worker_cpu" not in calls[0] or one is None:
            continue
        outside = r["wall"] - sum(c["wall"] for c in calls)
        parts_cpu = sum(c["parts_cpu_sum"] for c in calls)
        wait = sum(c["busiest_worker_cpu"] - c["parts_cpu_sum"] / k for c in calls)
        rest = sum(c["wall"] - c["busiest_worker_cpu"] for c in calls)
        out.append(f"{r['mode']}: {r['wall']:.1f} s against one process / {k} = {one['wall'] / k:.1f} s: "
                   f"{outside:.1f} s in the job's process outside the calls + {parts_cpu / k:.1f} s the parts' CPU "
                   f"spread evenly + {wait:.1f} s waiting for each call's busiest worker + {rest:.1f} s the rest of "
                   "the calls (transfers, waiting for a core)")
        if one.get("cpu"):
            same = one["cpu"] - outside  # the one process's CPU in the same calls, taking its outside as this row's
            out.append(f"{r['mode']}: the parts' CPU {parts_cpu:.1f} s against the one process's {same:.1f} s in "
                       f"the same calls ({parts_cpu / same:.2f}x; its {one['cpu']:.1f} s less the {outside:.1f} s "
                       "outside them)")
    return out


def _worker_counts(text: str) -> list[int]:
    """``--workers``: comma-separated counts, each at least 1."""
    return [count(1)(w.strip()) for w in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--N", type=count(1), default=8, help="agents (default 8, the paper's case)")
    p.add_argument("--workers", type=_worker_counts, default=None, help="comma-separated worker counts (default 1, 2, 4, ... up to the cores)")
    p.add_argument("--per-worker", type=_worker_counts, default=[1],
                   help="parts per worker (workers.dask_cpre.PARTS_PER_WORKER); comma-separated: each cluster once per value")
    p.add_argument("--processes", type=count(1), default=2, help="helper processes for the local mode (1: skip it)")
    p.add_argument("--parallel-after", type=float, default=1.0,
                   help="seconds a step must take in one process before the parts start (0: from the first step)")
    p.add_argument("--json", default=None, help="write the results here")
    p.add_argument("--no-symmetry", action="store_true", help="also run one process and the largest cluster without the symmetry")
    p.add_argument("--compare-cuts", type=count(0), default=0, metavar="P",
                   help="also run the largest cluster with P parts per worker, windows and split cut (0: not)")
    p.add_argument("--no-oxidd", action="store_true", help="leave out the oxidd rows (1 thread, and one per core)")
    p.add_argument("--rounds", type=count(1), default=1,
                   help="run one process and each cluster this many times, alternating; targets on the median")
    args = p.parse_args(argv)
    cores = os.cpu_count() or 1
    workers = args.workers or default_workers(cores)
    rec = measure(args.N, workers, args.per_worker, args.processes, no_symmetry=args.no_symmetry,
                  compare_cuts=args.compare_cuts, parallel_after=args.parallel_after, rounds=args.rounds,
                  oxidd=not args.no_oxidd)
    from workers.cluster import worker_environ

    rec["allocator"] = {k: os.environ.get(k) for k in worker_environ()}  # this process's: the one process's
    print("\n".join(lines(rec)))
    if args.json:
        Path(args.json).write_text(json.dumps(rec, indent=1))
    return 0


def same_allocator_as_the_workers() -> None:
    """Start this script again under the workers' allocator settings (``workers/dask.yaml``'s
    ``pre-spawn-environ``: glibc's malloc tunings and transparent huge pages), unless it already runs under them.

    The one process, the baseline, runs in this process, and the Dask workers get those settings from their
    nannies: measured under different allocators, the ratio would partly measure the allocator (huge pages alone
    make one process about 9 % faster on consensus N = 7)."""
    from workers.cluster import worker_environ
    from workers.huge_pages import restart_under

    want = worker_environ()
    if all(os.environ.get(k) == v for k, v in want.items()):
        return
    print("bench/synthesis.py: started again under the workers' allocator settings", file=sys.stderr)
    restart_under({**os.environ, **want})


def run(args: Any) -> dict[str, Any]:
    """The ``synthesis`` case of ``bench/run.py``: this module in a child process (it starts and stops its own
    clusters), under the workers' allocator settings as its one process must be (:func:`same_allocator_as_the_workers`)."""
    import subprocess
    import tempfile

    from workers.cluster import worker_environ

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "synthesis.json"
        proc = subprocess.run([sys.executable, "-m", "bench.synthesis", "--N", str(args.synthesis_N), "--no-symmetry",
                               "--compare-cuts", "8", "--rounds", str(args.synthesis_rounds), "--json", str(out)],
                              cwd=ROOT, timeout=args.consensus_timeout * (6 + 2 * args.synthesis_rounds),
                              env={**os.environ, **worker_environ()})
        if proc.returncode != 0 or not out.exists():
            return {"case": "synthesis", "status": f"failed (exit {proc.returncode})", "rows": []}
        return {"case": "synthesis", "status": "ok", **json.loads(out.read_text())}


def targets(rec: dict[str, Any], put: Any) -> None:
    """Issue 24's targets: each worker count's speed-up (the median of the rounds'), and the same domain in every
    mode."""
    for k, target in rec.get("targets", {}).items():
        v = target_speedup(rec, int(k))
        if v is not None:
            put(f"consensus synthesis, {k} Dask workers / one process", v, f">= {target}", v >= target)
    got = engine_speedups(rec)
    if got:
        v = round(statistics.median(got), 2)
        put(f"consensus synthesis, oxidd on {rec['cores']} threads / two Dask workers", v, f">= {ENGINE_TARGET}",
            v >= ENGINE_TARGET)
    same = [r["same_domain"] for r in rec["rows"]]
    put("synthesis modes give the one process's domain", all(same), "all", bool(same) and all(same))


if __name__ == "__main__":
    if not __package__:  # `python bench/synthesis.py`: as `python -m bench.synthesis` (bench/__init__.py says why)
        if not os.path.samefile(os.getcwd(), ROOT):
            sys.exit(f"bench/synthesis.py: run it from the repository root ({ROOT}), or as python -m bench.synthesis")
        os.execv(sys.executable, [sys.executable, "-m", "bench.synthesis", *sys.argv[1:]])
    same_allocator_as_the_workers()
    sys.exit(main())
