"""``compabs audit DIR``: re-check a finished job's stored abstraction and controller against the black boxes.

What is checked (:func:`run_audit`), always against what the job *stored* (:func:`workers.jobdir.load_job`:
the Zarr or ``.npz`` relations, ``interconnection.npz``, the controller files), never a recomputed abstraction:

* every distinct subsystem: ``N`` random concrete transitions ``x -> f(x, u, w)``, a share of them on cell
  boundaries and box edges; the successor's cell(s) must be in the stored successor range of
  ``(x̂, û, ŵ)`` unless the triple is stored as blocking (:func:`pipelines.verification.audit.audit_subsystem`);
* the interconnection: ``N`` random composed states; the cell of ``M(x)`` must be in ``M̂(x̂)``
  (:func:`pipelines.verification.audit.audit_interconnection`);
* the composition: ``N`` random composed transitions, ``w = M(x)`` computed concretely and every subsystem
  stepped with its share of it (:func:`pipelines.verification.audit.audit_composition`);
* the controller, if the job has one: closed-loop runs of the concrete system under it from random states of its
  domain (and the spec's initial states inside it); each must satisfy the specification
  (:func:`pipelines.verification.closed_loop.simulate_many`).

It prints a table, writes ``DIR/audit.json`` and exits with status 3 if anything was violated (2 for a user
error: a missing or damaged file, named).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from pipelines.errors import CompabsError

#: ``progress(part, done, total)`` for long audits.
AuditProgress = Callable[[str, int, int], None]

AUDIT_FILE = "audit.json"


def _closed_loop(arts: Any, runs: int, rng: np.random.Generator) -> dict[str, Any]:
    """Closed-loop runs of the concrete system under the job's stored controller."""
    from pipelines.verification.closed_loop import simulate_many
    from pipelines.controller import load_controller
    from workers.job import spec_regions
    from pipelines.spec.model import parse_spec, spec_hash

    controller = load_controller(arts.directory)
    ctrl_spec = controller.meta.get("spec")
    if ctrl_spec is not None and spec_hash(parse_spec(ctrl_spec)) != spec_hash(arts.spec):
        raise CompabsError(f"{arts.directory}/controller.json was synthesized for another spec than spec.json")
    spec, network = arts.spec, arts.network
    regions = spec_regions(spec, network)
    target = regions.get("target") or regions.get("safe")
    avoid = regions.get("avoid")
    kind = spec.specification.kind
    steps = (arts.report.get("closed_loop") or {}).get("steps") or spec.options.closed_loop_steps or 60
    starts: list[tuple[str, np.ndarray]] = []
    for x0 in spec.options.initial_states:
        x0 = np.asarray(x0, dtype=float)
        idx = controller.cell(x0)
        if idx is not None and bool(controller.in_domain(idx[None, :])[0]):
            starts.append(("initial", x0))
    cells = controller.sample_cells(runs, rng) if runs else np.zeros((0, network.state_dim), dtype=np.int64)
    if cells.shape[0]:
        lo, hi = controller.state_grid.clipped_cells(cells)
        starts += [("random", x) for x in rng.uniform(lo, hi)]
    violations = 0
    first = None
    t0 = time.perf_counter()
    X0 = np.array([x0 for _, x0 in starts]).reshape(len(starts), network.state_dim)
    for (origin, x0), run in zip(starts, simulate_many(network, controller.inputs, X0, int(steps), rng, kind,
                                                       target, avoid)):
        if run.violation:
            violations += 1
            first = first or f"from {x0.tolist()} ({origin}): {run.violation}"
    return {
        "runs": len(starts),
        "violations": violations,
        "first_violation": first,
        "steps": int(steps),
        "form": controller.meta.get("form", "explicit"),
        "domain_empty": cells.shape[0] == 0 and runs > 0,
        "seconds": time.perf_counter() - t0,
    }


def run_audit(
    directory: str | Path,
    transitions: int | None = None,
    seed: int | None = None,
    runs: int = 20,
    *,
    allowed_modules: Sequence[str] | None = None,
    progress: AuditProgress | None = None,
    write: bool = True,
) -> dict[str, Any]:
    """Audit a finished job's stored abstraction and controller; write ``DIR/audit.json``.

    Parameters
    ----------
    directory : path
        The job's directory (``compabs run --out``, or the service's ``DATA/jobs/<id>``).
    transitions : int, optional
        Random concrete transitions per part (each distinct subsystem, the interconnection, the composition).
        Default: the spec's ``options.audit_transitions``, or 10^6 if that is 0.
    seed : int, optional
        Seed of the random draws (default: fresh entropy; the seed used is in the result).
    runs : int
        Closed-loop runs from random domain states (0: none; the spec's initial states in the domain are always
        run).
    allowed_modules : sequence of str, optional
        Modules a ``module:function`` black box may come from (``None``: any, as on the local command line).
    progress : callable, optional
        ``progress(part, done, total)``.
    write : bool
        Write ``DIR/audit.json``.

    Returns
    -------
    dict
        ``transitions_checked``, ``violations`` (transitions and closed-loop runs), ``parts`` (per part:
        ``transitions_checked``, ``violations``, ``skipped_blocking``, ``first_violation``, ``seconds``),
        ``closed_loop`` (or ``None`` without a controller), ``seed``, ``relation_source``, ``relation_files``.

    Raises
    ------
    CompabsError
        A missing or damaged file (:class:`workers.jobdir.ArtifactError`), or a spec that no longer builds.
    """
    from workers.jobdir import load_job
    from pipelines.verification.audit import audit_composition, audit_interconnection, audit_subsystem

    report = progress or (lambda *_: None)
    arts = load_job(directory, allowed_modules)
    if transitions is None:
        transitions = arts.spec.options.audit_transitions or 1_000_000
    if transitions < 0:
        raise CompabsError(f"--transitions must be >= 0, got {transitions}")
    if seed is None:
        seed = int(np.random.SeedSequence().entropy % (2**63))
    rng = np.random.default_rng(seed)
    groups = arts.network.unique_subsystems()
    total = len(groups) + 3
    parts: dict[str, dict[str, Any]] = {}

    def timed(name: str, fn: Callable[[], Any], extra: dict[str, Any] | None = None) -> None:
        t0 = time.perf_counter()
        res = fn()
        parts[name] = {**res.as_dict(), **(extra or {}), "seconds": time.perf_counter() - t0}
        report(name, len(parts), total)

    for key, members in groups.items():
        sub = members[0]
        timed(f"subsystem {sub.name}", lambda: audit_subsystem(sub, arts.relations[key], transitions, rng),
              {"members": [m.name for m in members], "stored_as": arts.relation_files.get(key)})
    ia = arts.interconnection
    timed("interconnection", lambda: audit_interconnection(arts.network, ia, transitions, rng), {"mode": ia.mode})
    timed("composition", lambda: audit_composition(arts.network, arts.relations, ia, transitions, rng))
    closed = _closed_loop(arts, runs, rng) if arts.has_controller else None
    report("closed loop", total, total)
    checked = sum(p["transitions_checked"] for p in parts.values())
    violations = sum(p["violations"] for p in parts.values())
    result = {
        "directory": str(arts.directory),
        "job": arts.spec.name,
        "seed": seed,
        "transitions_per_part": transitions,
        "relation_source": arts.relation_source,
        "relation_files": arts.relation_files,
        "transitions_checked": checked,
        "transition_violations": violations,
        "violations": violations + (closed["violations"] if closed else 0),
        "parts": parts,
        "closed_loop": closed,
    }
    if write:
        path = arts.directory / AUDIT_FILE
        tmp = path.with_name(path.name + ".partial")
        tmp.write_text(json.dumps(result, indent=2))
        tmp.replace(path)
    return result


def format_table(result: dict[str, Any]) -> str:
    """The audit as a plain-text table, then the first violation of each part that has one."""
    rows = [("part", "checked", "violations", "blocking (skipped)", "seconds")]
    for name, p in result["parts"].items():
        rows.append((name, f"{p['transitions_checked']:,}", f"{p['violations']:,}", f"{p['skipped_blocking']:,}",
                     f"{p['seconds']:.2f}"))
    closed = result.get("closed_loop")
    if closed is not None:
        rows.append((f"closed loop ({closed['form']} controller, {closed['steps']} steps)", f"{closed['runs']:,} runs",
                     f"{closed['violations']:,}", "-", f"{closed['seconds']:.2f}"))
    else:
        rows.append(("closed loop", "no controller", "-", "-", "-"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = []
    for k, r in enumerate(rows):
        lines.append("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))))
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    lines.append(f"seed {result['seed']}, relations from {result['relation_source']}, "
                 f"{result['transitions_checked']:,} transitions checked, {result['violations']:,} violations")
    for name, p in result["parts"].items():
        if p["first_violation"]:
            lines.append(f"first violation ({name}): {p['first_violation']}")
    if closed is not None and closed["first_violation"]:
        lines.append(f"first violation (closed loop): {closed['first_violation']}")
    return "\n".join(lines)


def cmd_audit(args: argparse.Namespace) -> int:
    """The ``audit`` subcommand: 0 if nothing is violated, 3 otherwise (2 for a user error, raised)."""
    result = run_audit(args.dir, args.transitions, args.seed, args.runs)
    print(format_table(result))
    if result["violations"]:
        print(f"error: the audit of {args.dir} found {result['violations']} violations (details in "
              f"{Path(args.dir) / AUDIT_FILE}): the stored abstraction or controller is unsound", file=sys.stderr)
        return 3
    return 0


def add_parser(sub: Any) -> None:
    """Register ``compabs audit`` on the CLI's subparsers."""
    a = sub.add_parser("audit", help="re-check a finished job's stored abstraction and controller; writes DIR/audit.json")
    a.add_argument("dir", help="output directory of 'compabs run' (or a service job's directory)")
    a.add_argument("--transitions", type=int, default=None, metavar="N",
                   help="random concrete transitions per part (default: the spec's options.audit_transitions)")
    a.add_argument("--seed", type=int, default=None, help="seed of the random draws (default: fresh, reported)")
    a.add_argument("--runs", type=int, default=20, help="closed-loop runs from random domain states (default 20)")
    a.set_defaults(func=cmd_audit)
