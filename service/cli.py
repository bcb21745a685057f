"""The ``compabs`` command.

``compabs run SPEC --out DIR`` runs a job's stages with a progress bar each and writes ``DIR/report.json``
and the relation arrays. ``compabs schema`` prints the spec's JSON Schema. Errors a user can cause are
printed as one message and exit with status 2; nothing from the spec is executed except whitelisted
expressions (and ``module:function`` names, which the local command line allows).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipelines.errors import CompabsError, SpecError
from workers.jobdir import json_default as _json_default


class _Bars:
    """One tqdm progress bar per stage, fed by ``progress(stage, done, total, message)`` events."""

    def __init__(self, enabled: bool) -> None:
        self._enabled = enabled
        self._bars: dict = {}

    def __call__(self, stage: str, done: int, total: int, message: str) -> None:
        if not self._enabled:
            return
        from tqdm import tqdm

        bar = self._bars.get(stage)
        if bar is None:
            for other in self._bars.values():
                other.close()
            bar = self._bars[stage] = tqdm(total=total, desc=f"{stage:>15}", unit="task", leave=True, file=sys.stderr)
        bar.total = total
        bar.n = done
        bar.set_postfix_str(message[:60], refresh=False)
        bar.refresh()

    def close(self) -> None:
        for bar in self._bars.values():
            bar.close()


def _parse_sets(items: Sequence[str]) -> dict[str, float]:
    out = {}
    for item in items:
        if "=" not in item:
            raise SpecError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise SpecError(f"--set {name}: {value!r} is not a number") from None
    return out


def cmd_run(args: argparse.Namespace) -> int:
    from pipelines.spec.model import load_spec
    from workers.job import run_job

    spec = load_spec(args.spec, _parse_sets(args.set))
    if args.audit_transitions is not None:
        spec = spec.model_copy(update={"options": spec.options.model_copy(update={"audit_transitions": args.audit_transitions})})
    bars = _Bars(not args.quiet)
    try:
        report = run_job(
            spec, Path(args.out), scheduler=args.scheduler or os.environ.get("COMPABS_SCHEDULER"),
            workers=args.workers, in_process=args.in_process, progress=bars, allowed_modules=None,
            audit=not args.no_audit, synthesis=not args.no_synthesis, overwrite=args.overwrite,
        )
    finally:
        bars.close()
    keys = ("abstract_states", "region_states", "domain_states", "domain_states_by_fixed_point", "stage_seconds")
    summary = {k: report[k] for k in keys if k in report}
    summary["audit"] = {k: report["audit"][k] for k in ("transitions_checked", "violations")}
    if "runner" in report:
        r = report["runner"]
        summary["runner"] = {k: r.get(k) for k in ("scheduler", "workers", "dashboard", "chunks_computed", "chunks_reused")}
    if "closed_loop" in report:
        summary["closed_loop"] = {k: report["closed_loop"][k] for k in ("runs", "violations")}
    print(json.dumps(summary, indent=2, default=_json_default))
    if report["audit"]["violations"]:
        print("error: the audit found transitions missing from the abstraction (a soundness bug)", file=sys.stderr)
        return 3
    if report.get("closed_loop", {}).get("violations"):
        print(f"error: closed-loop runs violated the specification: {report['closed_loop']['first_violation']}",
              file=sys.stderr)
        return 3
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from pipelines.controller import load_controller
    from pipelines.network import build_network
    from pipelines.spec.model import parse_spec
    from pipelines.spec.regions import spec_regions
    from pipelines.verification.closed_loop import simulate

    controller = load_controller(args.dir)
    spec = parse_spec(controller.meta["spec"])
    network = build_network(spec, None)
    try:
        x0 = np.array([float(v) for v in args.x0.split(",")])
    except ValueError:
        raise SpecError(f"--x0 expects comma-separated numbers, got {args.x0!r}") from None
    if x0.size != network.state_dim:
        raise SpecError(f"--x0 has {x0.size} components; the system has {network.state_dim}")
    regions = spec_regions(spec, network)
    run = simulate(network, None if args.free else controller, x0, args.steps,
                   np.random.default_rng(args.seed), spec.specification.kind,
                   target=regions.get("target") or regions.get("safe"), avoid=regions.get("avoid"), choose=args.choose)
    print(json.dumps(run.as_dict()))
    return 0 if run.violation is None or args.free else 4


def cmd_schema(args: argparse.Namespace) -> int:
    from pipelines.spec.model import json_schema

    print(json.dumps(json_schema(), indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="compabs", description="Data-driven compositional abstractions and controllers.")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="abstract (and audit) the system of a job spec")
    r.add_argument("spec", help="job spec, YAML or JSON")
    r.add_argument("--out", required=True, help="output directory (report.json, relations.zarr, controller, figures)")
    r.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a spec parameter")
    r.add_argument("--audit-transitions", type=int, default=None, help="override options.audit_transitions")
    r.add_argument("--no-audit", action="store_true", help="skip the audit")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.add_argument("--no-synthesis", action="store_true", help="stop after the abstraction and its audit")
    r.add_argument("--scheduler", default=None, help="tcp://HOST:PORT of a Dask scheduler (or COMPABS_SCHEDULER)")
    r.add_argument("--workers", type=int, default=2, help="worker processes of the embedded local cluster")
    r.add_argument("--in-process", action="store_true", help="no cluster: run the per-cell stage in this process")
    r.add_argument("--overwrite", action="store_true", help="if --out holds relations of another spec, delete them")
    r.set_defaults(func=cmd_run)
    m = sub.add_parser("simulate", help="run the concrete system under a saved controller; prints JSON")
    m.add_argument("dir", help="output directory of 'compabs run'")
    m.add_argument("--x0", required=True, help="initial state, comma-separated")
    m.add_argument("--steps", type=int, default=50)
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--choose", choices=["random", "first"], default="random", help="which admissible input")
    m.add_argument("--free", action="store_true", help="all inputs 0 instead of the controller")
    m.set_defaults(func=cmd_simulate)
    s = sub.add_parser("schema", help="print the JSON Schema of job specs")
    s.set_defaults(func=cmd_schema)
    from service.audit_cmd import add_parser as add_audit_parser

    add_audit_parser(sub)
    from service.serve import add_parser as add_serve_parser

    add_serve_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except CompabsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
