"""compabs latency bench (issue 47): the API answers while a job synthesizes.

    python -m bench.latency                          # consensus at N = 4 (tens of seconds of synthesis), 200 + 200
    python -m bench.latency --agents 3 --requests 10 # a small job, few requests (tests/test_bench.py)
    python -m bench.latency --json out.json          # also write the latencies as JSON

(From the repository root; ``python bench/latency.py`` is the same.)

It starts ``compabs serve`` in a child process (real HTTP on a free port of 127.0.0.1, a token, jobs in their own
processes without a Dask cluster: ``--in-process``), submits the consensus example (``examples/small.yaml``) at
``--agents`` agents, waits until the job is ``running`` in its synthesis stage (CUDD's fixed points, with the audit
beside them in a child of the job's process), and then sends ``GET /health`` and ``GET /jobs/{id}`` alternately,
one at a time, ``--requests`` of each. For each route it prints the median, the 99th percentile (nearest rank) and
the largest latency, and how many answered 200 within :data:`LIMIT` seconds; then how many of the requests were
sent while the job was still synthesizing (each ``GET /jobs/{id}`` answer says). The job is cancelled at the end.

The exit status is 0 when every request answered 200 within :data:`LIMIT` seconds.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import secrets
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import yaml

ROOT = Path(__file__).resolve().parents[1]
#: Seconds within which every request must be answered (issue 47's target).
LIMIT = 1.0
#: Seconds to wait for the server to start and for the job to reach synthesis (bounds on a hang).
START_WAIT, STAGE_WAIT = 120.0, 600.0
#: The routes measured, in the order they are sent (``{id}``: the job's).
ROUTES = ("/health", "/jobs/{id}")


def job_spec(agents: int) -> dict[str, Any]:
    """The consensus example at ``agents`` agents: its synthesis grows with them (N = 4: tens of seconds on two
    cores), and the audit beside it keeps a second core busy as a real job does."""
    data = yaml.safe_load((ROOT / "examples" / "small.yaml").read_text())
    data["parameters"]["N"] = agents
    data["options"].update({"audit_transitions": 2_000_000, "closed_loop_runs": 2, "initial_states": []})
    return data


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def percentile(values: list[float], q: float) -> float:
    """The nearest-rank ``q``-th percentile (0 < q <= 100) of ``values``."""
    ordered = sorted(values)
    return ordered[max(0, math.ceil(q / 100 * len(ordered)) - 1)]


def summary(route: str, seconds: list[float], ok: list[bool]) -> dict[str, Any]:
    """One route's numbers: count, median, p99 and max in seconds, and how many answered 200 within LIMIT."""
    within = sum(1 for s, good in zip(seconds, ok) if good and s <= LIMIT)
    return {"route": route, "n": len(seconds), "median": percentile(seconds, 50), "p99": percentile(seconds, 99),
            "max": max(seconds), "within": within}


def line(s: dict[str, Any]) -> str:
    """One printed line of a route (what tests/test_bench.py parses)."""
    return (f"GET {s['route']:<11} n {s['n']:>4}  median {s['median'] * 1e3:8.1f} ms  p99 {s['p99'] * 1e3:8.1f} ms  "
            f"max {s['max'] * 1e3:8.1f} ms  within {LIMIT:g} s: {s['within']} of {s['n']}")


def _wait(what: str, timeout: float, check: Callable[[], bool], server: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if server.poll() is not None:
            raise RuntimeError(f"the server exited with status {server.returncode} while waiting for {what}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what}: not within {timeout:g} s")
        time.sleep(0.2)


def synthesizing(job: dict[str, Any]) -> bool:
    """Whether a job's JSON shows it running in synthesis (and not yet in the closed loop after it)."""
    stages = {s["stage"] for s in job.get("stages", [])}
    return job.get("status") == "running" and "synthesis" in stages and "closed_loop" not in stages


def measure(agents: int, requests: int, log: Path, data_dir: Path) -> dict[str, Any]:
    """Start the server, submit the job, measure; the results (see :func:`summary`)."""
    token, port = secrets.token_urlsafe(16), free_port()
    env = {**os.environ, "COMPABS_TOKEN": token, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "service.cli", "serve", "--in-process", "--port", str(port), "--data",
           str(data_dir), "--log-level", "warning"]
    with open(log, "wb") as out:
        server = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    auth = {"Authorization": f"Bearer {token}"}
    try:
        with httpx.Client(base_url=base, timeout=60.0) as http:
            def up() -> bool:
                try:
                    return http.get("/health").status_code == 200
                except httpx.TransportError:
                    return False

            _wait("the server to answer /health", START_WAIT, up, server)
            r = http.post("/jobs", json=job_spec(agents), headers=auth)
            if r.status_code != 201:
                raise RuntimeError(f"POST /jobs answered {r.status_code}: {r.text[:500]}")
            job_id = r.json()["id"]
            state: dict[str, Any] = {}

            def in_synthesis() -> bool:
                state.update(http.get(f"/jobs/{job_id}", headers=auth).json())
                if state["status"] in ("succeeded", "failed", "cancelled"):
                    raise RuntimeError(f"the job ended ({state['status']}) before it was seen in synthesis: "
                                       f"{state.get('error')}")
                return synthesizing(state)

            _wait("the job to reach synthesis", STAGE_WAIT, in_synthesis, server)
            seconds: dict[str, list[float]] = {r: [] for r in ROUTES}
            ok: dict[str, list[bool]] = {r: [] for r in ROUTES}
            during = 0
            for _ in range(requests):
                for route in ROUTES:
                    t0 = time.perf_counter()
                    answer = http.get(route.format(id=job_id), headers=auth)
                    seconds[route].append(time.perf_counter() - t0)
                    ok[route].append(answer.status_code == 200)
                    if route != "/health" and answer.status_code == 200:
                        during += 2 * synthesizing(answer.json())  # this request and the /health before it
            http.delete(f"/jobs/{job_id}", headers=auth)
    finally:
        server.terminate()
        try:
            server.wait(60)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
    return {"job": job_id, "agents": agents, "limit_s": LIMIT, "during_synthesis": during,
            "sent": requests * len(ROUTES), "routes": [summary(r, seconds[r], ok[r]) for r in ROUTES]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=4, help="agents of the consensus job (default 4)")
    p.add_argument("--requests", type=int, default=200, help="requests of each route (default 200)")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON")
    args = p.parse_args(argv)
    if args.agents < 2 or args.requests < 1:
        p.error("--agents must be at least 2 and --requests at least 1")
    with tempfile.TemporaryDirectory(prefix="compabs-latency-") as d:
        log = Path(d) / "serve.log"
        try:
            res = measure(args.agents, args.requests, log, Path(d) / "data")
        except RuntimeError as exc:
            tail = log.read_text(errors="replace")[-3000:] if log.exists() else ""
            print(f"error: {exc}\nthe server's log ends:\n{tail}", file=sys.stderr)
            return 2
    print(f"compabs latency bench: job {res['job']} (consensus, {res['agents']} agents), "
          f"{res['during_synthesis']} of {res['sent']} requests sent while it synthesized")
    for s in res["routes"]:
        print(line(s))
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))
    return 0 if all(s["within"] == s["n"] for s in res["routes"]) else 1


if __name__ == "__main__":
    if not __package__:  # `python bench/latency.py`: as `python -m bench.latency` (bench/__init__.py says why)
        if not os.path.samefile(os.getcwd(), ROOT):
            sys.exit(f"bench/latency.py: run it from the repository root ({ROOT}), or as python -m bench.latency")
        os.execv(sys.executable, [sys.executable, "-m", "bench.latency", *sys.argv[1:]])
    sys.exit(main())
