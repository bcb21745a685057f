"""compabs's benchmark: the paper's cases end to end, scalability in N, and baselines, in one run.

The command line of ``python bench/run.py`` and ``python -m bench``: the cases in order, one table, the targets, the
JSON.

    python bench/run.py                      # every case but consensus, general, synthesis, ltl and contracts
    python bench/run.py --quick              # small sizes, minutes (what tests/test_bench.py runs)
    python bench/run.py --cases tanks,consensus,scalability,floor,scp,workers,bdd
    python bench/run.py --cases tanks,scp    # some cases; consensus, general, synthesis, ltl and contracts run only
                                             # when named
    python bench/run.py --json out.json      # also write the results as JSON

Cases (``--cases``), each in a module of its own that says what it measures:

``tanks``, ``tanks_fine``, ``consensus``
    the paper's examples end to end through ``run_job`` (:mod:`bench.end_to_end`; ``--quick``: ``small.yaml``
    for the tanks, neither of the others)
``scalability``
    the paper's Fig. 3 series up to N = 1024, and the same with the map declared ``max`` (:mod:`bench.scalability`)
``floor`` (a), ``scp`` (b), ``workers`` (c), ``bdd`` (d)
    the per-cell stage against the bare black box (:mod:`bench.floor`), the batched SCP against one LP per cell
    (:mod:`bench.scp`), one Dask worker against two (:mod:`bench.two_workers`), a relation's BDD in bulk against
    one cube per constraint (:mod:`bench.bdd`)
``general`` (only when named, never under ``--quick``)
    the field's benchmarks beside SCOTS (:mod:`bench.general`)
``synthesis`` (only when named, never under ``--quick``)
    consensus synthesis in every mode, one process against Dask workers (:mod:`bench.synthesis`)
``ltl`` (only when named; under ``--quick`` the robot alone)
    temporal-logic tasks: the automaton, the product and its game on both back ends (:mod:`bench.ltl`)
``contracts`` (only when named, never under ``--quick``)
    the ring of rooms by assume-guarantee contracts up to N = 100, beside the exact fixed points under a time cap
    and on a coarser grid (:mod:`bench.contracts`)

How each child process is measured, and what the table's columns mean: :mod:`bench.harness`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench import bdd, contracts, end_to_end, floor, general, ltl, scalability, scp, synthesis, two_workers
from bench.harness import ROOT, baseline_progress, child_main, fmt, jsonable, stage_line
from service.arguments import count

ALL_CASES = ("tanks", "tanks_fine", "consensus", "scalability", "floor", "scp", "workers", "bdd", "general",
             "synthesis", "ltl", "contracts")
DEFAULT_CASES = tuple(c for c in ALL_CASES if c not in ("consensus", "general", "synthesis", "ltl", "contracts"))
#: Cases too large for ``--quick``.
NOT_QUICK = ("tanks_fine", "consensus", "general", "synthesis", "contracts")
#: The baselines by case name: one child per spec or worker count, a ratio each.
BASELINES = {"floor": floor, "scp": scp, "workers": two_workers, "bdd": bdd}
#: The child cases by kind (``--child``), from every case module.
CHILDREN = {**end_to_end.CHILDREN, **scalability.CHILDREN, **floor.CHILDREN, **scp.CHILDREN, **two_workers.CHILDREN,
            **bdd.CHILDREN, **general.CHILDREN, **ltl.CHILDREN, **contracts.CHILDREN}
#: The paper's figures, in the JSON output.
PAPER = {**end_to_end.PAPER, "scalability": scalability.PAPER}


# ====================================================================================== running the cases
def run_case(case: str, args: Any, results: dict[str, Any]) -> None:
    """Run one case and put its record (or why it did not run) into ``results``."""
    if args.quick and case in NOT_QUICK:
        results["skipped"][case] = "not run under --quick"
    elif case in end_to_end.CASES:
        name, rec = end_to_end.run(args, case)
        results["cases"][name] = rec
    elif case == "scalability":
        results["cases"]["scalability"] = scalability.run(args)
    elif case == "general":
        results["cases"]["general"] = general.run(args)
    elif case == "synthesis":
        results["cases"]["synthesis"] = synthesis.run(args)
    elif case == "ltl":
        results["cases"]["ltl"] = ltl.run(args)
    elif case == "contracts":
        results["cases"]["contracts"] = contracts.run(args)
    else:
        rec = BASELINES[case].run(args)
        results["cases"][case] = rec
        baseline_progress(rec)


def targets(results: dict) -> dict[str, tuple]:
    """(measured, target, met) for each of the issues' "Done when" items that this run measured."""
    c = results["cases"]
    out: dict[str, tuple] = {}

    def put(key: str, val: Any, target: str, ok: bool) -> None:
        out[key] = (val, target, None if val is None else ok)

    end_to_end.targets(c, put)
    if "scalability" in c:
        scalability.targets(c["scalability"], put)
    for name, module in BASELINES.items():
        if name in c:
            module.targets(c[name], put)
    if "general" in c:
        general.targets(c["general"], put)
    if "synthesis" in c:
        synthesis.targets(c["synthesis"], put)
    if "ltl" in c:
        ltl.targets(c["ltl"], put)
    if "contracts" in c:
        contracts.targets(c["contracts"], put)
    return out


def headline_ratios(results: dict) -> dict[str, float | None]:
    """The ratios of this run in one flat dict (positive where measured; None where not)."""
    c = results["cases"]
    out: dict[str, float | None] = {}
    for name in BASELINES:
        if name in c:
            out[name] = c[name]["ratio"]
    for name in ("tanks", "consensus"):
        if name in c:
            for k, v in c[name]["vs_paper"].items():
                out[f"{name}_vs_paper_{k}"] = v
    return out


# ====================================================================================== the table
def print_table(results: dict, out: Any = None) -> None:
    """One line per case (and per N), then the baselines, then the targets."""
    out = out or sys.stdout

    def w(s: str = "") -> None:
        print(s, file=out)

    cases = results["cases"]
    w(f"{'case':<24}{'status':<9}{'total s':>9}{'CPU s':>9}{'peak MB':>9}{'others':>8}  {'abstract':>10}"
      f"{'domain':>11}  vs paper (ours/paper)")
    for name, c in cases.items():
        if name == "synthesis":  # its own table, below
            continue
        rows = c["points"] + c["probes"] if name == "scalability" else (c["runs"] if "runs" in c else [c])
        for r in rows:
            vp = r.get("vs_paper") or {}
            vps = ", ".join(f"{k} {fmt(v)}" for k, v in vp.items() if v is not None)
            w(f"{r['case']:<24}{r['status']:<9}{fmt(r['total_wall']):>9}{fmt(r['total_cpu']):>9}"
              f"{fmt(r['peak_rss_mb'], 4):>9}{fmt(r['others_cores'], 2):>8}  {fmt(r['abstract_states']):>10}"
              f"{fmt(r['domain_states']):>11}  {vps}")
            if r["stages"]:
                w(f"    stages wall/CPU s: {stage_line(r['stages'])}")
            if r.get("error"):
                w(f"    {r['status']}: {r['error'][:300]}")
            syn = (r.get("details") or {}).get("synthesis") or {}
            if syn.get("quotient") or syn.get("domain_bound"):
                w(f"    {end_to_end.domain_line(r['domain_states'], syn)}")
    w()
    w("baselines (same run)")
    lines: list[str] = []
    if (cases.get("tanks") or {}).get("local_games"):
        lines += end_to_end.local_games_lines(cases["tanks"]["local_games"])
    if "scalability" in cases:
        lines += scalability.lines(cases["scalability"])
    if "general" in cases:
        lines += general.lines(cases["general"])
    if "ltl" in cases:
        lines += ltl.lines(cases["ltl"])
    if "contracts" in cases:
        lines += contracts.lines(cases["contracts"])
    if "synthesis" in cases:
        s = cases["synthesis"]
        lines += synthesis.lines(s) if s.get("status") == "ok" else [f"  synthesis: {s.get('status')}"]
    for name, module in BASELINES.items():
        if name in cases:
            lines += module.lines(cases[name])
    for line in lines:
        w(line)
    w()
    w("targets (issues 6, 22 and 24)")
    for k, (val, target, ok) in results["targets"].items():
        w(f"  {k:<34} {fmt(val):>10}  target {target:<10} {'met' if ok else ('NOT met' if ok is False else '-')}")


# ====================================================================================== main
def meta(args: Any) -> dict:
    """What ran where: versions, the machine, the commit and the files changed since."""
    import numpy

    try:
        import dd

        dd_version = getattr(dd, "__version__", "?")
    except ImportError:  # pragma: no cover
        dd_version = None
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                                text=True).stdout.split("\n")
        dirty = [line[3:] for line in status if line.strip()]
    except OSError:  # pragma: no cover
        rev, dirty = None, []
    return {
        "quick": bool(args.quick),
        "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "dd": dd_version,
        "cpus": os.cpu_count(),
        "memory_gb": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1),
        "loadavg_start": list(os.getloadavg()),
        "git": rev,
        "modified_files": dirty,
        "command": " ".join(sys.argv),
    }


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bench/run.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small sizes (minutes); never consensus, tanks_fine, general, "
                   "synthesis or contracts")
    p.add_argument("--json", metavar="OUT", help="write the results as JSON")
    p.add_argument("--cases", default=",".join(DEFAULT_CASES),
                   help=f"comma-separated, of {','.join(ALL_CASES)} (default: all but consensus, general, synthesis, "
                   "ltl and contracts)")
    p.add_argument("--consensus-timeout", type=float, default=1800.0, metavar="S")
    p.add_argument("--tanks-timeout", type=float, default=1200.0, metavar="S")
    p.add_argument("--point-timeout", type=float, default=900.0, metavar="S",
                   help="timeout of every other child process (one N, one baseline run)")
    p.add_argument("--mem-limit-gb", type=float, default=12.0, help="kill a case whose process tree exceeds this RSS")
    p.add_argument("--bisect", type=int, default=6, metavar="K", help="probes between the last N that worked and the "
                   "first that failed (scalability)")
    p.add_argument("--e2e-workers", type=int, default=2, metavar="W",
                   help="tanks/consensus end to end on an embedded cluster of W workers, as `compabs run` (0: in "
                        "process, synthesis parts in helper processes)")
    p.add_argument("--synthesis-N", type=int, default=8, metavar="N", help="agents of the synthesis case's consensus")
    p.add_argument("--synthesis-rounds", type=count(1), default=2, metavar="R",
                   help="rounds of one process and the clusters in the synthesis case (targets on the median)")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--params", help=argparse.SUPPRESS)
    p.add_argument("--events", help=argparse.SUPPRESS)
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if args.child:  # one case's child process (bench.harness.run_child)
        return child_main(args.child, args.params, args.events, CHILDREN)

    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = set(cases) - set(ALL_CASES)
    if unknown:
        p.error(f"unknown case(s) {sorted(unknown)}; choose from {ALL_CASES}")
    results: dict[str, Any] = {"meta": meta(args), "paper": PAPER, "cases": {}, "skipped": {}}
    t0 = time.perf_counter()
    for case in cases:
        print(f"[{time.perf_counter() - t0:7.1f} s] {case} ...", file=sys.stderr, flush=True)
        run_case(case, args, results)
    results["meta"]["seconds"] = time.perf_counter() - t0
    results["meta"]["loadavg_end"] = list(os.getloadavg())
    results["targets"] = targets(results)
    results["ratios"] = headline_ratios(results)
    if "scalability" in results["cases"]:
        results["exponents"] = results["cases"]["scalability"]["exponents"]
    if args.json:  # first: a table that fails to print loses no measurement
        Path(args.json).write_text(json.dumps(results, indent=1, default=jsonable))
    print_table(results)
    return 0


__all__ = ["ALL_CASES", "CHILDREN", "DEFAULT_CASES", "main", "print_table", "targets"]
