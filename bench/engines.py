"""BDD engines on identical problems (issue 49, "measure before choosing"): the same fixed point on ``dd.cudd`` and
on ``oxidd`` (plain BDDs and BDDs with complement edges, on 1, 2 and, where the machine has them, 16 threads).

Each problem (a job spec, ``name[:N]``) is abstracted once in this process by the real pipeline
(:func:`workers.job.run_abstraction`, audit off) and its controllable predecessor prepared as the synthesis prepares
it (:class:`~pipelines.synthesis.cpre.ControllablePredecessor`: its method, its greedy chain, the variable order of
the job; the symmetry of interchangeable subsystems off, since it is written for CUDD alone). The chain, the
admissible pairs, the shared ``M̂``, the specification's sets and the chain restricted to the sets the loops stay
in (``ControllablePredecessor.within``, computed here once) are written as DDDMP with the model's header
(:func:`pipelines.symbolic.files.dump`). Each engine then runs in a child process of its own (its peak RSS is its
own): it reads those files into a fresh manager with the same variable order (:mod:`pipelines.symbolic.engines`),
runs the specification's fixed point with the same chain of relational products (:meth:`Game.predecessors`, the
code of :func:`pipelines.synthesis.cpre.predecessors_of` over the engine seam), counts and writes its domain, and reads the
reference domain back to compare the two as sets (equal functions in one canonical manager, and the states of
their symmetric difference).

The fixed points are those of :mod:`pipelines.synthesis.fixed_points` as a job runs them, without the controller:
safety ``νZ. S ∧ ∃u.CPre(Z)`` and Reach(Safe) (the layered reach, ``∃u.CPre(Z)`` only on ``¬Z``). The safety loop
starts where a job's does, from the bound of the local games (:func:`~pipelines.synthesis.local_games.invariant_bound`,
computed here once in CUDD and handed to every engine; ``--no-local-games``: from ``S``). ``--pipeline`` also runs
:func:`~pipelines.synthesis.fixed_points.safe` or :func:`~pipelines.synthesis.fixed_points.reach_safe` itself in
this process (layered, no symmetry, the local games inside its time): its domain is then the reference, so the
rows say the replica computes what the synthesis computes.

    python bench/engines.py [--problems consensus:6,tanks,rooms:3,platoon:4] [--engines dd.cudd,oxidd.bdd,oxidd.bcdd]
                            [--threads 1,2] [--rounds R] [--pipeline] [--no-local-games] [--timeout S]
                            [--oxidd-cache ENTRIES] [--json OUT]
                            # or: python -m bench.engines ...

Columns: the engine and its threads, seconds reading the problem, seconds of the fixed point (the median of
``--rounds``), its iterations, the speed-up over ``dd.cudd`` and over the same kind on one thread (both measured in
this run), the child's peak RSS and how much of it came after the imports (the engine's own), the domain's states,
and whether the domain is the reference's set. Issue 49's rule for a new default: at least 1.5x faster than
``dd.cudd`` on every compositional problem, with the same domains.

Consensus runs at N = 6 unless told (``consensus:8``): without the symmetry each agent multiplies the fixed point's
time about fourfold (N = 4 to 5 to 6 in one CUDD process), so N = 8 takes tens of minutes per engine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
#: Problems by name: the spec and its ``N`` when none is given (``name:N`` sets it).
PROBLEMS: dict[str, tuple[str, int | None]] = {
    "consensus": ("consensus.yaml", 6), "tanks": ("tanks.yaml", None), "rooms": ("rooms.yaml", 3),
    "platoon": ("platoon.yaml", 4), "small": ("small.yaml", None),
}
DEFAULT_PROBLEMS = "consensus:6,tanks,rooms:3,platoon:4"
ENGINES = ("dd.cudd", "oxidd.bdd", "oxidd.bcdd")
#: Issue 49: another engine becomes the default if at least this much faster on every compositional problem.
ADOPT_AT = 1.5


# ====================================================================================== the problem
def parse_problem(text: str) -> tuple[str, int | None]:
    """``name`` or ``name:N`` (:data:`PROBLEMS`)."""
    name, _, n = text.strip().partition(":")
    if name not in PROBLEMS:
        raise argparse.ArgumentTypeError(f"unknown problem {name!r}: one of {', '.join(PROBLEMS)}")
    return name, int(n) if n else PROBLEMS[name][1]


def export_problem(name: str, N: int | None, out: Path, pipeline: bool = False, local_games: bool = True,
                   say: Callable[[str], None] = print) -> dict[str, Any]:
    """Abstract the problem, prepare its CPre and write it to ``out/problem`` (:func:`~pipelines.symbolic.files.dump`;
    the roots named in ``meta["names"]``). With ``pipeline``, also run the synthesis's own fixed point and write its
    domain to ``out/pipeline.dddmp``. Returns what the table reports of it."""
    import yaml

    from pipelines.spec.model import parse_spec
    from pipelines.spec.regions import abstract_region
    from pipelines.symbolic.files import dump
    from pipelines.symbolic.relations import region
    from pipelines.synthesis.cpre import ControllablePredecessor
    from workers.job import run_abstraction

    data = yaml.safe_load((ROOT / "examples" / PROBLEMS[name][0]).read_text())
    if N is not None:
        data["parameters"]["N"] = N
    data.setdefault("options", {})["initial_states"] = []
    spec = parse_spec(yaml.safe_dump(data))
    t0 = time.perf_counter()
    a = run_abstraction(spec, audit=False)
    abstraction = time.perf_counter() - t0
    t0 = time.perf_counter()
    cpre = ControllablePredecessor.from_network(a.network, a.relations, a.interconnection, symmetry=False)
    build = time.perf_counter() - t0
    m, sp = cpre.model, spec.specification
    grid = a.network.composed_state_grid()

    def get(which: str) -> Any:
        return region(m, abstract_region(getattr(sp, which), grid, f"specification.{which}"))

    S = get("safe") if sp.safe is not None else None
    kind = {"safe": "safe", "reach_and_stay": "reach_safe"}.get(sp.kind)
    if kind is None:
        raise ValueError(f"{name}: the bench runs safety and reach-and-stay specifications, not {sp.kind!r}")
    roots: dict[str, Any] = {"admissible": cpre.admissible, "x_domain": m.x_domain}
    if cpre.M is not None:
        roots["M"] = cpre.M
    for k, (rel, _) in enumerate(cpre.chain):
        roots[f"chain{k}"] = rel
    invariant = (S if kind == "safe" else get("target") if S is None else get("target") & S)
    invariant &= m.x_domain
    roots["invariant"] = invariant
    _within(roots, "invariant", cpre.within(invariant))
    local = None
    if local_games:  # the safety loop's start, as a job computes it (in CUDD, once: both engines start there)
        from pipelines.synthesis.local_games import invariant_bound

        local = invariant_bound(cpre, invariant)
        roots["start"] = local.start
    if kind == "reach_safe" and S is not None:
        keep = m.x_domain & S
        roots["keep"] = keep
        _within(roots, "keep", cpre.within(keep))
    names = list(roots)
    meta = {"names": names, "problem": name, "N": N, "kind": kind, "method": cpre.method,
            "chain_bits": [list(bits) for _, bits in cpre.chain], "x_bits": m.x_bits, "xn_bits": m.xn_bits,
            "u_bits": m.u_bits, "w_bits": list(cpre.w_bits)}
    dump(m, out / "problem", [roots[n] for n in names], meta)
    rec = {"problem": name, "N": N, "kind": kind, "method": cpre.method, "order": m.order,
           "abstraction_seconds": round(abstraction, 2), "build_seconds": round(build, 2),
           "variables": len(m.variables), "relation_nodes": sum(rel.dag_size for rel, _ in cpre.chain),
           "M_nodes": cpre.M.dag_size if cpre.M is not None else 0,
           "local_games": None if local is None else {"seconds": round(local.seconds, 2), "used": local.used}}
    say(f"{name}{'' if N is None else f' N = {N}'}: abstraction {abstraction:.1f} s, CPre ({cpre.method}, "
        f"{len(m.variables)} variables, chain {rec['relation_nodes']:,} nodes) {build:.1f} s")
    if pipeline:
        rec["pipeline"] = _pipeline(cpre, kind, roots, S, out / "pipeline.dddmp", local_games)
        say(f"  pipeline's own fixed point (fixed_points.{kind}) {rec['pipeline']['seconds']:.1f} s, "
            f"domain {rec['pipeline']['domain_states']:,}")
    cpre.close()
    return rec


def _within(roots: dict[str, Any], name: str, within: Any) -> None:
    for k, (rel, _) in enumerate(within.chain):
        roots[f"{name}_chain{k}"] = rel
    roots[f"{name}_admissible"] = within.admissible


def _pipeline(cpre: Any, kind: str, roots: dict[str, Any], S: Any, path: Path, local_games: bool) -> dict[str, Any]:
    """The synthesis's own fixed point on the problem (layered; the CPre has no symmetry)."""
    from pipelines.symbolic.files import write_root
    from pipelines.synthesis.fixed_points import reach_safe, safe

    t0 = time.perf_counter()
    if kind == "safe":
        r = safe(cpre, roots["invariant"], layered=True, local_games=local_games)
    else:
        r = reach_safe(cpre, roots["invariant"], layered=True, safe_set=S, local_games=local_games)
    seconds = time.perf_counter() - t0
    write_root(cpre.model, path, r.domain)
    return {"seconds": round(seconds, 2), "domain_states": r.domain_states, "iterations": r.iterations}


# ====================================================================================== the fixed points
class Game:
    """The problem's CPre ingredients in one engine (:mod:`pipelines.synthesis.cpre`'s names)."""

    def __init__(self, engine: Any) -> None:
        self.e, r, meta = engine, engine.roots, engine.meta
        self.kind = meta["kind"]
        self.M = r.get("M")
        self.w_bits, self.u_bits = meta["w_bits"], meta["u_bits"]
        bits = meta["chain_bits"]
        self.whole = ([(r[f"chain{k}"], b) for k, b in enumerate(bits)], r["admissible"])
        self.within = {w: ([(r[f"{w}_chain{k}"], b) for k, b in enumerate(bits)], r[f"{w}_admissible"])
                       for w in ("invariant", "keep") if f"{w}_admissible" in r}

    def predecessors(self, Z: Any, outside: Any = None, within: str | None = None) -> Any:
        """``∃u.CPre(Z)`` (exact on ``outside`` where given): :func:`~pipelines.synthesis.cpre.predecessors_of`."""
        e = self.e
        chain, admissible = self.whole if within is None else self.within[within]
        bad = ~e.to_next(Z)
        for rel, xn_bits in chain:
            bad = e.and_exists(bad, rel, xn_bits)
        if self.M is not None:
            care = self.M if outside is None else self.M & outside
            bad = e.and_exists(care, bad, self.w_bits)
        return e.and_exists(admissible, ~bad, self.u_bits)

    def safe(self, start: Any) -> tuple[Any, int]:
        """``νZ. S ∧ ∃u.CPre(Z)`` as ``Z ∧ ∃u.CPre(Z)`` from ``start`` (``S``, or the local games' bound inside it),
        the chain restricted to ``S`` (:func:`~pipelines.synthesis.fixed_points.safe`)."""
        Z, n = start, 0
        while True:
            Zn = Z & self.predecessors(Z, within="invariant")
            n += 1
            if Zn == Z:
                return Z, n
            Z = Zn

    def reach(self, T: Any, keep: Any, within: str | None) -> tuple[Any, int]:
        """The layered ``μZ. (T ∨ ∃u.CPre(Z)) ∧ keep`` (:func:`~pipelines.synthesis.fixed_points.reach`)."""
        Z, n = T & keep, 0
        while True:
            new = self.predecessors(Z, outside=~Z, within=within) & keep & ~Z
            n += 1
            if new == self.e.false:
                return Z, n
            Z |= new

    def solve(self) -> tuple[Any, int]:
        """The problem's fixed point: its domain and iterations (Reach(Safe): the safety part's and the reach's)."""
        r = self.e.roots
        safe, n = self.safe(r.get("start", r["invariant"]))
        if self.kind == "safe":
            return safe, n
        if "keep" in r:
            Z, m = self.reach(safe, r["keep"], "keep")
        else:
            Z, m = self.reach(safe, r["x_domain"], None)
        return Z, n + m


# ====================================================================================== one engine, in a child
def run_engine(problem: Path, name: str, threads: int, reference: Path | None, out: Path | None,
               cache: int | None = None) -> dict[str, Any]:
    """Read the problem into engine ``name``, solve it, and compare its domain with ``reference``'s (a DDDMP file);
    write the domain to ``out``. Seconds are wall; RSS this process's peak (MiB)."""
    from pipelines.symbolic.engines import engine, peak_rss_mb

    rss0 = peak_rss_mb()
    t0 = time.perf_counter()
    e = engine(problem, name, threads, **({"cache": cache} if cache else {}))
    load = time.perf_counter() - t0
    rss_loaded = peak_rss_mb()
    c0, t0 = time.process_time(), time.perf_counter()
    domain, iterations = Game(e).solve()
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    rec: dict[str, Any] = {"engine": name, "threads": threads if name != "dd.cudd" else 1,
                           "load_seconds": round(load, 3), "seconds": round(seconds, 3), "cpu": round(cpu, 3),
                           "iterations": iterations, "domain_states": e.count(domain),
                           "domain_nodes": e.nodes(domain), "rss_start_mb": round(rss0, 1),
                           "rss_loaded_mb": round(rss_loaded, 1), "peak_rss_mb": round(peak_rss_mb(), 1)}
    if reference is not None:
        ref = e.read(reference)
        rec["same_set"] = bool(domain == ref)
        rec["symmetric_difference"] = e.count((domain & ~ref) | (ref & ~domain))
    if out is not None:
        e.write(domain, out)
    return rec


def child(problem: Path, name: str, threads: int, reference: Path | None, out: Path, result: Path,
          timeout: float, cache: int | None) -> dict[str, Any]:
    """:func:`run_engine` in a child process (``python -m bench.engines --child``); its record, or why none."""
    cmd = [sys.executable, "-m", "bench.engines", "--child", name, "--threads", str(threads), "--problem",
           str(problem), "--out", str(out), "--result", str(result)]
    if reference is not None:
        cmd += ["--reference", str(reference)]
    if cache:
        cmd += ["--oxidd-cache", str(cache)]
    try:
        proc = subprocess.run(cmd, cwd=ROOT, timeout=timeout, capture_output=True, text=True)
    except subprocess.TimeoutExpired:
        return {"engine": name, "threads": threads, "status": f"timed out after {timeout:g} s"}
    if proc.returncode != 0 or not result.exists():
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        return {"engine": name, "threads": threads, "status": f"failed (exit {proc.returncode}): {tail[0]}"}
    return {**json.loads(result.read_text()), "status": "ok"}


# ====================================================================================== the bench
def measure(problems: list[tuple[str, int | None]], engines: list[str], threads: list[int], rounds: int = 1,
            pipeline: bool = False, timeout: float = 600.0, cache: int | None = None, local_games: bool = True,
            say: Callable[[str], None] = print) -> dict[str, Any]:
    """Every problem on every engine (``oxidd.*`` once per thread count), ``rounds`` times each, alternating."""
    from pipelines.symbolic.engines import oxidd_available

    if not oxidd_available() and any(e.startswith("oxidd") for e in engines):
        say("oxidd is not installed (pip install oxidd): only dd.cudd runs")
        engines = [e for e in engines if not e.startswith("oxidd")]
    runs = [(e, 1) for e in engines if e == "dd.cudd"] + [(e, k) for e in engines if e != "dd.cudd" for k in threads]
    out: dict[str, Any] = {"cores": os.cpu_count(), "rounds": rounds, "problems": []}
    for name, N in problems:
        with tempfile.TemporaryDirectory(prefix="compabs-engines-") as tmp:
            d = Path(tmp)
            rec = export_problem(name, N, d, pipeline=pipeline, local_games=local_games, say=say)
            reference = d / "pipeline.dddmp" if pipeline else None
            rows: dict[tuple[str, int], list[dict[str, Any]]] = {r: [] for r in runs}
            for rnd in range(rounds):
                for k, (e, t) in enumerate(runs):
                    dom = d / f"domain{k}.dddmp"
                    row = child(d / "problem", e, t, reference, dom, d / f"row{k}_{rnd}.json", timeout, cache)
                    rows[(e, t)].append(row)
                    if reference is None and row["status"] == "ok":  # the first engine's domain is the reference
                        reference = dom
                    say(f"  {_label(row):<24} " + (f"{row['seconds']:8.2f} s, peak RSS {row['peak_rss_mb']:,.0f} MB, "
                                                  f"domain {row['domain_states']:,}" if row["status"] == "ok"
                                                  else row["status"]))
            rec["rows"] = [_median(rs) for rs in rows.values()]
            _ratios(rec["rows"])
            out["problems"].append(rec)
    return out


def _label(row: dict[str, Any]) -> str:
    e = row["engine"]
    return e if e == "dd.cudd" else f"{e}, {row['threads']} thread{'s' if row['threads'] > 1 else ''}"


def _median(rs: list[dict[str, Any]]) -> dict[str, Any]:
    """One row of the rounds: the first's fields, the median seconds, the largest peak RSS, every round agreeing."""
    ok = [r for r in rs if r["status"] == "ok"]
    if len(ok) < len(rs) or not ok:
        return next(r for r in rs if r["status"] != "ok")
    row = dict(ok[0])
    row["seconds"] = round(statistics.median(r["seconds"] for r in ok), 3)
    row["each_round"] = [r["seconds"] for r in ok]
    row["peak_rss_mb"] = max(r["peak_rss_mb"] for r in ok)
    if "same_set" in row:
        row["same_set"] = all(r["same_set"] for r in ok)
    return row


def _ratios(rows: list[dict[str, Any]]) -> None:
    """Each row's speed-up over ``dd.cudd`` and over the same engine on one thread."""
    base = next((r for r in rows if r["engine"] == "dd.cudd" and r["status"] == "ok"), None)
    for r in rows:
        if r["status"] != "ok":
            continue
        if base is not None:
            r["vs_cudd"] = round(base["seconds"] / r["seconds"], 2) if r["seconds"] else None
        one = next((o for o in rows if o["engine"] == r["engine"] and o["threads"] == 1 and o["status"] == "ok"), None)
        if one is not None and r["engine"] != "dd.cudd":
            r["vs_one_thread"] = round(one["seconds"] / r["seconds"], 2) if r["seconds"] else None


def lines(rec: dict[str, Any]) -> list[str]:
    """The table, and issue 49's verdict."""
    out = [f"BDD engines on identical problems ({rec['cores']} cores; fixed-point seconds the median of "
           f"{rec['rounds']} round(s); the machine may be shared: read the ratios)"]
    for p in rec["problems"]:
        n = "" if p["N"] is None else f" N = {p['N']}"
        lg = p.get("local_games")
        out.append(f"  {p['problem']}{n}: {p['kind']}, {p['method']} CPre, {p['variables']} variables, chain "
                   f"{p['relation_nodes']:,} nodes" + (f", M̂ {p['M_nodes']:,}" if p["M_nodes"] else "")
                   + ("; safety from S" if not lg or not lg["used"] else
                      f"; safety from the local games' bound ({lg['seconds']:.1f} s in CUDD, not counted)")
                   + (f"; pipeline's fixed point {p['pipeline']['seconds']:.2f} s (the reference domain)"
                      if "pipeline" in p else "; reference domain: dd.cudd's"))
        out.append(f"    {'engine':<26} {'read s':>7} {'fixed s':>8} {'iter':>5} {'vs cudd':>8} {'vs 1 thr':>8} "
                   f"{'peak RSS MB':>11} {'(engine)':>8} {'domain states':>20}  same set")
        for r in p["rows"]:
            if r["status"] != "ok":
                out.append(f"    {_label(r):<26} {r['status']}")
                continue
            same = "-" if "same_set" not in r else "yes" if r["same_set"] else f"NO ({r['symmetric_difference']:,})"
            vs1 = f"{r['vs_one_thread']:.2f}x" if "vs_one_thread" in r else "-"
            vsc = f"{r['vs_cudd']:.2f}x" if r.get("vs_cudd") else "-"
            out.append(f"    {_label(r):<26} {r['load_seconds']:7.2f} {r['seconds']:8.2f} {r['iterations']:5d} "
                       f"{vsc:>8} {vs1:>8} {r['peak_rss_mb']:11,.0f} {r['peak_rss_mb'] - r['rss_start_mb']:8,.0f} "
                       f"{r['domain_states']:20,}  {same}")
    out.append("  " + verdict(rec))
    return out


def verdict(rec: dict[str, Any]) -> str:
    """Issue 49's rule: an engine (kind and threads) becomes the default only if it is at least :data:`ADOPT_AT`
    faster than ``dd.cudd`` on every problem measured, with the same domains."""
    best: dict[tuple[str, int], list[float]] = {}
    for p in rec["problems"]:
        for r in p["rows"]:
            if r["engine"] == "dd.cudd":
                continue
            ok = r["status"] == "ok" and r.get("same_set", True) and r.get("vs_cudd")
            best.setdefault((r["engine"], r["threads"]), []).append(r["vs_cudd"] if ok else 0.0)
    if not best:
        return "verdict: no other engine ran"
    (e, t), ratios = max(best.items(), key=lambda kv: min(kv[1]))
    name = _label({"engine": e, "threads": t})
    if min(ratios) >= ADOPT_AT:
        return f"verdict: {name} is at least {ADOPT_AT}x dd.cudd on every problem (worst {min(ratios):.2f}x): adopt"
    return (f"verdict: keep dd.cudd: the best other engine, {name}, is {min(ratios):.2f}x dd.cudd on its worst "
            f"problem (each: {', '.join(f'{v:.2f}x' for v in ratios)}; adopting needs >= {ADOPT_AT}x on every one)")


def _counts(text: str) -> list[int]:
    return [int(t) for t in text.split(",") if t.strip()]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--problems", default=DEFAULT_PROBLEMS, help=f"name[:N],... of {', '.join(PROBLEMS)}")
    p.add_argument("--engines", default=",".join(ENGINES), help="comma-separated, of " + ", ".join(ENGINES))
    p.add_argument("--threads", type=_counts, default=None,
                   help="oxidd's thread counts (default 1, 2, and 16 where the machine has 16 cores)")
    p.add_argument("--rounds", type=int, default=1, help="runs of each engine, alternating; the median is reported")
    p.add_argument("--pipeline", action="store_true", help="also run the synthesis's own fixed point (the reference)")
    p.add_argument("--no-local-games", action="store_true", help="start the safety loops from S, not the local games' bound")
    p.add_argument("--timeout", type=float, default=600.0, help="seconds each engine's child may take")
    p.add_argument("--oxidd-cache", type=int, default=None, help="oxidd's apply-cache entries (default 2^22)")
    p.add_argument("--json", default=None, help="write the results here")
    # a child: one engine on one problem (what measure starts)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--problem", default=None, help=argparse.SUPPRESS)
    p.add_argument("--reference", default=None, help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help=argparse.SUPPRESS)
    p.add_argument("--result", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        rec = run_engine(Path(args.problem), args.child, (args.threads or [1])[0],
                         Path(args.reference) if args.reference else None, Path(args.out), args.oxidd_cache)
        Path(args.result).write_text(json.dumps(rec))
        return 0
    engines = [e.strip() for e in args.engines.split(",") if e.strip()]
    bad = [e for e in engines if e not in ENGINES]
    if bad:
        p.error(f"unknown engine(s) {bad}: of {', '.join(ENGINES)}")
    threads = args.threads or [1, 2] + ([16] if (os.cpu_count() or 1) >= 16 else [])
    problems = [parse_problem(t) for t in args.problems.split(",") if t.strip()]
    rec = measure(problems, engines, threads, rounds=max(1, args.rounds), pipeline=args.pipeline,
                  timeout=args.timeout, cache=args.oxidd_cache, local_games=not args.no_local_games)
    print("\n".join(lines(rec)))
    if args.json:
        Path(args.json).write_text(json.dumps(rec, indent=1))
    return 0


if __name__ == "__main__":
    if not __package__:  # `python bench/engines.py`: as `python -m bench.engines` (bench/__init__.py says why)
        if not os.path.samefile(os.getcwd(), ROOT):
            sys.exit(f"bench/engines.py: run it from the repository root ({ROOT}), or as python -m bench.engines")
        os.execv(sys.executable, [sys.executable, "-m", "bench.engines", *sys.argv[1:]])
    sys.exit(main())
