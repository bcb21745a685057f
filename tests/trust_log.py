"""Counts of the trust campaign (issue 7): each hostile-input and fault test records what it tried.

A test calls :func:`record` with counts under the keys of :data:`COLUMNS`; the records go to this process's
list (printed as one table at the end of the pytest session by :func:`pytest_terminal_summary`, which
``tests/conftest.py`` imports, so the table shows with or without ``-s``) and, one JSON object a line, to the
file named by ``COMPABS_TRUST_LOG`` (``bench/trust.py`` sets it and sums the file). A generated campaign counts
its cases with a :class:`Tally`, which records one row and then fails the test on any wrong case.
"""

from __future__ import annotations

import json
import os
from collections import Counter
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
    "tampered": "tampered controllers refused",
    "crashed": "processes crashed (signal) (must be 0)",
}
#: Columns that must sum to 0.
MUST_BE_ZERO = ("5xx", "executed", "wrong", "crashed")

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


class Tally:
    """One row of a generated campaign: :meth:`check` counts a case and collects it if its outcome was wrong
    (instead of stopping at the first), :meth:`done` records the row, then fails the test on any wrong case.

    ``executed`` is a list that guards append to when a payload ran (its growth is the row's "payloads executed").
    """

    def __init__(self, label: str, executed: list[Any] | None = None, seed: Any = None) -> None:
        self.label, self.seed, self.n = label, seed, Counter[str]()
        self.bad: list[str] = []
        self._executed = executed if executed is not None else []
        self._start = len(self._executed)

    def check(self, ok: bool, case: str, status: int | None = None) -> None:
        """Count one case; ``status``: its HTTP status, for the 4xx and 5xx columns (None when not over HTTP)."""
        self.n["cases"] += 1
        if status is not None:
            self.n["4xx"] += 400 <= status < 500
            self.n["5xx"] += status >= 500
        if not ok:
            self.n["wrong"] += status is None or status < 500  # a 5xx has its own column
            self.bad.append(case[:600])

    def done(self, cases: str = "inputs", ok_as: str | None = None, api: bool = False) -> dict[str, Any]:
        """Record the row (the cases under the column ``cases``, those that passed under ``ok_as``), then assert
        that every case passed and that nothing was executed."""
        executed = len(self._executed) - self._start
        counts = {cases: self.n["cases"], "executed": executed, "wrong": self.n["wrong"]}
        if api:
            counts.update({"4xx": self.n["4xx"], "5xx": self.n["5xx"]})
        if ok_as:
            counts[ok_as] = self.n["cases"] - len(self.bad)
        rec = record(self.label, **counts)
        seed = f" (seed {self.seed})" if self.seed is not None else ""
        assert not self.bad, f"{self.label}: {len(self.bad)} of {self.n['cases']} cases wrong{seed}:\n" + \
            "\n".join(self.bad[:8])
        assert executed == 0, self._executed[self._start:]
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
