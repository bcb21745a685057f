"""``compabs audit DIR``: the stored abstraction and controller of a finished job, checked against the black boxes.

The job here is small.yaml run in-process; its relations are in ``relations.zarr`` as a cluster run's are (one
format), and a cluster run is audited in ``tests/test_trust_cluster.py``. Each corruption test damages one stored array in a copy of the job and
expects exit status 3 with the part and the cell named: the audit must read what was stored, not recompute it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
import zarr

from service.cli import main
from workers.jobdir import INTERCONNECTION_ARRAYS, load_interconnection, load_job

from .conftest import EXAMPLES
from .trust_log import record


def small_spec_file(directory: Path, **options) -> Path:
    """small.yaml with fewer closed-loop runs and audit transitions (seconds instead of ten)."""
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"] = {**data.get("options", {}), "closed_loop_runs": 5, "audit_transitions": 50_000, **options}
    path = directory / "small.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def small_job(tmp_path_factory) -> Path:
    """A finished in-process job of small.yaml (with its controller)."""
    base = tmp_path_factory.mktemp("audit")
    out = base / "job"
    assert main(["run", str(small_spec_file(base)), "--out", str(out), "--quiet", "--in-process"]) == 0
    return out


@pytest.fixture
def job(small_job, tmp_path) -> Path:
    """A private copy of the finished job (tests may damage it)."""
    return Path(shutil.copytree(small_job, tmp_path / "job"))


def shrink_one_interval(relations: dict[str, np.ndarray], sub) -> tuple[int, int, int, int]:
    """Remove from one stored successor interval the cell the concrete system reaches from the cell's centre.

    Picks a non-blocking triple with at least two successor cells, so that the interval stays non-empty, and
    excludes the cell of ``f(centre of x̂, û, centre of ŵ)``: concrete states near the centre land there.

    Returns ``(x, u, w, removed cell)``.
    """
    lo, hi, blocking = relations["lo"], relations["hi"], relations["blocking"]
    xg, ug, wg = sub.state_grid, sub.input_grid, sub.internal_grid
    for x in range(xg.size // 3, xg.size):
        for u in range(ug.size):
            for w in range(wg.size // 2, wg.size):
                if blocking[x, u, w] or hi[x, u, w, 0] <= lo[x, u, w, 0]:
                    continue
                xc = xg.points(xg.unravel(np.array([x])))
                uc = ug.points(ug.unravel(np.array([u])))
                wc = wg.points(wg.unravel(np.array([w])))
                c = int(xg.cell_of(sub.dynamics(xc, uc, wc))[0][0, 0])
                if c == lo[x, u, w, 0]:
                    lo[x, u, w, 0] = c + 1
                else:
                    hi[x, u, w, 0] = c - 1
                return x, u, w, c
    raise AssertionError("no triple with two successors")


def audit(job: Path, capsys, *extra: str) -> tuple[int, str, str, dict]:
    code = main(["audit", str(job), "--transitions", "100000", "--seed", "7", *extra])
    cap = capsys.readouterr()
    result = json.loads((job / "audit.json").read_text()) if (job / "audit.json").exists() else {}
    return code, cap.out, cap.err, result


def test_a_finished_job_passes_its_audit(job, capsys):
    code, out, err, result = audit(job, capsys)
    assert code == 0, out + err
    parts = result["parts"]
    assert set(parts) == {"subsystem agent[0]", "interconnection", "composition"}
    assert all(p["transitions_checked"] >= 90_000 and p["violations"] == 0 for p in parts.values())
    assert parts["subsystem agent[0]"]["members"] == ["agent[0]", "agent[1]"]
    assert result["relation_source"] == "zarr" and result["seed"] == 7
    closed = result["closed_loop"]
    assert closed["runs"] >= 20 and closed["violations"] == 0 and closed["form"] in ("explicit", "layered")
    for name in parts:
        assert name in out
    assert "closed loop" in out and "0 violations" in out
    # The job's own report carries the composition and the closed loop too.
    report = json.loads((job / "report.json").read_text())
    assert {"agent[0]", "interconnection", "composition"} <= set(report["audit"]["parts"])
    assert report["audit"]["parts"]["composition"]["transitions_checked"] >= 10_000
    assert report["closed_loop"]["runs"] >= 5


def test_same_seed_same_audit(job, capsys):
    first = audit(job, capsys)[3]
    second = audit(job, capsys)[3]

    def strip(r):
        return {k: {kk: vv for kk, vv in v.items() if kk != "seconds"} for k, v in r["parts"].items()}

    assert strip(first) == strip(second)


def test_the_stored_interconnection_is_what_the_job_built(job):
    arts = load_job(job)
    ia = arts.interconnection
    spec = arts.spec
    assert ia.mode == spec.interconnection.error and len(ia.nodes) == len(arts.report["interconnection"]["nodes"])
    for node, described in zip(ia.nodes, arts.report["interconnection"]["nodes"]):
        assert node.describe() == described
    assert np.array_equal(ia.M_bar, np.asarray(arts.report["interconnection"]["M_bar"]))


def test_a_shrunk_relation_interval_is_caught(job, capsys):
    arts = load_job(job)
    (key,) = arts.relations
    group = zarr.open_group(str(job / "relations.zarr"), path=arts.relation_files[key], mode="r+",
                            use_consolidated=False)
    arrays = {k: group[k][:] for k in ("lo", "hi", "blocking")}
    sub = arts.network.subsystems[0]
    x, u, w, c = shrink_one_interval(arrays, sub)
    group["hi"][:] = arrays["hi"]
    group["lo"][:] = arrays["lo"]

    code, out, err, result = audit(job, capsys, "--runs", "0")
    assert code == 3, out + err
    part = result["parts"]["subsystem agent[0]"]
    assert part["violations"] > 0
    assert f"agent[0]: state cell {x}, input {u}, internal cell {w}" in part["first_violation"]
    assert f"in cell [{c}]" in part["first_violation"]
    comp = result["parts"]["composition"]
    assert comp["violations"] > 0 and f"state cell {x}, input {u}, internal cell {w}" in comp["first_violation"]
    assert result["parts"]["interconnection"]["violations"] == 0
    assert "error: the audit" in err and f"state cell {x}" in out
    record("audit: shrunk stored relation interval (zarr)", faults=1, failed_cleanly=1, wrong=0)


def test_a_shrunk_interconnection_node_is_caught(job, capsys):
    ia = load_interconnection(job)
    path = job / INTERCONNECTION_ARRAYS
    with np.load(path) as data:
        arrays = {k: data[k].copy() for k in data.files}
    k = [i for i, n in enumerate(ia.nodes) if n.output == "w0"][0]
    lo, hi = arrays[f"node{k}_lo"], arrays[f"node{k}_hi"]
    wide = np.argwhere(hi > lo)
    cell = tuple(wide[len(wide) // 2])
    hi[cell] = lo[cell]  # keep one output cell of several
    np.savez_compressed(path, **arrays)

    code, out, err, result = audit(job, capsys, "--runs", "0")
    assert code == 3, out + err
    assert result["parts"]["interconnection"]["violations"] > 0
    assert "not allowed" in result["parts"]["interconnection"]["first_violation"]
    assert result["parts"]["composition"]["violations"] > 0
    assert result["parts"]["subsystem agent[0]"]["violations"] == 0
    record("audit: shrunk stored interconnection node", faults=1, failed_cleanly=1, wrong=0)


def test_missing_or_foreign_files_are_named(job, tmp_path, capsys):
    (job / INTERCONNECTION_ARRAYS).unlink()
    assert main(["audit", str(job), "--transitions", "10"]) == 2
    assert "interconnection.npz" in capsys.readouterr().err

    other = tmp_path / "other"
    other.mkdir()
    assert main(["audit", str(other), "--transitions", "10"]) == 2
    assert "is not a finished job" in capsys.readouterr().err


def test_relations_of_another_spec_are_refused(job, capsys):
    spec = json.loads((job / "spec.json").read_text())
    spec["subsystems"][0]["state"]["ub"] = 30  # fewer state cells than the stored relation has
    (job / "spec.json").write_text(json.dumps(spec))
    report = json.loads((job / "report.json").read_text())
    report.pop("spec_hash")
    (job / "report.json").write_text(json.dumps(report))
    assert main(["audit", str(job), "--transitions", "10"]) == 2
    err = capsys.readouterr().err
    assert "relations.zarr" in err and "mixes two jobs" in err, err


def test_either_cell_chooses_per_coordinate_and_stays_on_the_grid():
    """A point on the upper box edge in one coordinate and on an inner cell boundary in another: each coordinate
    takes its upper or lower cell independently, and the edge coordinate never leaves the grid (the whole-point
    swap did, and grid.ravel raised 'invalid entry in coordinates array')."""
    from pipelines.grid import UniformGrid
    from pipelines.verification.audit import _either_cell

    grid = UniformGrid.covering([0.0, 0.0], [2.0, 3.0], [1.0, 1.0])  # points 0..2 and 0..3: edges at 2.5, 3.5
    x = np.tile([[2.0, 1.5]], (400, 1))  # x1 = 2 is the grid's last point; x2 = 1.5 is a boundary of cells 1, 2
    x[:200, 0] = 2.5  # the upper edge of the last cell in x1 ...
    x[:100, 0] = 0.5  # ... and an inner boundary (cells 0 and 1)
    corner = np.tile([[-0.5, 3.5]], (50, 1))  # the lower edge in x1 and the upper edge in x2 at once
    idx = _either_cell(grid, np.vstack([x, corner]), np.random.default_rng(0))
    grid.ravel(idx)  # every index is on the grid
    assert (idx[400:] == [0, 3]).all()
    idx = idx[:400]
    assert set(idx[:100, 0]) == {0, 1} and set(idx[:, 1]) == {1, 2}
    assert set(idx[100:200, 0]) == {2}  # the edge of the box: only the cell that holds it
    pairs = {tuple(r) for r in idx[:100]}
    assert len(pairs) == 4  # the coordinates are chosen independently


def test_either_cell_is_its_numpy_expression_on_the_same_draws():
    """The compiled choice against the expression it fuses (both cells, a uniform per coordinate, the other cell
    where the pick is off the grid), from the same generator state: boundaries, box edges and points outside."""
    from pipelines.grid import UniformGrid
    from pipelines.verification.audit import _either_cell

    grid = UniformGrid.covering([0.0, -1.0, 5.0], [4.0, 1.0, 9.0], [0.5, 0.25, 1.0])
    rng = np.random.default_rng(12)
    x = rng.uniform([-1.0, -2.0, 4.0], [5.0, 2.0, 10.0], (3000, 3))
    edges = np.asarray(grid.origin) + (rng.integers(-2, 20, (3000, 3)) - 0.5) * grid.eta_array
    x = np.where(rng.random((3000, 3)) < 0.5, edges, x)
    got = _either_cell(grid, x, np.random.default_rng(7))
    up, low = grid.cell_of(x, "upper")[0], grid.cell_of(x, "lower")[0]
    pick_up = np.random.default_rng(7).random(x.shape) < 0.5
    idx = np.where(pick_up, up, low)
    off = (idx < 0) | (idx >= np.asarray(grid.shape))
    np.testing.assert_array_equal(got, np.where(off, np.where(pick_up, low, up), idx))
    assert (up != low).any()
