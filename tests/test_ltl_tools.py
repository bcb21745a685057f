"""Issue 48, the tools on controllers with memory: an ``ltl`` job (examples/robot_ltl.yaml) on both back ends,
exported as C (compiled with the system compiler and run against the job's controller on random states and
automaton states: the same next automaton state, an admissible input, the same domain), as JSON (read back equal,
a damaged one refused) and CSV; ``compabs control --q``, ``compabs simulate`` (the automaton state tracked),
``compabs audit`` (the closed loop under the product controller), the figures of ``compabs run`` and
``compabs figures``, and a reloaded BDD controller bounding its runs as the job's arrays do.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipelines.controller_integrity import ControllerIntegrityError
from pipelines.controller_loading import load_controller
from pipelines.export.memory import ExportedProductController, export_product, write_product_csv, write_product_json
from pipelines.export.memory_c import write_product_c
from pipelines.network import build_network
from pipelines.product_controller import ProductController
from pipelines.spec.model import parse_spec
from pipelines.verification.product_loop import simulate_product
from service.cli import main

from .conftest import EXAMPLES
from .test_export_c import build_driver

CC = shutil.which("cc")
BACKENDS = ("explicit", "bdd")


@pytest.fixture(scope="module")
def jobs(tmp_path_factory) -> dict[str, Path]:
    """robot_ltl run by ``compabs run`` on each back end (figures drawn, no audit)."""
    root = tmp_path_factory.mktemp("robot_ltl")
    data = yaml.safe_load((EXAMPLES / "robot_ltl.yaml").read_text())
    out = {}
    for backend in BACKENDS:
        data["options"]["synthesis_backend"] = backend
        spec = root / f"{backend}.yaml"
        spec.write_text(yaml.safe_dump(data))
        out[backend] = root / backend
        assert main(["run", str(spec), "--out", str(out[backend]), "--quiet", "--in-process", "--no-audit"]) == 0
    return out


def test_run_draws_the_figures_of_an_ltl_job(jobs):
    for backend, job in jobs.items():
        report = json.loads((job / "report.json").read_text())
        assert report["figures"] == ["trajectory.png", "phase_plane.png"], backend
        assert all((job / f).stat().st_size > 10_000 for f in report["figures"])
        example = json.loads((job / "closed_loop_example.json").read_text())
        states = example["controlled"]["automaton_states"]
        assert len(states) == len(example["controlled"]["states"]) and example["origin"] == "initial"
        assert example["controlled"]["violation"] is None
    (jobs["bdd"] / "trajectory.png").unlink()
    assert main(["figures", str(jobs["bdd"])]) == 0
    assert (jobs["bdd"] / "trajectory.png").is_file()


def test_figures_colour_by_automaton_state_and_name_the_regions(jobs):
    from pipelines.figures import figure_setting
    from pipelines.figures.automaton_plot import product_trajectory
    from pipelines.figures.phase_plane import phase_plane

    ctrl = load_controller(jobs["explicit"])
    assert isinstance(ctrl, ProductController)
    network = build_network(parse_spec(ctrl.meta["spec"]), None)
    x0 = np.array([[0.5, 0.5]])
    (run,) = simulate_product(network, ctrl, x0, None, np.random.default_rng(0), "first")
    setting = figure_setting(network, [{"x0": [0.5, 0.5], "in_domain": True}])
    assert set(setting.atoms) == {"a", "b", "o"} and setting.formula == "F(a & F(b & F a)) & G !o"
    fig = product_trajectory(setting, run, run.extra["automaton_states"], ctrl.automaton, setting.atoms)
    ax = fig.axes[0]
    labels = {t.get_text() for t in ax.texts if (t.get_gid() or "").startswith("atom_label:")}
    assert labels == {"a", "b", "o"}
    colours = {line.get_color() for line in ax.lines if (line.get_gid() or "").startswith("step:")}
    assert len(colours) == len(set(run.extra["automaton_states"][1:])) > 1
    plane = phase_plane(setting, ctrl.in_domain, [("initial", x0[0], run)])
    gids = {p.get_gid() for p in plane.axes[0].patches}
    assert {"atom:a:0", "atom:b:0", "atom:o:0"} <= gids


def _states(ctrl: ProductController, rng: np.random.Generator) -> np.ndarray:
    """Cell centres, random points of the box and around it, the regions' box corners, NaN."""
    g = ctrl.state_grid
    lb, ub = np.asarray(g.lb), np.asarray(g.ub)
    centres = g.points(g.unravel(np.arange(g.size)))
    inside = rng.uniform(lb, ub, size=(1500, g.dim))
    around = rng.uniform(lb - 0.5, ub + 0.5, size=(300, g.dim))
    boxes = [c for atom in ctrl.meta["regions"].values() for lo, hi in atom
             for c in (lo, hi, [lo[0], hi[1]], [hi[0], lo[1]])]
    return np.concatenate([centres, inside, around, np.asarray(boxes, dtype=float), np.full((1, g.dim), np.nan)])


def _compile(header_dir: Path, source: Path, n: int, m: int) -> Path:
    """A driver reading rows (x, q) as doubles, writing (ok, q_next, u) as doubles."""
    (header_dir / "main.c").write_text(f"""#include <stdio.h>
#include "ctl.h"
int main(void)
{{
    double row[{n + 1}], u[{m}], o[{m + 2}];
    while (fread(row, sizeof(double), {n + 1}, stdin) == {n + 1}) {{
        int q_next = -7;
        for (int j = 0; j < {m}; ++j)
            u[j] = -1e300;
        o[0] = compabs_step(row, (int)row[{n}], u, &q_next);
        o[1] = q_next;
        for (int j = 0; j < {m}; ++j)
            o[j + 2] = u[j];
        fwrite(o, sizeof(double), {m + 2}, stdout);
    }}
    return 0;
}}
""")
    return build_driver(header_dir, source)


@pytest.mark.skipif(CC is None, reason="no C compiler")
@pytest.mark.parametrize("backend", BACKENDS)
def test_the_c_export_steps_as_the_controller(jobs, backend, tmp_path):
    ctrl = load_controller(jobs[backend])
    assert isinstance(ctrl, ProductController)
    export = export_product(ctrl)
    _, source = write_product_c(export, tmp_path / "ctl")
    n, m = ctrl.state_grid.dim, ctrl.input_dim
    exe = _compile(tmp_path, source, n, m)
    rng = np.random.default_rng(5)
    X = _states(ctrl, rng)
    n_q = ctrl.automaton.n_states
    q = rng.integers(-1, n_q + 1, size=X.shape[0])  # -1 and n_q: no automaton state
    rows = np.concatenate([X, q[:, None].astype(float)], axis=1)
    out = np.frombuffer(subprocess.run([str(exe)], input=rows.tobytes(), capture_output=True, check=True).stdout)
    out = out.reshape(-1, m + 2)
    ok, q_next, U = out[:, 0] == 1, out[:, 1].astype(np.int64), out[:, 2:]
    bad = (q < 0) | (q >= n_q)
    assert not ok[bad].any() and (q_next[bad] == -7).all()
    good = np.flatnonzero(~bad)
    expected = ctrl.automaton_state_after(q[good], X[good])
    assert np.array_equal(q_next[good], expected)
    idx, on = ctrl.cells(X[good])
    winning = np.zeros(good.size, dtype=bool)
    winning[on] = ctrl.winning(idx[on], expected[on])
    assert np.array_equal(ok[good], winning) and ok[good].sum() > 1000
    read_back = export.controller()
    U_py, ok_py, q_py = read_back.step(X[good], q[good])
    assert np.array_equal(ok_py, ok[good]) and np.array_equal(q_py, q_next[good])
    assert np.array_equal(U_py[ok_py], U[good][ok_py])
    for r in rng.choice(np.flatnonzero(ok), size=300, replace=False):  # the C input is one of C_q's
        admissible = ctrl.inputs(X[r], int(q_next[r]))
        assert np.any(np.all(np.isclose(admissible, U[r]), axis=1)), (X[r], q_next[r], U[r])


def test_json_and_csv_exports_read_back(jobs, tmp_path):
    ctrl = load_controller(jobs["explicit"])
    assert isinstance(ctrl, ProductController)
    export = export_product(ctrl)
    path = write_product_json(export, tmp_path / "ctl.json")
    back = load_controller(path)
    assert isinstance(back, ExportedProductController)
    stored = json.loads(path.read_text())
    assert {k: v for k, v in stored.items() if k != "integrity"} == json.loads(json.dumps(export.to_json()))
    assert back.automaton.to_json() == ctrl.automaton.to_json()
    # The other back end's controller exports the same automaton and, per state, the same domain.
    other = export_product(load_controller(jobs["bdd"]))  # type: ignore[arg-type]
    assert other.sizes["winning_cells_per_state"] == export.sizes["winning_cells_per_state"]
    files = write_product_csv(export, tmp_path / "ctl.csv")
    rows = np.loadtxt(files[0], delimiter=",", skiprows=1)
    assert rows.shape[0] == sum(export.sizes["winning_cells_per_state"])
    U, ok = back.input_many(rows[:, 1:3], rows[:, 0].astype(np.int64))
    assert ok.all() and np.allclose(U, rows[:, 3:])
    table = np.loadtxt(files[1], delimiter=",", skiprows=1, dtype=np.int64)
    assert np.array_equal(table[:, 3:], ctrl.automaton.delta) and table[ctrl.automaton.initial, 1] == 1
    assert np.loadtxt(files[2], delimiter=",", skiprows=1).shape == (3, 5)
    # A damaged export is refused, naming it.
    text = path.read_text()
    path.write_text(text.replace('"accepting":[', '"accepting":[0,', 1))
    with pytest.raises(ControllerIntegrityError, match="ctl.json: its checksum differs"):
        load_controller(path)
    path.write_text(json.dumps({k: v for k, v in stored.items() if k != "integrity"}))
    with pytest.raises(ControllerIntegrityError, match="no integrity record"):
        load_controller(path)


def test_the_cli_exports_controls_simulates_and_audits(jobs, capsys):
    job = str(jobs["bdd"])
    for fmt in ("c", "json", "csv"):
        assert main(["export", job, "--format", fmt]) == 0
    assert main(["export", job, "--format", "c", "--form", "tree"]) == 2
    assert "BDD form only" in capsys.readouterr().err
    assert main(["import", str(jobs["bdd"] / "controller_export.json"), "--x", "1,1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the export of an 'ltl' controller" in err[0]
    ctrl = load_controller(jobs["bdd"])
    assert isinstance(ctrl, ProductController)
    assert main(["control", job, "--x", "0.5,0.5", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["q"] == int(ctrl.initial_state(np.array([[0.5, 0.5]]))[0]) and r["in_domain"] and r["atoms"] == []
    assert r["determinized"] in r["inputs"] and r["layer"] == ctrl.layer_of(np.array(r["cell"]), r["q"])
    accepting = int(np.flatnonzero(ctrl.automaton.accepting)[0])
    assert main(["control", job, "--x", "0.5,0.5", "--q", str(accepting), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["accepting"]
    assert main(["control", job, "--x", "0.5,0.5", "--q", "99"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--q 99: the automaton has states 0 .." in err[0]
    assert main(["simulate", job, "--x0", "0.5,0.5", "--choose", "first"]) == 0
    run = json.loads(capsys.readouterr().out)
    assert run["states"][0] == [0.5, 0.5] and len(run["automaton_states"]) == len(run["states"])
    assert run["accepting"][-1] and run["accepted_at"] == len(run["states"]) - 1 <= run["bound"]
    assert ctrl.automaton.accepting[run["automaton_states"][-1]] and run["violation"] is None
    assert main(["simulate", job, "--x0", "2,2"]) == 2  # inside the wall: no winning product state
    assert "outside the controller's winning set" in capsys.readouterr().err
    assert main(["audit", job, "--transitions", "2000", "--seed", "1", "--runs", "30"]) == 0
    audit = json.loads((jobs["bdd"] / "audit.json").read_text())
    loop = audit["closed_loop"]
    assert loop["form"] == "product" and loop["runs"] >= 30 and loop["violations"] == 0
    assert loop["accepted"] == loop["runs"]


def test_a_reloaded_bdd_controller_keeps_its_layers(jobs):
    arrays, bdd = load_controller(jobs["explicit"]), load_controller(jobs["bdd"])
    assert isinstance(arrays, ProductController) and isinstance(bdd, ProductController) and bdd.is_symbolic
    rng = np.random.default_rng(11)
    cells = arrays.sample_cells(40, rng)
    for idx in cells:
        for q in range(arrays.automaton.n_states):
            assert arrays.layer_of(idx, q) == bdd.layer_of(idx, q), (idx, q)
    network = build_network(parse_spec(bdd.meta["spec"]), None)
    x = arrays.state_grid.points(cells)
    bounds = [[r.extra["bound"] for r in simulate_product(network, c, x, None, np.random.default_rng(1))]
              for c in (arrays, bdd)]
    assert bounds[0] == bounds[1] and len(set(bounds[0])) > 1
