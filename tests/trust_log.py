"""Counts of the trust campaign (issue 7): each hostile-input and fault test records what it tried.

A test calls :func:`record` with counts under the keys of :data:`COLUMNS`; the records go to this process's
list (printed as one table at the end of the pytest session by :func:`pytest_terminal_summary`, which
``tests/conftest.py`` imports, so the table shows with or without ``-s``) and, one JSON object a line, to the
file named by ``COMPABS_TRUST_LOG`` (``bench/trust.py`` sets it and sums the file).
"""

from __future__ import annotations

import json
import os
from typing import Any

#: Columns of the trust table, in order, with their meaning.
COLUMNS: dict[str, str] = {
    "inputs": "inputs tried",
    "4xx": "4xx",
    "5xx": "5xx (must be 0)",
    "executed": "payloads executed (must be 0)",
    "faults": "faults injected",
    "identical": "jobs completed identical",
    "failed_cleanly": "jobs failed cleanly",
    "wrong": "results wrong (must be 0)",
}
#: Columns that must sum to 0.
MUST_BE_ZERO = ("5xx", "executed", "wrong")

RECORDS: list[dict[str, Any]] = []


def record(label: str, **counts: int) -> dict[str, Any]:
    """Record one test's counts (keys of :data:`COLUMNS`) under a label; returns the record."""
    unknown = set(counts) - set(COLUMNS)
    if unknown:
        raise ValueError(f"unknown trust columns {sorted(unknown)}")
    rec = {"label": label, **{k: int(v) for k, v in counts.items()}}
    RECORDS.append(rec)
    path = os.environ.get("COMPABS_TRUST_LOG")
    if path:
        with open(path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")
    print(f"trust: {label}: " + ", ".join(f"{COLUMNS[k]} {v}" for k, v in counts.items()))
    return rec


def totals(records: list[dict[str, Any]]) -> dict[str, int]:
    """Column sums over records."""
    return {k: sum(int(r.get(k, 0)) for r in records) for k in COLUMNS}


def table(records: list[dict[str, Any]]) -> str:
    """Per-label rows and a total row, plain text."""
    head = ["campaign"] + [COLUMNS[k] for k in COLUMNS]
    rows = [[r["label"]] + [str(r.get(k, "")) if k in r else "" for k in COLUMNS] for r in records]
    tot = totals(records)
    rows.append(["TOTAL"] + [str(tot[k]) for k in COLUMNS])
    widths = [max(len(x[i]) for x in [head] + rows) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
             for row in [head] + rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    lines.insert(len(lines) - 1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: Any) -> None:
    """Print the trust table after a session that ran any trust test."""
    if RECORDS:
        terminalreporter.write_sep("=", "trust campaign (issue 7)")
        terminalreporter.write_line(table(RECORDS))
