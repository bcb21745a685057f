"""``compabs audit DIR``: the command line of :func:`workers.job_audit.audit_job` (what it checks is said there).

It prints a table, writes ``DIR/audit.json`` and exits with status 3 if anything was violated (2 for a user
error: a missing or damaged file, named).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from service.arguments import count
from service.settings import local_caps
from workers import jobdir


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
    from workers.job_audit import audit_job  # the pipelines: only when auditing

    result = audit_job(args.dir, args.transitions, args.seed, args.runs, caps=local_caps())
    print(format_table(result))
    if result["violations"]:
        print(f"error: the audit of {args.dir} found {result['violations']} violations (details in "
              f"{Path(args.dir) / jobdir.AUDIT}): the stored abstraction or controller is unsound", file=sys.stderr)
        return 3
    return 0


def add_parser(sub: Any) -> None:
    """Register ``compabs audit`` on the CLI's subparsers."""
    a = sub.add_parser("audit", help="re-check a finished job's stored abstraction and controller; writes DIR/audit.json")
    a.add_argument("dir", help="output directory of 'compabs run' (or a service job's directory)")
    a.add_argument("--transitions", type=count(0), default=None, metavar="N",
                   help="random concrete transitions per part (default: the spec's options.audit_transitions)")
    a.add_argument("--seed", type=count(0), default=None, help="seed of the random draws (default: fresh, reported)")
    a.add_argument("--runs", type=count(0), default=20, help="closed-loop runs from random domain states (default 20)")
    a.set_defaults(func=cmd_audit)
