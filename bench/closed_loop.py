"""Closed loops under a BDD controller: inputs drawn from the controller's node table for all runs at once
(:mod:`pipelines.symbolic.joint_table`) against the per-cell samplers it replaced (a ``let`` and exact model counts
per visited cell, :class:`pipelines.symbolic.counting.Sampler`), on the same finished job, runs and steps.

    python bench/closed_loop.py [--runs 100] [--steps 70] DIR [DIR ...]   # DIR: the --out of 'compabs run'

Each job directory's stored controller and spec give the network, the regions and the steps; both modes run
``--runs`` closed loops from the same random domain states with the same seed, and the row prints both times, the
ratio, and each mode's violations (0 expected: both draw admissible inputs, uniformly, so their runs differ).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def measure(directory: Path, runs: int, steps: int) -> dict[str, Any]:
    from pipelines.controller import Controller
    from pipelines.spec.regions import closed_loop_regions, spec_regions
    from pipelines.verification.closed_loop import run_closed_loop
    from workers import jobdir
    from workers.job_audit import _controller

    arts = jobdir.load_job(directory)
    controller = _controller(arts)
    if type(controller) is not Controller:
        raise SystemExit(f"error: {directory}: not one BDD over states and inputs ({type(controller).__name__})")
    spec, network = arts.spec, arts.network
    checked = closed_loop_regions(spec, network, spec_regions(spec, network))
    row: dict[str, Any] = {"job": str(directory), "nodes": controller.nodes}
    table = controller._joint
    for mode in ("per_cell", "joint_table"):
        # the per-cell samplers are what a LayeredController draws with: no table
        controller._joint = (lambda: None) if mode == "per_cell" else table  # type: ignore[method-assign]
        t0 = time.perf_counter()
        loop = run_closed_loop(network, controller, [], runs, steps, np.random.default_rng(spec.options.seed + 1),
                               spec.specification.kind, checked["target"], checked["avoid"], safe=checked["safe"])
        row[mode] = {"seconds": round(time.perf_counter() - t0, 2), "violations": loop.violations}
    row["ratio"] = round(row["per_cell"]["seconds"] / row["joint_table"]["seconds"], 2)
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--steps", type=int, default=70)
    args = ap.parse_args(argv)
    print(f"closed loops, {args.runs} runs of {args.steps} steps: per-cell samplers vs one node table")
    for d in args.dirs:
        r = measure(d, args.runs, args.steps)
        print(f"  {r['job']}: {r['nodes']:,} nodes; per cell {r['per_cell']['seconds']} s "
              f"({r['per_cell']['violations']} violations), node table {r['joint_table']['seconds']} s "
              f"({r['joint_table']['violations']} violations): {r['ratio']}x", flush=True)
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    raise SystemExit(main())
