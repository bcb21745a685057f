"""The ``compabs`` command.

``compabs run SPEC --out DIR`` runs a job's stages with a progress bar each and writes ``DIR/report.json``
and the relation arrays; ``compabs validate SPEC`` runs the checks that need no black-box evaluation
(:mod:`pipelines.spec.validate`), which ``run`` runs first too. ``compabs schema`` prints the spec's JSON Schema.

Every failure ends in one line ``error: ...`` on stderr and exit status 2, never a traceback: a bad argument,
a spec that cannot be read or is invalid, a directory that cannot be written or holds another spec's job, a
black box's NaN, a damaged store, even an internal error (``COMPABS_DEBUG=1`` prints its traceback too). Exit
status 3 is a violation the audit or the closed loop found, 130 an interrupt. Nothing from the spec is executed
except whitelisted expressions (and ``module:function`` names, which the local command line allows).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn, cast

import numpy as np

from pipelines.errors import CompabsError, SpecError
from service.arguments import count
from service.settings import local_caps
from workers.jobdir import json_default as _json_default

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.spec.model import JobSpec


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


#: Environment variable that makes an internal error print its traceback and keeps the workers' task-error logs.
DEBUG_ENV = "COMPABS_DEBUG"
#: Log levels of the embedded cluster's worker processes (Dask's ``logging`` setting, handed to them through
#: the environment): a failing task, e.g. a black box's NaN, is reported once as the ``error:`` line, not also
#: as the worker's "Compute Failed" record and its traceback. Memory warnings still show.
QUIET_WORKER_LOGGING = "{'distributed.worker': 'critical', 'distributed.worker.memory': 'warning'}"


def _parse_sets(items: Sequence[str]) -> dict[str, float]:
    out = {}
    for item in items:
        if "=" not in item:
            raise SpecError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        try:
            number = float(value)
        except ValueError:
            raise SpecError(f"--set {name}: {value!r} is not a number") from None
        if not math.isfinite(number):
            raise SpecError(f"--set {name}: {value!r} is not a finite number")
        out[name.strip()] = number
    return out


def _load(args: argparse.Namespace) -> JobSpec:
    """The spec of ``args.spec`` with ``--set`` (and ``--audit-transitions``) applied, validated."""
    from pipelines.spec.model import load_spec
    from pipelines.spec.validate import with_options

    spec = load_spec(args.spec, _parse_sets(args.set))
    if getattr(args, "audit_transitions", None) is not None:
        try:
            spec = with_options(spec, audit_transitions=args.audit_transitions)
        except SpecError as exc:
            raise SpecError(f"--audit-transitions {args.audit_transitions}: {exc}") from None
    return spec


@contextlib.contextmanager
def _quiet_workers() -> Iterator[None]:
    """Worker processes started meanwhile log no task errors (:data:`QUIET_WORKER_LOGGING`), unless the user set
    Dask's logging (``DASK_LOGGING``) or asked for debugging output."""
    if os.environ.get(DEBUG_ENV) or "DASK_LOGGING" in os.environ:
        yield
        return
    os.environ["DASK_LOGGING"] = QUIET_WORKER_LOGGING
    try:
        yield
    finally:
        os.environ.pop("DASK_LOGGING", None)


def cmd_validate(args: argparse.Namespace) -> int:
    """The ``validate`` subcommand: one line per check, then ``ok`` (exit 0), or one ``error:`` line (exit 2)."""
    from pipelines.spec.validate import validate_spec

    result = validate_spec(_load(args), allowed_modules=None, caps=local_caps())
    print("\n".join([*result.lines, "ok"]))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from workers.job import run_job

    spec = _load(args)  # run_job validates it (pipelines.spec.validate) before creating --out or a cluster
    bars = _Bars(not args.quiet)
    try:
        with _quiet_workers():
            report = run_job(
                spec, Path(args.out), scheduler=args.scheduler or os.environ.get("COMPABS_SCHEDULER"),
                workers=args.workers, in_process=args.in_process, progress=bars, allowed_modules=None,
                audit=not args.no_audit, synthesis=not args.no_synthesis, overwrite=args.overwrite, caps=local_caps(),
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


class Parser(argparse.ArgumentParser):
    """argparse, with a usage error as one ``error:`` line (exit 2) like every other failure of the command."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {self.prog}: {message} (see '{self.prog} --help')", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="compabs", description="Data-driven compositional abstractions and controllers.")
    # (Subcommands are Parsers too; the cast is for the subcommand modules' add_parser(sub), typed for argparse's.)
    sub = cast("argparse._SubParsersAction[argparse.ArgumentParser]", p.add_subparsers(dest="command", required=True))
    v = sub.add_parser("validate", help="check a job spec without running it (no black-box evaluation)")
    v.add_argument("spec", help="job spec, YAML or JSON")
    v.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a spec parameter")
    v.set_defaults(func=cmd_validate)
    r = sub.add_parser("run", help="abstract (and audit) the system of a job spec")
    r.add_argument("spec", help="job spec, YAML or JSON")
    r.add_argument("--out", required=True, help="output directory (report.json, relations.zarr, controller, figures)")
    r.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a spec parameter")
    r.add_argument("--audit-transitions", type=count(0), default=None, metavar="N",
                   help="override options.audit_transitions (0: no audit)")
    r.add_argument("--no-audit", action="store_true", help="skip the audit")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.add_argument("--no-synthesis", action="store_true", help="stop after the abstraction and its audit")
    r.add_argument("--scheduler", default=None, help="tls://HOST:PORT of a Dask scheduler (or COMPABS_SCHEDULER); credentials from COMPABS_TLS_*")
    r.add_argument("--workers", type=count(1, 256), default=2, help="worker processes of the embedded local cluster "
                   "(1 to 256)")
    r.add_argument("--in-process", action="store_true", help="no cluster: run the per-cell stage in this process")
    r.add_argument("--overwrite", action="store_true", help="if --out holds relations of another spec, delete them")
    r.set_defaults(func=cmd_run)
    m = sub.add_parser("simulate", help="run the concrete system under a saved controller; prints JSON")
    m.add_argument("dir", help="output directory of 'compabs run'")
    m.add_argument("--x0", required=True, help="initial state, comma-separated")
    m.add_argument("--steps", type=count(1), default=50)
    m.add_argument("--seed", type=count(0), default=0)
    m.add_argument("--choose", choices=["random", "first"], default="random", help="which admissible input")
    m.add_argument("--free", action="store_true", help="all inputs 0 instead of the controller")
    m.set_defaults(func=cmd_simulate)
    s = sub.add_parser("schema", help="print the JSON Schema of job specs")
    s.set_defaults(func=cmd_schema)
    from service.audit_cmd import add_parser as add_audit_parser

    add_audit_parser(sub)
    from service.serve import add_credentials_parser
    from service.serve import add_parser as add_serve_parser

    add_serve_parser(sub)
    add_credentials_parser(sub)
    return p


def one_line(message: str) -> str:
    """A (possibly multi-line) message as one line: ``"invalid spec:\\n  a: x\\n  b: y"`` -> ``"invalid spec: a: x;
    b: y"``."""
    out = ""
    for part in (line.strip() for line in str(message).splitlines()):
        if part:
            out = part if not out else f"{out}{' ' if out.endswith(':') else '; '}{part}"
    return out


def _fail(message: str, status: int = 2) -> int:
    print(f"error: {one_line(message)}", file=sys.stderr)
    return status


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv``; returns the exit status (usage errors too, which argparse raises)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, its error: line printed)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    try:
        return args.func(args)
    except CompabsError as exc:
        return _fail(str(exc))
    except OSError as exc:  # a file of the job or its store that cannot be read or written
        where = f" ({exc.filename})" if exc.filename else ""
        return _fail(f"{exc.strerror or exc}{where}")
    except KeyboardInterrupt:
        return _fail("interrupted", 130)
    except Exception as exc:  # a bug: still one line; its traceback on request
        if os.environ.get(DEBUG_ENV):
            traceback.print_exc()
        return _fail(f"internal error ({type(exc).__name__}: {exc}); {DEBUG_ENV}=1 prints its traceback. Please "
                     "report it with the spec")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
