"""The C export compiles (``cc -std=c99 -Wall -Werror -O2``) and answers as the tool does: on every domain cell
(centres, random points, cell corners), on every other cell (0) and outside the box (0)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipelines.controller import Controller, load_controller
from pipelines.export.c import write_c
from pipelines.export.emit import Export, domain_cells, export_controller

from .test_export import cases, jobs  # noqa: F401 - the module-scoped fixture

CC = shutil.which("cc")
pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler")


def compile_driver(export: Export, where: Path) -> Path:
    """The export's C and a driver reading states (doubles) on stdin, writing ``ok, u...`` (doubles)."""
    where.mkdir(parents=True, exist_ok=True)
    _, source = write_c(export, where / "ctl")
    n, m = export.state_grid.dim, sum(g.dim for g in export.input_grids)
    (where / "main.c").write_text(f"""#include <stdio.h>
#include "ctl.h"
int main(void)
{{
    double x[{n}], u[{m}], o[{m + 1}];
    while (fread(x, sizeof(double), {n}, stdin) == {n}) {{
        for (int j = 0; j < {m}; ++j)
            u[j] = -1e300;
        o[0] = compabs_control(x, u);
        for (int j = 0; j < {m}; ++j)
            o[j + 1] = u[j];
        fwrite(o, sizeof(double), {m + 1}, stdout);
    }}
    return 0;
}}
""")
    exe = where / "drv"
    assert CC is not None
    subprocess.run([CC, "-std=c99", "-Wall", "-Werror", "-O2", "-o", str(exe), str(source), str(where / "main.c"),
                    "-lm"], check=True, capture_output=True)
    return exe


def run_c(exe: Path, X: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    out = subprocess.run([str(exe)], input=np.ascontiguousarray(X, dtype=float).tobytes(), capture_output=True,
                         check=True).stdout
    o = np.frombuffer(out).reshape(-1, m + 1)
    return o[:, 1:], o[:, 0] == 1


def states(export: Export, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Test states and how many of them are domain-cell centres: centres of every cell of the grid, random points
    and corners of domain cells, states outside the box, NaN, and the box's corners."""
    g = export.state_grid
    every = g.points(g.unravel(np.arange(g.size)))
    cells = domain_cells(export.bdd, g)
    lo, hi = g.clipped_cells(cells)
    inside = lo + rng.random(lo.shape) * (hi - lo)
    corners = np.where(rng.random(lo.shape) < 0.5, lo, hi)
    lb, ub = np.asarray(g.lb), np.asarray(g.ub)
    outside = rng.uniform(lb - 5, ub + 5, size=(2000, g.dim))
    edges = np.array([lb, ub, np.where(np.arange(g.dim) % 2, lb, ub), ub + 1e-9, lb - 1e-9,
                      np.full(g.dim, np.nan)])
    return np.concatenate([every, inside, corners, outside, edges]), every


def check(ctrl: Controller, export: Export, exe: Path, rng: np.random.Generator) -> dict[str, int]:
    X, every = states(export, rng)
    m = sum(g.dim for g in export.input_grids)
    U, ok = run_c(exe, X, m)
    want, want_ok = export.controller().input_many(X)
    np.testing.assert_array_equal(ok, want_ok)
    np.testing.assert_array_equal(U[ok], want[ok])  # bit for bit
    assert np.all(U[~ok] == -1e300)  # u untouched without an input
    # the C's input is one of the BDD controller's admissible inputs, at every domain cell's centre
    g = export.state_grid
    dom = ctrl.in_domain(g.unravel(np.arange(g.size)))
    np.testing.assert_array_equal(ok[:g.size], dom)
    for r in np.flatnonzero(dom):
        assert np.any(np.all(ctrl.inputs(every[r]) == U[r], axis=1)), every[r]
    return {"states": X.shape[0], "with_input": int(ok.sum()), "domain_cells": int(dom.sum())}


@pytest.mark.parametrize("form", ["bdd", "tree"])
def test_the_c_export_agrees_with_the_controller_everywhere(jobs, tmp_path, form):  # noqa: F811
    rng = np.random.default_rng(11)
    for name, ctrl in cases(jobs):
        export = export_controller(ctrl, form=form)
        exe = compile_driver(export, tmp_path / f"{name}_{form}")
        got = check(ctrl, export, exe, rng)
        assert got["domain_cells"] == export.sizes["domain_states"] > 0, name


@pytest.mark.slow
def test_consensus_n4_c_export_on_every_domain_cell(tmp_path):
    """Consensus with N = 4 (191,493 domain cells, 33^4 states): the layered controller's export in C agrees
    with the export's tables on every domain cell, and with the BDD controller on sampled cells."""
    import yaml

    from .conftest import EXAMPLES
    from .test_export import make_job

    data = yaml.safe_load((EXAMPLES / "consensus.yaml").read_text())
    data["parameters"]["N"] = 4
    data["options"]["initial_states"] = [[14.8, 15.8, 15.5, 15.1]]
    spec = tmp_path / "cons4.yaml"
    spec.write_text(yaml.safe_dump(data))
    job = make_job(spec, tmp_path / "job")
    ctrl = load_controller(job, "controller_reach_safe")
    assert isinstance(ctrl, Controller)
    export = export_controller(ctrl, form="bdd")
    exe = compile_driver(export, tmp_path / "c")
    g = export.state_grid
    cells = domain_cells(export.bdd, g)
    assert cells.shape[0] == export.sizes["domain_states"] == 191_493
    X = g.points(cells)
    U, ok = run_c(exe, X, 4)
    want, want_ok = export.controller().input_many(X)
    assert ok.all() and want_ok.all()
    np.testing.assert_array_equal(U, want)
    rng = np.random.default_rng(4)
    for r in rng.choice(cells.shape[0], 200, replace=False):
        assert np.any(np.all(ctrl.inputs(X[r]) == U[r], axis=1))
