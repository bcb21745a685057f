"""The C export compiles (``cc -std=c99 -Wall -Werror -O2``) and answers as the tool does: on every domain cell
(centres, random points, cell corners), on every other cell (0) and outside the box (0); for the ten tanks
(2.2e11 domain cells) on a million domain cells drawn uniformly from the export's BDD."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipelines.controller import Controller
from pipelines.controller_loading import load_controller
from pipelines.export.c import write_c
from pipelines.export.emit import Export, domain_cells, domain_count, export_controller, sample_domain_cells
from pipelines.grid import quantize
from pipelines.symbolic.node_table import BDDTable

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
    return build_driver(where, source)


def build_driver(where: Path, source: Path) -> Path:
    """Compile an export's C ``source`` with the driver ``where/main.c`` (warnings are errors) into ``where/drv``."""
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


def test_domain_sampling_is_uniform_over_the_domain(jobs):  # noqa: F811
    """``sample_domain_cells`` draws only domain cells, every one of them, each about equally often (a chi-square
    bound six standard deviations wide), and counts the domain exactly from the table alone."""
    rng = np.random.default_rng(12)
    for name, ctrl in cases(jobs):
        export = export_controller(ctrl, form="bdd")
        g = export.state_grid
        cells = domain_cells(export.bdd, g)
        D = cells.shape[0]
        assert domain_count(export.bdd) == D == export.sizes["domain_states"] > 0, name
        per_cell = 200
        draws = sample_domain_cells(export.bdd, g, per_cell * D, rng)
        counts = np.bincount(g.ravel(draws), minlength=g.size)
        in_domain = np.zeros(g.size, dtype=bool)
        in_domain[g.ravel(cells)] = True
        assert np.all(counts[~in_domain] == 0) and np.all(counts[in_domain] > 0), name
        chi2 = float(((counts[in_domain] - per_cell) ** 2).sum() / per_cell)
        assert chi2 < (D - 1) + 6 * np.sqrt(2 * (D - 1)), (name, chi2, D)
    empty = BDDTable(np.zeros((0, 2), dtype=np.int64), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64),
                     np.zeros(1, dtype=np.int64), 1, np.zeros(0, dtype=np.int64))
    assert domain_count(empty) == 0 and sample_domain_cells(empty, g, 5, rng).shape == (0, g.dim)


def uniform_in_cells(g, cells: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A state drawn uniformly in each cell's part of the box, shape (B, n)."""
    lo, hi = g.clipped_cells(cells)
    return lo + rng.random(lo.shape) * (hi - lo)


def outside_the_box(g, size: int, rng: np.random.Generator) -> np.ndarray:
    """States with at least one coordinate outside the box: far, just outside (the next double beyond an edge),
    infinite or NaN."""
    lb, ub = np.asarray(g.lb), np.asarray(g.ub)
    X = rng.uniform(lb, ub, size=(size, g.dim))
    rows = np.arange(size)
    axis = rng.integers(0, g.dim, size)
    low = rng.random(size) < 0.5
    far = np.where(low, lb[axis] - rng.exponential(20.0, size), ub[axis] + rng.exponential(20.0, size))
    near = np.where(low, np.nextafter(lb[axis], -np.inf), np.nextafter(ub[axis], np.inf))
    special = np.array([np.nan, np.inf, -np.inf])[rng.integers(0, 3, size)]
    kind = rng.integers(0, 8, size)  # 6 in 8 far, 1 in 8 just outside, 1 in 8 special
    X[rows, axis] = np.where(kind < 6, far, np.where(kind == 6, near, special))
    return X


@pytest.mark.slow
def test_tanks_c_export_on_a_million_sampled_domain_cells(tanks_job, tmp_path):
    """The ten tanks (examples/tanks.yaml, Reach(Safe): 217,735,106,888 domain cells of 41^10, 1.6e-5 of the grid;
    the exact tree is not built above 2^21 grid cells, so the export is the BDD). The C agrees bit for bit with the
    export's tables on 10^6 domain cells drawn uniformly from the domain (a state drawn uniformly in each), its
    input is one the BDD controller allows on 300 of them, and it says "no input" (u untouched) on 10^5 states of
    the box outside the domain, on about 9 * 10^4 states in cells next to domain cells but outside the domain, and
    on 10^5 states outside the box (far, the next double beyond an edge, infinite, NaN)."""
    ctrl = load_controller(tanks_job)  # the spec's one fixed point, reach_safe, as ``compabs run`` wrote it
    assert isinstance(ctrl, Controller)
    export = export_controller(ctrl)
    assert export.form == "bdd" and export.tree is None and export.sizes["tree_nodes"] is None
    assert export.sizes["domain_states"] == domain_count(export.bdd) == 217_735_106_888
    exe = compile_driver(export, tmp_path / "c")
    g, m = export.state_grid, sum(ig.dim for ig in export.input_grids)
    table = export.controller()
    rng = np.random.default_rng(25)

    # in the domain: 10^6 cells drawn uniformly, a state drawn uniformly in each
    cells = sample_domain_cells(export.bdd, g, 1_000_000, rng)
    X = uniform_in_cells(g, cells, rng)
    idx, in_box = quantize(g, X)
    assert in_box.all() and np.array_equal(idx, cells)
    U, ok = run_c(exe, X, m)
    want, want_ok = table.input_many(X)
    assert ok.all() and want_ok.all()
    np.testing.assert_array_equal(U.view(np.int64), want.view(np.int64))  # bit for bit
    assert ctrl.in_domain(cells[:5000]).all()
    for r in rng.choice(cells.shape[0], 300, replace=False):
        assert np.any(np.all(ctrl.inputs(X[r]) == U[r], axis=1)), X[r]

    # in the box, outside the domain: uniform in the box, and in cells one step from a sampled domain cell
    # (a tenth of those are outside); kept where the tables say "outside", which the BDD controller confirms
    uniform = rng.uniform(np.asarray(g.lb), np.asarray(g.ub), size=(100_100, g.dim))
    moved = cells.copy()
    moved[np.arange(moved.shape[0]), rng.integers(0, g.dim, moved.shape[0])] += rng.choice([-1, 1], moved.shape[0])
    moved = moved[np.all((moved >= 0) & (moved < np.asarray(g.shape)), axis=1)]
    parts = []
    for Y in (uniform, uniform_in_cells(g, moved, rng)):
        idx, in_box = quantize(g, Y)
        assert in_box.all()
        _, inside = table.codes(idx)
        assert not ctrl.in_domain(idx[~inside]).any()
        parts.append(Y[~inside])
    assert parts[0].shape[0] >= 100_000 and parts[1].shape[0] >= 50_000, [p.shape for p in parts]
    X = np.concatenate(parts)
    # outside the box
    X = np.concatenate([X, outside_the_box(g, 100_000, rng)])
    U, ok = run_c(exe, X, m)
    _, want_ok = table.input_many(X)
    assert not ok.any() and not want_ok.any()
    assert np.all(U == -1e300)  # u untouched
