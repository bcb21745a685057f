"""compabs trust campaign (issues 7 and 23): hostile inputs and injected faults, one table.

    python bench/trust.py                 # run the campaign's tests (minutes) and print the table
    python bench/trust.py --fast          # without the slow share (fewer hypothesis examples)
    python bench/trust.py --collect FILE  # only print the table of a log an earlier run wrote
    python bench/trust.py --json out.json # also write the records and totals as JSON

(From the repository root; ``python -m bench.trust`` is the same.)

It runs pytest on the trust tests with ``COMPABS_TRUST_LOG`` naming a log file: each test appends what it tried
(``tests/trust_log.py``: inputs tried, 4xx, 5xx, payloads executed, faults injected, jobs completed identical,
jobs failed cleanly, results wrong). The fault tests that live elsewhere (a worker SIGKILLed in the per-cell
stage, the runner SIGKILLed mid-job, a task that kills its workers, the API SIGKILLed mid-job and restarted) are
run too and counted when they pass (:data:`EXTERNAL`).

Issue 23's classes: numbers, costs, headers and YAML anchors against the API (``tests/test_trust_boundary.py``),
the store's integrity and the command line (``tests/test_trust_boundary_cli.py``), each drawn from
``COMPABS_TRUST_SEED`` (default 23; set it to try other inputs), and the regression tests of the defects that
record a row (``tests/test_integrity.py``, ``tests/test_cli_errors.py``). The campaign tries more than 20,000
inputs (the slow share included).

Issue 47's class: tampered controllers (``tests/test_trust_controllers.py``, drawn from the same seed): bytes of
a header, a DDDMP or NPZ payload or a JSON export changed, files truncated, removed or swapped, a controller of
another spec, a header carrying C, invalid node lines with recomputed checksums, each tried against
``load_controller``, ``compabs export/control/audit/import`` (in child processes, so that a crash shows as a signal)
and the API's download. Its columns: tampered controllers refused, and processes crashed (signal), which must be 0;
a tampered controller accepted is a wrong result.

The exit status is 0 only if every test passed, the columns that must be 0 (5xx, payloads executed,
results wrong, processes crashed) are 0 and (a full run) at least :data:`MIN_INPUTS` inputs were tried.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

#: The campaign's own test files.
TRUST_TESTS = [
    "tests/test_trust_expr.py",
    "tests/test_trust_specs.py",
    "tests/test_trust_schemathesis.py",
    "tests/test_trust_cluster.py",
    "tests/test_trust_constants.py",
    "tests/test_audit.py",
    "tests/test_trust_boundary.py",
    "tests/test_trust_boundary_cli.py",
    "tests/test_integrity.py",
    "tests/test_cli_errors.py",
    "tests/test_trust_controllers.py",
]
#: The least number of inputs the whole campaign (the slow share included) must try (issue 23).
MIN_INPUTS = 20_000
#: Fault tests of other files, counted when they pass: node id -> (label, counts).
EXTERNAL: dict[str, tuple[str, dict[str, int]]] = {
    "tests/test_workers.py::test_worker_killed_mid_job":
        ("faults: worker SIGKILLed in the per-cell stage (test_workers)", {"faults": 1, "identical": 1}),
    "tests/test_workers.py::test_runner_killed_mid_job_resumes":
        ("faults: runner SIGKILLed mid-job, resumed (test_workers)", {"faults": 1, "identical": 1}),
    "tests/test_workers.py::test_task_that_kills_its_workers_is_a_clear_error":
        ("faults: a task that kills every worker (test_workers)", {"faults": 3, "failed_cleanly": 1}),
    "tests/test_service_e2e.py::test_api_killed_mid_job_resumes_after_restart":
        ("faults: API SIGKILLed mid-job, restarted; completes, audited (test_service_e2e)", {"faults": 1}),
}


def _external_records(junit: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """Records for the EXTERNAL tests that passed, and the node ids that did not, from a JUnit XML report."""
    import xml.etree.ElementTree as ET

    passed, failed = set(), []
    for case in ET.parse(junit).getroot().iter("testcase"):
        node = case.get("classname", "").replace(".", "/") + ".py::" + case.get("name", "")
        bad = any(child.tag in ("failure", "error", "skipped") for child in case)
        if node in EXTERNAL:
            (failed.append(node) if bad else passed.add(node))
    records = [{"label": EXTERNAL[n][0], **EXTERNAL[n][1]} for n in EXTERNAL if n in passed]
    return records, failed


def run_campaign(fast: bool, log: Path) -> tuple[int, list[dict[str, Any]], list[str], float]:
    """Run the tests; return pytest's exit status, the records, the external tests that failed, the seconds."""
    junit = log.with_suffix(".xml")
    cmd = [sys.executable, "-m", "pytest", "-q", "-rfE", "-p", "no:warnings", f"--junitxml={junit}",
           *TRUST_TESTS, *EXTERNAL]
    if fast:
        cmd += ["-m", "not slow"]
    env = dict(os.environ, COMPABS_TRUST_LOG=str(log))
    t0 = time.monotonic()
    status = subprocess.run(cmd, cwd=ROOT, env=env).returncode
    seconds = time.monotonic() - t0
    records = read_log(log)
    external, failed = _external_records(junit) if junit.exists() else ([], list(EXTERNAL))
    return status, records + external, failed, seconds


def read_log(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--fast", action="store_true", help="skip the slow share (fewer generated specs)")
    p.add_argument("--collect", type=Path, default=None, help="print the table of an existing log, run nothing")
    p.add_argument("--json", type=Path, default=None, help="also write records and totals as JSON")
    args = p.parse_args(argv)
    # tests/ is a package of the repository root, as bench/ is: importable here, not where this file is read as a
    # script (bench/__init__.py)
    from tests.trust_log import COLUMNS, MUST_BE_ZERO, table, totals

    status, seconds, failed = 0, 0.0, list[str]()
    if args.collect:
        records = read_log(args.collect)
    else:
        with tempfile.TemporaryDirectory(prefix="compabs-trust-") as d:
            status, records, failed, seconds = run_campaign(args.fast, Path(d) / "trust.jsonl")
    tot = totals(records)
    print()
    print("compabs trust campaign" + (f" ({seconds:.0f} s)" if seconds else ""))
    print(table(records))
    print()
    width = max(len(v) for v in COLUMNS.values())
    for key, name in COLUMNS.items():
        flag = "  <-- must be 0" if key in MUST_BE_ZERO and tot[key] else ""
        print(f"  {name:<{width}}  {tot[key]:>7,}{flag}")
    bad = [COLUMNS[k] for k in MUST_BE_ZERO if tot[k]]
    few = not args.fast and not args.collect and tot["inputs"] < MIN_INPUTS
    if few:
        print(f"the campaign tried {tot['inputs']:,} inputs, fewer than {MIN_INPUTS:,}")
    if failed:
        print(f"external fault tests that did not pass: {failed}")
    if status:
        print(f"pytest exited with status {status}: some trust test failed (see above)")
    if args.json:
        args.json.write_text(json.dumps({"records": records, "totals": tot, "pytest_status": status,
                                         "external_failed": failed, "seconds": seconds}, indent=2))
    return 1 if (bad or failed or status or few) else 0


if __name__ == "__main__":
    if not __package__:  # `python bench/trust.py`: as `python -m bench.trust` (bench/__init__.py says why)
        if not os.path.samefile(os.getcwd(), ROOT):
            sys.exit(f"bench/trust.py: run it from the repository root ({ROOT}), or as python -m bench.trust")
        os.execv(sys.executable, [sys.executable, "-m", "bench.trust", *sys.argv[1:]])
    sys.exit(main())
