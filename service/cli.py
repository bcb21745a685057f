"""The ``compabs`` command.

``compabs run SPEC --out DIR`` runs a job's stages with a progress bar each (on stderr), writes ``DIR/report.json``
and the relation arrays, controller and figures, and prints a summary for people on stdout (:func:`summary_lines`:
states, relations, domain, closed loop, audit, times, the files) or, with ``--json``, the report itself; each of
the report's ``warnings`` (an empty winning domain, initial states outside it) is a ``warning: ...`` line on
stderr. ``compabs validate SPEC`` runs the checks that need no black-box evaluation (:mod:`pipelines.spec.validate`),
which ``run`` runs first too. ``compabs schema`` prints the spec's JSON Schema; ``compabs --version`` prints
``compabs VERSION``.

Every failure ends in one line ``error: ...`` on stderr and exit status 2, never a traceback: a bad argument,
a spec that cannot be read or is invalid, a directory that cannot be written or holds another spec's job, a
black box's NaN, a damaged store, even an internal error (``COMPABS_DEBUG=1`` prints its traceback too). Exit
status 3 is a violation the audit or the closed loop found, 4 an empty winning domain when ``run`` was given
``--fail-on-empty-domain`` (for scripts and CI; without it an empty domain is a warning, status 0), 130 an
interrupt. Nothing from the spec is executed except whitelisted expressions (and ``module:function`` names,
which the local command line allows).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import threading
import time
import traceback
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, cast

import numpy as np

from pipelines.errors import CompabsError, SpecError
from service.arguments import count
from service.termination import Terminated, terminate_as_interrupt
from service.text_table import Row, format_table
from workers.huge_pages import restart_with_huge_pages

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.spec.model import JobSpec


class _Bars:
    """One tqdm progress bar per stage, fed by ``progress(stage, done, total, message)`` events (thread-safe).

    Stages follow one another, except the audit, which runs beside synthesis and the closed loop (its events come
    from another thread, :mod:`workers.processes.audit_beside`): a new stage closes the bars before it, but not an
    unfinished audit's. A stage whose total grows with its count (``total == done + 1`` after a change of total,
    e.g. synthesis counting fixed-point iterations, whose number nobody knows in advance) shows the count of
    iterations without a percentage, until its last event (``done >= total``) makes the count reached its total.
    """

    #: Stages that run beside the others.
    BESIDE = frozenset({"audit"})

    def __init__(self, enabled: bool) -> None:
        self._enabled = enabled
        self._bars: dict = {}
        self._totals: dict[str, int] = {}
        self._open_ended: set[str] = set()
        self._lock = threading.Lock()

    def __call__(self, stage: str, done: int, total: int, message: str) -> None:
        if not self._enabled:
            return
        with self._lock:
            self._update(stage, done, total, message)

    def _update(self, stage: str, done: int, total: int, message: str) -> None:
        from tqdm import tqdm

        bar = self._bars.get(stage)
        if bar is None:
            for other, old in self._bars.items():
                if other not in self.BESIDE or (old.total is not None and old.n >= old.total):
                    old.close()
            bar = self._bars[stage] = tqdm(total=total, desc=f"{stage:>15}", unit="task", leave=True, file=sys.stderr)
        if done >= total and bar.total is not None and bar.n >= bar.total:
            # A complete bar's closing event (the audit's "1/1" after its transitions) keeps its counts.
            bar.set_postfix_str(message[:60], refresh=True)
            return
        previous = self._totals.get(stage)
        self._totals[stage] = total
        if previous is not None and total != previous and 0 < done == total - 1:
            self._open_ended.add(stage)
            bar.unit = "it"
        bar.unit_scale = total >= 10_000  # 4.20M/4.20M, not 4200000/4200000
        if stage not in self._open_ended:
            bar.total, bar.n = total, done
        elif done >= total:  # its last event: the count reached is its total
            bar.n = max(bar.n, done)
            bar.total = bar.n
        else:
            bar.total, bar.n = None, done
        bar.set_postfix_str(message[:60], refresh=False)
        bar.refresh()

    def close(self) -> None:
        with self._lock:
            for bar in self._bars.values():
                bar.close()


#: Exit status of ``compabs run --fail-on-empty-domain`` when no controller exists (an empty winning domain).
EMPTY_DOMAIN_STATUS = 4
#: Environment variable that makes an internal error print its traceback and keeps the workers' task-error logs.
DEBUG_ENV = "COMPABS_DEBUG"
#: Steps of ``compabs simulate`` unless --steps says (an ``ltl`` job: its run's bound).
SIMULATE_STEPS = 50
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
    from service.settings import local_caps

    result = validate_spec(_load(args), allowed_modules=None, caps=local_caps())
    lines = list(result.lines)
    specification = result.spec.specification
    if specification.kind == "ltl":  # MONA's translation (a fraction of a second): refused here above its cap
        from workers.automata import spec_automaton

        automaton = spec_automaton(specification, result.spec.options.max_automaton_states)
        lines.append(f"specification.automaton: {automaton.n_states} states ({int(automaton.accepting.sum())} "
                     f"accepting), {automaton.n_letters} letters; options.max_automaton_states "
                     f"{result.spec.options.max_automaton_states}")
    print("\n".join([*lines, "ok"]))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """The ``run`` subcommand: the job, then its summary (or ``--json`` its report) on stdout, its warnings on
    stderr, and the exit status (module docstring)."""
    from pipelines.spec.validate import cap_synthesis_processes
    from service.settings import local_caps
    from workers.executors import Execution
    from workers.job import run_job
    from workers.jobdir import json_default
    from workers.stages import JobPolicy

    t0 = time.perf_counter()
    spec = _load(args)  # run_job validates it (pipelines.spec.validate) before creating --out or a cluster
    scheduler = args.scheduler or os.environ.get("COMPABS_SCHEDULER")
    spec = cap_synthesis_processes(spec, on_cluster=bool(scheduler))  # helpers on this machine: one per core at most
    bars = _Bars(not args.quiet)
    try:
        with _quiet_workers():
            report = run_job(
                spec, Path(args.out), Execution(scheduler=scheduler, workers=args.workers, in_process=args.in_process),
                progress=bars, policy=JobPolicy(allowed_modules=None, caps=local_caps()), audit=not args.no_audit,
                synthesis=not args.no_synthesis, overwrite=args.overwrite,
            )
    finally:
        bars.close()
    if args.json:
        print(json.dumps(report, indent=2, default=json_default))  # as report.json (workers.jobdir.write_report)
    else:
        print("\n".join(summary_lines(report, Path(args.out), time.perf_counter() - t0)))
    for warning in report.get("warnings", []):
        print(f"warning: {one_line(warning)}", file=sys.stderr)
    if report["audit"]["violations"]:
        print("error: the audit found transitions missing from the abstraction (a soundness bug)", file=sys.stderr)
        return 3
    if report.get("closed_loop", {}).get("violations"):
        print(f"error: closed-loop runs violated the specification: {report['closed_loop']['first_violation']}",
              file=sys.stderr)
        return 3
    if args.fail_on_empty_domain and report.get("domain_states") == 0:
        return _fail("the winning domain is empty (--fail-on-empty-domain)", EMPTY_DOMAIN_STATUS)
    return 0


# ====================================================================================== the run's summary
#: The summary's lines wrap at :data:`SUMMARY_WIDTH` columns (:func:`service.text_table.format_table`).
SUMMARY_WIDTH = 100


def seconds_text(seconds: float) -> str:
    """A duration for people: ``"<1 ms"``, ``"0.455 s"``, ``"12.3 s"`` (3 significant digits below a minute),
    ``"2 min 05 s"``, ``"1 h 02 min"``."""
    if seconds < 1e-3:
        return "<1 ms"
    if seconds < 59.95:
        return f"{seconds:.3g} s"
    if seconds < 3600:
        minutes, rest = divmod(round(seconds), 60)
        return f"{minutes} min {rest:02d} s"
    hours, rest = divmod(round(seconds / 60), 60)
    return f"{hours} h {rest:02d} min"


def share_text(part: float, whole: float) -> str:
    """``part`` of ``whole`` in percent, 3 significant digits (``"57.8%"``; ``"<0.01%"`` for a sliver)."""
    if whole <= 0:
        return "-"
    percent = 100 * part / whole
    if 0 < percent < 0.01:
        return "<0.01%"
    return f"{percent:.3g}%"


def _line(label: str, *parts: str) -> Row:
    """One labelled row of the summary (laid out with the others by :func:`service.text_table.format_table`)."""
    return label, parts


def _count(n: int, noun: str) -> str:
    return f"{n:,} {noun}{'' if n == 1 else 's'}"


def _subsystem_parts(info: dict) -> list[str]:
    """The relation of one distinct subsystem: its (x, u, w) triples, its transitions and successor cells per
    triple under the growth bound it was computed with, its blocking share."""
    bound = info.get("growth_bound")
    means, counts = info.get("mean_successors") or {}, info.get("non_blocking") or {}
    if bound not in means:
        bound = next(iter(means), None)
    parts = [_count(int(info.get("triples", 0)), "(x, u, w) triple")]
    mean = means.get(bound)
    if mean is not None:
        parts.append(f"{_count(round(mean * counts.get(bound, 0)), 'transition')} ({mean:.3g} successors each, {bound})")
    if info.get("blocking_fraction") is not None:
        parts.append(f"{share_text(info['blocking_fraction'], 1)} blocking")
    return parts


def _runner_parts(runner: dict) -> list[str]:
    if runner.get("in_process"):
        where = "in this process"
    else:
        where = f"on {_count(int(runner.get('workers') or 0), 'worker')}"
        if runner.get("scheduler") and not runner.get("embedded"):
            where += f" of {runner['scheduler']}"
    return [f"{runner.get('chunks_computed', 0):,} computed", f"{runner.get('chunks_reused', 0):,} reused", where]


def _file_lines(report: dict, out: Path) -> list[Row]:
    """The job's files: report, relations, controller (its header; its DDDMP files, or an explicit game's arrays, lie
    beside it), figures."""
    from workers import jobdir

    lines = [_line("report", str(out / jobdir.REPORT)), _line("relations", str(out / jobdir.RELATIONS))]
    files = list(report.get("controller", {}).get("files", []))
    headers = [f for f in files if f.endswith(".json")]
    if headers:
        others = len(files) - len(headers)
        kind = "array file" if report.get("controller", {}).get("form") == "array" else "BDD file"
        more = f" (and {_count(others, kind)} beside it)" if others else ""
        lines.append(_line("controller", *(str(out / f) for f in headers[:-1]), str(out / headers[-1]) + more))
    elif files:
        lines.append(_line("controller", *(str(out / f) for f in files)))
    if report.get("figures"):
        lines.append(_line("figures", *(str(out / f) for f in report["figures"])))
    return lines


def summary_lines(report: dict, out: Path, total_seconds: float | None = None) -> list[str]:
    """The summary ``compabs run`` prints: what the job found and where its files are, for people.

    Parameters
    ----------
    report : dict
        The job's report (:func:`workers.job.run_job`).
    out : Path
        The job directory, as given (``--out``): the files are named under it.
    total_seconds : float, optional
        The command's wall time (the stages' sum overstates it: the audit runs beside synthesis).

    Returns
    -------
    list of str
        One line each (wrapped at :data:`SUMMARY_WIDTH` columns); no Dask dashboard (it closed with the command's
        cluster).
    """
    from workers.stages import STAGES

    states = int(report["abstract_states"])
    header = f"{report['name']}: {_count(states, 'abstract state')}, {report.get('subsystem_count', '?')} subsystems"
    lines: list[Row] = []
    for info in report.get("subsystems", []):
        members = info.get("members") or [info["name"]]
        label = info["name"] + (f" ×{len(members):,}" if len(members) > 1 else "")
        lines.append(_line(label, *_subsystem_parts(info)))
    for name, region in (report.get("regions") or {}).items():
        lines.append(_line(name, f"{_count(region['states'], 'state')} ({share_text(region['states'], states)})"))
    if "domain_states" in report:
        domain = int(report["domain_states"])
        parts = [f"{_count(domain, 'state')} ({share_text(domain, states)} of the states)"]
        fixed = report.get("controller", {}).get("fixed_point")
        others = {k: n for k, n in (report.get("domain_states_by_fixed_point") or {}).items() if k != fixed}
        if fixed and others:
            parts.append(f"{fixed} fixed point (" + "; ".join(f"{k}: {n:,}" for k, n in others.items()) + ")")
        syn = report.get("synthesis") or {}
        if syn.get("quotient"):  # a sound domain, not the maximal one: say so where the number is read
            q = syn["quotient"]
            at_most = (syn.get("domain_bound") or {}).get("domain_states_at_most")
            rounds = q.get("refine_rounds") or 0
            grown = f", grown on the fine grid ({rounds} round{'s' * (rounds != 1)} at most)" if rounds else ""
            parts.append(f"from the quotient of level {q['level']}{grown}, not maximal"
                         + (f" (the maximal one has at most {at_most:,})" if at_most is not None else ""))
        lines.append(_line("domain", *parts))
        resumed = ((report.get("synthesis") or {}).get("checkpoints") or {}).get("resumed_at_iteration") or {}
        if resumed:
            lines.append(_line("resumed", *(f"{k} from iteration {n}" for k, n in resumed.items())))
    else:
        lines.append(_line("domain", "not synthesized"))
    loop = report.get("closed_loop")
    if loop is not None:
        parts = [_count(loop["runs"], "run"), _count(loop["violations"], "violation")]
        initial = loop.get("initial_states") or []
        if initial:
            inside = sum(bool(rec.get("in_domain")) for rec in initial)
            parts.append(f"{inside} of {len(initial)} initial states in the domain")
        lines.append(_line("closed loop", *parts))
    audit = report.get("audit", {})
    if audit.get("transitions_checked"):
        parts = [_count(audit["transitions_checked"], "transition"), _count(audit["violations"], "violation")]
        how = ["beside synthesis"] if audit.get("beside_synthesis") else ["read back from the first run"] if audit.get(
            "stored") else []
        lines.append(_line("audit", *parts, *how))
    else:
        lines.append(_line("audit", "not run"))
    if "runner" in report:
        lines.append(_line("chunks", *_runner_parts(report["runner"])))
    if total_seconds is not None:
        lines.append(_line("time", seconds_text(total_seconds)))
    seconds = report.get("stage_seconds", {})
    order = [s for s in STAGES if s in seconds] + [s for s in seconds if s not in STAGES]
    lines.append(_line("stages", *(f"{s.replace('_', ' ')} {seconds_text(seconds[s])}" for s in order)))
    return [header, *format_table(lines + _file_lines(report, out), SUMMARY_WIDTH)]


def cmd_simulate(args: argparse.Namespace) -> int:
    from pipelines.controller_loading import load_controller
    from pipelines.export.memory import ExportedProductController
    from pipelines.network import build_network
    from pipelines.product_controller import ProductController
    from pipelines.spec.model import parse_spec
    from pipelines.spec.regions import closed_loop_regions, spec_regions
    from pipelines.verification.closed_loop import simulate

    controller = load_controller(args.dir)
    if isinstance(controller, ExportedProductController):
        raise CompabsError(f"{args.dir} is the export of a controller with memory; simulate reads a job's --out "
                           "directory")
    spec = parse_spec(controller.meta["spec"])
    network = build_network(spec, None)
    try:
        x0 = np.array([float(v) for v in args.x0.split(",")])
    except ValueError:
        raise SpecError(f"--x0 expects comma-separated numbers, got {args.x0!r}") from None
    if x0.size != network.state_dim:
        raise SpecError(f"--x0 has {x0.size} components; the system has {network.state_dim}")
    if isinstance(controller, ProductController):
        return _simulate_product(network, controller, x0, args)
    regions = spec_regions(spec, network)
    run = simulate(network, None if args.free else controller, x0, args.steps or SIMULATE_STEPS,
                   np.random.default_rng(args.seed), spec.specification.kind,
                   **closed_loop_regions(spec, network, regions), choose=args.choose)
    print(json.dumps(run.as_dict()))
    return 0 if run.violation is None or args.free else 4


def _simulate_product(network: Any, controller: Any, x0: np.ndarray, args: argparse.Namespace) -> int:
    """``compabs simulate`` of an ``ltl`` job: the run tracks the automaton state and stops when it accepts
    (:func:`~pipelines.verification.product_loop.simulate_product`; ``--steps`` default: the bound its first
    product state's layer gives). The JSON adds per state of the run its automaton state, whether it accepts,
    and the bound."""
    from pipelines.verification.product_loop import simulate_product

    if args.free:
        raise SpecError("--free runs the system without a controller, and an 'ltl' job's trace is checked under its "
                        "controller with memory; leave --free out")
    if args.choose == "steady":
        raise SpecError("--choose steady is not for an 'ltl' controller (its admissible inputs change with the "
                        "automaton state); use random or first")
    idx = controller.cell(x0)
    q0 = int(controller.initial_state(x0[None, :])[0])
    if idx is None or not controller.winning(idx[None, :], q0)[0]:
        raise SpecError(f"--x0 {x0.tolist()} is outside the controller's winning set (automaton state {q0} after its "
                        "letter): no run under it is guaranteed")
    (run,) = simulate_product(network, controller, x0[None, :], args.steps, np.random.default_rng(args.seed),
                              args.choose)
    automaton = run.extra["automaton_states"]
    out = {**run.as_dict(), "automaton_states": automaton, "accepting": run.in_target.tolist(),
           "accepted_at": run.settled_at, "bound": run.extra["bound"]}
    print(json.dumps(out))
    return 0 if run.violation is None else 4


def cmd_schema(args: argparse.Namespace) -> int:
    from pipelines.spec.model import json_schema

    print(json.dumps(json_schema(), indent=2))
    return 0


def package_version() -> str:
    """compabs's version from its installed package metadata (``"unknown"`` when run from a checkout that was
    never installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("compabs")
    except PackageNotFoundError:
        return "unknown (not installed)"


class Parser(argparse.ArgumentParser):
    """argparse, with a usage error as one ``error:`` line (exit 2) like every other failure of the command."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {self.prog}: {message} (see '{self.prog} --help')", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="compabs", description="Data-driven compositional abstractions and controllers.")
    p.add_argument("--version", action="version", version=f"compabs {package_version()}")
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
    where = r.add_mutually_exclusive_group()
    where.add_argument("--in-process", dest="in_process", action="store_const", const=True, default=None,
                       help="no cluster: run the per-cell stage in this process (the default for small jobs)")
    where.add_argument("--cluster", dest="in_process", action="store_const", const=False,
                       help="start the embedded cluster even for a small job")
    r.add_argument("--overwrite", action="store_true", help="if --out holds relations of another spec, delete them")
    r.add_argument("--json", action="store_true", help="print the report (as report.json) instead of the summary")
    r.add_argument("--fail-on-empty-domain", action="store_true",
                   help=f"exit with status {EMPTY_DOMAIN_STATUS} when the winning domain is empty (no controller)")
    r.set_defaults(func=cmd_run)
    m = sub.add_parser("simulate", help="run the concrete system under a saved controller; prints JSON")
    m.add_argument("dir", help="output directory of 'compabs run'")
    m.add_argument("--x0", required=True, help="initial state, comma-separated")
    m.add_argument("--steps", type=count(1), default=None, help=f"steps (default {SIMULATE_STEPS}; an 'ltl' job: "
                   "the bound of the run's first product state)")
    m.add_argument("--seed", type=count(0), default=0)
    m.add_argument("--choose", choices=["random", "first", "steady"], default="random",
                   help="which admissible input: random, the first, or steady (the previous one while admissible)")
    m.add_argument("--free", action="store_true", help="all inputs 0 instead of the controller")
    m.set_defaults(func=cmd_simulate)
    s = sub.add_parser("schema", help="print the JSON Schema of job specs")
    s.set_defaults(func=cmd_schema)
    from service.audit_cmd import add_parser as add_audit_parser
    from service.export_cmd import add_parser as add_export_parser
    from service.figures_cmd import add_parser as add_figures_parser

    add_audit_parser(sub)
    add_figures_parser(sub)
    add_export_parser(sub)
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


#: The commands that build or evaluate BDDs, which the command line runs with huge pages for CUDD's tables
#: (:mod:`workers.huge_pages`).
HUGE_PAGE_COMMANDS = frozenset({"run", "serve", "export", "simulate"})


def _command_word(argv: Sequence[str]) -> str | None:
    """The subcommand of a command line (its first word that is not an option; ``compabs`` itself has only
    ``--version`` and ``--help``), read before the parser is built."""
    return next((a for a in argv if not a.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv``; returns the exit status (usage errors too, which argparse raises)."""
    if argv is None and _command_word(sys.argv[1:]) in HUGE_PAGE_COMMANDS:  # the command line, not main([...])
        restart_with_huge_pages()  # before the parser imports the subcommands' modules, which it would do twice
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a usage error (2, its error: line printed)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    try:
        # SIGTERM, SIGHUP: unwound like Ctrl-C, the cluster and the children stopped (serve handles its own).
        with terminate_as_interrupt() if args.command != "serve" else contextlib.nullcontext():
            return args.func(args)
    except Terminated as exc:
        return _fail(str(exc), exc.status)
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
