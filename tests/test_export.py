"""Controllers that leave the tool (issue 25): determinized, minimised, JSON/CSV, read back, queried at a state."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from pipelines.controller import Controller, LayeredController, controller_of
from pipelines.controller_loading import load_controller
from pipelines.errors import CompabsError, SpecError
from pipelines.export.determinize import determinize, determinized_at
from pipelines.export.emit import domain_cells, export_controller, write_csv, write_json
from pipelines.export.table import ExportedController, ExportError, load_export
from pipelines.grid import UniformGrid, quantize
from pipelines.spec.model import load_spec
from pipelines.synthesis.options import SynthesisOptions
from pipelines.synthesis.synthesize import synthesize
from service import export_cmd
from workers.job import run_abstraction

from .conftest import EXAMPLES


def make_job(spec_path: Path, out: Path) -> Path:
    """Abstraction and synthesis in this process; every fixed point's controller saved as ``controller_<key>``
    (the first also as ``controller``), with the header ``compabs run`` writes."""
    spec = load_spec(spec_path)
    res = run_abstraction(spec, audit=False)
    net = res.network
    cpre, results, _ = synthesize(net, res.relations, res.interconnection, spec.specification,
                                  SynthesisOptions(reach_and_stay_methods=tuple(spec.options.fixed_points)))
    meta = {"kind": spec.specification.kind, "state_grid": net.composed_state_grid().describe(),
            "input_grids": [s.input_grid.describe() for s in net.subsystems], "spec": spec.model_dump(mode="json")}
    out.mkdir(parents=True, exist_ok=True)
    for k, (key, r) in enumerate(results.items()):
        ctrl = controller_of(cpre, r, {**meta, "fixed_point": key, "domain_states": r.domain_states})
        ctrl.save(out, f"controller_{key}")
        if k == 0:
            ctrl.save(out, "controller")
    return out


def safe_spec(tmp: Path) -> Path:
    """small.yaml as a safety game on a box whose edges are cell boundaries (cells centred on the integers, box
    [0.5, 31.5]): the upper edge of the box is the boundary of the last cell and a grid point beyond it."""
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["name"] = "small_safe"
    data["subsystems"][0]["state"] = {"lb": 0.5, "ub": 31.5, "eta": 1}
    data["specification"] = {"kind": "safe", "safe": {"boxes": [{"lb": [4.5, 4.5], "ub": [27.5, 27.5]}]}}
    data["options"]["initial_states"] = [[12.3, 16.2]]
    path = tmp / "small_safe.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def jobs(tmp_path_factory) -> dict[str, Path]:
    """The small example (explicit co-Büchi and layered Reach(Safe) controllers) and the 2-D safety game."""
    tmp = tmp_path_factory.mktemp("export_jobs")
    return {"small": make_job(EXAMPLES / "small.yaml", tmp / "small"),
            "safe": make_job(safe_spec(tmp), tmp / "safe")}


def cases(jobs):
    yield "cobuchi", load_controller(jobs["small"], "controller_cobuchi")
    yield "reach_safe", load_controller(jobs["small"], "controller_reach_safe")
    yield "safe", load_controller(jobs["safe"], "controller_safe")


# ============================================================================ quantizer (the upper-edge bug)
BOUNDARY_GRID = UniformGrid.covering([0.5, 0.0], [3.5, 2.0], [1.0, 1.0])


def test_a_state_on_the_upper_edge_of_the_box_gets_the_last_cell():
    g = BOUNDARY_GRID
    assert g.shape == (3, 3)  # cells [0.5, 1.5], [1.5, 2.5], [2.5, 3.5] x centres 0, 1, 2
    X = np.array([[3.5, 2.0], [0.5, 0.0], [1.5, 1.0], [3.5 + 1e-12, 1.0], [0.5 - 1e-3, 1.0], [np.nan, 1.0],
                  [2.0, -0.5]])
    idx, ok = quantize(g, X)
    np.testing.assert_array_equal(ok, [True, True, True, False, False, False, False])
    np.testing.assert_array_equal(idx[:3], [[2, 2], [0, 0], [1, 1]])  # an inner boundary: the upper cell


@given(st.floats(0.5, 3.5), st.floats(0.0, 2.0))
def test_every_state_of_the_box_lies_in_its_cell(a, b):
    g = BOUNDARY_GRID
    idx, ok = quantize(g, np.array([[a, b]]))
    assert ok[0]
    lo, hi = g.clipped_cells(idx)
    assert np.all(lo[0] - 1e-9 <= [a, b]) and np.all([a, b] <= hi[0] + 1e-9)


def test_controller_cells_on_the_upper_edge_of_the_box(jobs):
    ctrl = load_controller(jobs["safe"], "controller_safe")
    assert isinstance(ctrl, Controller)
    ub = np.asarray(ctrl.state_grid.ub)
    idx = ctrl.cell(ub)
    assert idx is not None
    np.testing.assert_array_equal(idx, np.asarray(ctrl.state_grid.shape) - 1)
    assert ctrl.cell(ub + 1e-6) is None


def test_in_domain_is_the_domain_bdd_at_each_cell(jobs):
    """``Controller.in_domain`` walks the domain's node table for all cells at once; against one ``let`` of the
    domain BDD per cell on every cell of each grid (explicit and layered controllers), and cells off the grid
    (negative, past the last cell, past the bits' width) are in no domain."""
    for name, ctrl in cases(jobs):
        m, g = ctrl.model, ctrl.state_grid
        every = g.unravel(np.arange(g.size))
        want = np.array([m.bdd.let(m.state_assignment(c), ctrl.domain) == m.bdd.true for c in every])
        assert 0 < want.sum() < g.size, name
        np.testing.assert_array_equal(ctrl.in_domain(every), want, err_msg=name)
        inside = every[want][:3]
        off = np.repeat(inside[:1], 3, axis=0)  # an inside cell with its first code before the first cell, past
        off[:, 0] = [-1, g.shape[0], g.shape[0] * 2**20 + inside[0, 0]]  # the last, and past the bits' width
        mixed = np.concatenate([inside, off, inside])
        np.testing.assert_array_equal(ctrl.in_domain(mixed), [True] * 3 + [False] * 3 + [True] * 3, err_msg=name)
        assert ctrl.in_domain(np.zeros((0, g.dim), dtype=np.int64)).shape == (0,)


# ============================================================================ determinized and minimised
def test_the_determinized_input_is_admissible_on_every_domain_cell(jobs):
    for name, ctrl in cases(jobs):
        e = export_controller(ctrl)
        g = ctrl.state_grid
        every = g.unravel(np.arange(g.size))
        cells = domain_cells(e.bdd, g)
        np.testing.assert_array_equal(cells, every[ctrl.in_domain(every)], err_msg=name)
        assert cells.shape[0] == e.sizes["domain_states"] == ctrl.meta["domain_states"] > 0
        codes, ok = e.codes(every)
        np.testing.assert_array_equal(ok, ctrl.in_domain(every), err_msg=name)
        for cell, code in zip(cells, e.codes(cells)[0]):
            allowed = ctrl.input_indices(cell)
            assert np.any(np.all(allowed == code, axis=1)), (name, cell, code)
            assert np.array_equal(code, allowed[0]) or e.rule == "earliest_layer"  # smallest index


def test_rules_are_recorded_and_the_per_cell_answer_matches(jobs):
    got = {name: export_controller(ctrl).rule for name, ctrl in cases(jobs)}
    assert got == {"cobuchi": "smallest_index", "reach_safe": "earliest_layer", "safe": "smallest_index"}
    ctrl = load_controller(jobs["small"], "controller_reach_safe")
    assert isinstance(ctrl, LayeredController)
    e = export_controller(ctrl)
    cells = domain_cells(e.bdd, ctrl.state_grid)
    codes = e.codes(cells)[0]
    rng = np.random.default_rng(3)
    for r in rng.choice(cells.shape[0], 60, replace=False):
        np.testing.assert_array_equal(determinized_at(ctrl, cells[r]), codes[r])
    explicit = load_controller(jobs["small"], "controller_cobuchi")
    assert isinstance(explicit, Controller)
    with pytest.raises(ExportError, match="layered"):
        determinize(explicit, "earliest_layer")
    with pytest.raises(ExportError, match="unknown rule"):
        determinize(explicit, "largest")
    smallest = export_controller(ctrl, rule="smallest_index")
    for cell, code in zip(cells[:80], smallest.codes(cells[:80])[0]):
        np.testing.assert_array_equal(code, ctrl.input_indices(cell)[0])


def test_tree_and_bdd_forms_agree_on_every_cell_and_sizes_are_reported(jobs):
    for name, ctrl in cases(jobs):
        g = ctrl.state_grid
        every = g.unravel(np.arange(g.size))
        bdd, tree = export_controller(ctrl, form="bdd"), export_controller(ctrl, form="tree")
        assert tree.tree is not None and tree.sizes["tree_nodes"] > 0 and bdd.sizes["bdd_nodes"] > 0
        auto = export_controller(ctrl)
        assert auto.form == ("tree" if tree.sizes["tree_bytes"] < tree.sizes["bdd_bytes"] else "bdd"), name
        want, ok = bdd.codes(every)
        got, ok_tree = tree.controller().codes(every)
        np.testing.assert_array_equal(ok_tree, ok, err_msg=name)
        np.testing.assert_array_equal(got[ok], want[ok], err_msg=name)


# ============================================================================ JSON, CSV, read back
def test_json_export_reads_back_and_agrees_with_the_bdd_controller(jobs, tmp_path):
    rng = np.random.default_rng(5)
    for name, ctrl in cases(jobs):
        for form in ("bdd", "tree"):
            e = export_controller(ctrl, form=form)
            path = write_json(e, tmp_path / f"{name}_{form}.json")
            back = load_controller(path)
            assert isinstance(back, ExportedController)
            data = json.loads(path.read_text())
            assert data["rule"] == e.rule and data["kind"] == ctrl.meta["kind"] and data["form"] == form
            g = ctrl.state_grid
            X = rng.uniform(np.asarray(g.lb) - 1, np.asarray(g.ub) + 1, size=(400, g.dim))
            for x in X:
                u = back.input(x)
                allowed = ctrl.inputs(x)
                if allowed.shape[0] == 0:
                    assert u is None and back.inputs(x).shape == (0, ctrl.input_dim)
                else:
                    assert u is not None and np.any(np.all(allowed == u, axis=1)), (name, x)


def test_a_damaged_export_is_a_clear_error(jobs, tmp_path):
    ctrl = load_controller(jobs["small"], "controller_cobuchi")
    assert isinstance(ctrl, Controller)
    data = export_controller(ctrl).to_json()
    bad = json.loads(json.dumps(data))
    bad["bdd"]["low"][1] = 10**6
    with pytest.raises(ExportError, match="out of range"):
        ExportedController(bad)
    del data["bdd"]
    with pytest.raises(ExportError, match="missing or malformed"):
        ExportedController(data)
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(ExportError, match="not JSON"):
        load_export(tmp_path / "x.json")


def test_csv_lists_the_domain_and_refuses_past_the_cap(jobs, tmp_path):
    ctrl = load_controller(jobs["small"], "controller_cobuchi")
    assert isinstance(ctrl, Controller)
    e = export_controller(ctrl, form="bdd")
    rows = np.loadtxt(write_csv(e, tmp_path / "c.csv"), delimiter=",", skiprows=1)
    assert rows.shape == (e.sizes["domain_states"], 4)
    for row in rows[::37]:
        assert np.any(np.all(ctrl.inputs(row[:2]) == row[2:], axis=1))
    with pytest.raises(ExportError, match=r"629 cells.*--format c"):
        write_csv(e, tmp_path / "d.csv", max_rows=100)


# ============================================================================ the commands
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="compabs")
    export_cmd.add_parser(p.add_subparsers(dest="command", required=True))
    return p


def run(argv: list[str]) -> int:
    args = parser().parse_args(argv)
    return args.func(args)


def test_export_import_and_control_commands(jobs, tmp_path, capsys):
    d = str(jobs["small"])
    assert run(["export", d, "--format", "json", "--out", str(tmp_path / "e.json")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["domain_states"] == 629 and summary["bdd_nodes"] > 0
    assert run(["import", str(tmp_path / "e.json")]) == 0
    assert json.loads(capsys.readouterr().out)["rule"] == "smallest_index"
    assert run(["import", str(tmp_path / "e.json"), "--x", "16,16"]) == 0
    u = [float(v) for v in capsys.readouterr().out.split(",")]
    assert run(["control", d, "--x", "16,16", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["in_domain"] and r["determinized"] == u and u in r["inputs"]
    assert run(["control", d, "--x", "16,16"]) == 0
    assert "determinized (smallest_index rule)" in capsys.readouterr().out
    assert run(["control", d, "--x", "0,32"]) == 1
    assert "outside the controller's domain" in capsys.readouterr().out
    assert run(["control", d, "--x", "40,1"]) == 1
    assert "outside the state box" in capsys.readouterr().out
    assert run(["import", str(tmp_path / "e.json"), "--x", "0,32"]) == 1
    with pytest.raises(SpecError, match="states have 2"):
        run(["control", d, "--x", "1"])
    with pytest.raises(SpecError, match="comma-separated numbers"):
        run(["control", d, "--x", "a,b"])
    with pytest.raises(CompabsError, match="no controller"):
        run(["control", str(tmp_path), "--x", "1,2"])
    assert run(["export", d, "--format", "csv", "--out", str(tmp_path / "e.csv")]) == 0
    assert (tmp_path / "e.csv").read_text().startswith("x1,x2,u1,u2\n")
    with pytest.raises(ExportError, match="CSV limit"):
        run(["export", d, "--format", "csv", "--max-rows", "10", "--out", str(tmp_path / "f.csv")])
    new_dir = tmp_path / "new" / "dir"  # --out into a directory that does not exist yet
    assert run(["export", d, "--format", "c", "--controller", "reach_safe", "--out", str(new_dir / "ctl")]) == 0
    assert (new_dir / "ctl.c").exists() and (new_dir / "ctl.h").exists()
