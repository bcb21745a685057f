"""Growth bounds per component under matrices of Lipschitz constants, on strongly anisotropic systems (hypothesis).

Each example draws a 2-D to 4-D map whose Jacobian is far from isotropic: a rotation, a shear, or a heading that
moves the position but not the reverse (the vehicle's structure), with or without an internal input, and gives
its per-entry constants in closed form (``|d f_i / d x_j|`` bounded on the box, with a margin). The whole grid is
abstracted with each growth bound (:class:`~pipelines.abstraction.growth_bound.GrowthBound`), the constants are
checked against the samples as a job checks them, and random concrete transitions are audited: every concrete
successor's cell (both cells on a boundary) must lie in the abstract successor box. A matrix with one entry too
small is refused by the data check, naming the entry and the pair of samples; with the check left out, the audit
catches the relation it builds.
"""

from __future__ import annotations

import pickle
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipelines.abstraction.cells import abstract_chunk
from pipelines.abstraction.constants import LipschitzMatrix
from pipelines.abstraction.growth_bound import HullBound, LipschitzBound, ScpBound, growth_bound, standard_bounds
from pipelines.abstraction.lipschitz import ConstantRecord, check_constants, estimate_entries, resolve_constant
from pipelines.abstraction.relation import SlopeRecord, assemble, chunk_ranges
from pipelines.errors import LipschitzError, SpecError
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.verification.audit import audit_subsystem

from .strategies import anisotropic

SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])
BOUNDS = [("lipschitz", "paper"), ("hull", "paper"), ("scp", "paper"), ("scp", "radius")]
def _subsystem(spec: dict, internal: dict):
    """The subsystem of ``spec`` (its interconnection map is never sampled here: only the grids matter)."""
    n = len(spec["state"]["lb"])
    job: dict = {"subsystems": [spec]}
    if spec.get("reads"):
        job["interconnection"] = {"map": "[x[0]]", "internal": internal, "error": "linear"}
    else:
        job["subsystems"] = [{**spec, "lipschitz": {"x": spec["lipschitz"]["x"]}}]
    job["specification"] = {"kind": "safe", "safe": {"boxes": [{"lb": spec["state"]["lb"], "ub": spec["state"]["ub"]}]}}
    sub = build_network(parse_spec(job), None).subsystems[0]
    assert sub.n == n
    return sub


def _constants(sub) -> dict[str, ConstantRecord]:
    rng = np.random.default_rng(0)
    return {arg: resolve_constant(sub, arg, rng) for arg in ("x", "w")}


def _relation(sub, bound, chunk=7):
    res = [abstract_chunk(sub, a, b, bound, full_statistics=True) for a, b in chunk_ranges(sub, chunk)]
    return assemble(res, sub.state_grid.size, bound.name, bound.L_x, bound.L_w), res


def _slopes(res):
    sx, sw = res[0].slope_x, res[0].slope_w
    for r in res[1:]:
        sx, sw = sx.merge(r.slope_x), sw.merge(r.slope_w)
    return {"x": sx, "w": sw}


def _check_sound(sysd, method, objective, seed):
    spec, internal, kind = sysd
    sub = _subsystem(spec, internal)
    consts = _constants(sub)
    assert not consts["x"].value.is_scalar
    bound = growth_bound(method, consts["x"].value, consts["w"].value, objective)
    rel, res = _relation(sub, bound)
    # the closed-form constants hold on the data, entry by entry
    assert check_constants(sub, "s", consts, _slopes(res)), consts["x"].as_dict()
    result = audit_subsystem(sub, rel, 3_000, np.random.default_rng(seed))
    assert result.violations == 0, (kind, result.first_violation)
    return sub, rel, res


@pytest.mark.parametrize("method,objective", BOUNDS)
@settings(max_examples=12, **SETTINGS)
@given(sysd=anisotropic(2), seed=st.integers(0, 2**31 - 1))
def test_2d_anisotropic_relations_are_sound(sysd, method, objective, seed):
    _check_sound(sysd, method, objective, seed)


@pytest.mark.parametrize("method,objective", BOUNDS)
@settings(max_examples=6, **SETTINGS)
@given(sysd=anisotropic(3), seed=st.integers(0, 2**31 - 1))
def test_3d_anisotropic_relations_are_sound(sysd, method, objective, seed):
    _check_sound(sysd, method, objective, seed)


@pytest.mark.parametrize("method,objective", BOUNDS)
@settings(max_examples=3, **SETTINGS)
@given(sysd=anisotropic(4), seed=st.integers(0, 2**31 - 1))
def test_4d_anisotropic_relations_are_sound(sysd, method, objective, seed):
    _check_sound(sysd, method, objective, seed)


# ------------------------------------------------------------------------------------- the vehicle's structure
HEADING = {
    "name": "car",
    "state": {"lb": [0, 0, -1.6], "ub": [2.4, 2.4, 1.6], "eta": [0.4, 0.4, 0.4]},
    "input": {"lb": -1, "ub": 1, "eta": 1},
    "dynamics": "[x[0] + 0.9 * cos(x[2]), x[1] + 0.9 * sin(x[2]), x[2] + 0.3 * u[0]]",
    "samples": 8,
    "growth_bound": "hull",
}
TRUE = [[1, 0, 0.9], [0, 1, 0.9], [0, 0, 1]]


def _heading(L_x, **over):
    spec = {**HEADING, "lipschitz": {"x": L_x}, **over}
    job = {"subsystems": [spec], "specification": {"kind": "safe", "safe": {"boxes": [
        {"lb": HEADING["state"]["lb"], "ub": HEADING["state"]["ub"]}]}}}
    return build_network(parse_spec(job), None).subsystems[0]


def test_per_component_constants_buy_successors_on_the_heading_structure():
    """Heading moves position, not the reverse: the matrix's bounds are tighter than one constant's (its largest
    row sum) for every bound, and the hull's heading component is one cell wide where one constant made it more."""
    sub = _heading(TRUE)
    L = LipschitzMatrix(TRUE)
    one = LipschitzMatrix.scalar(L.norm, 3, 3)
    none = LipschitzMatrix.scalar(0.0, 3, 0)
    for cls in (LipschitzBound, HullBound, ScpBound):
        per = _relation(sub, cls(L, none))[0]
        flat = _relation(sub, cls(one, none))[0]
        live = ~per.blocking
        assert (~flat.blocking <= live).all()  # tighter boxes leave the box less often
        width = (per.hi - per.lo + 1)[live & ~flat.blocking]
        width_flat = (flat.hi - flat.lo + 1)[live & ~flat.blocking]
        assert (width <= width_flat).all() and (width.prod(axis=-1) < width_flat.prod(axis=-1)).any(), cls


def test_a_matrix_with_one_entry_too_small_is_refused_naming_it_and_the_pair():
    from workers.executors import InProcess
    from workers.job import _abstract_subsystem

    small = [[1, 0, 0.9], [0, 1, 0.45], [0, 0, 1]]  # d y' / d theta is up to 0.9
    sub = _heading(small)
    consts = _constants(sub)
    with pytest.raises(LipschitzError) as exc:
        _abstract_subsystem([sub], consts, InProcess(), None, lambda *a: None, 0, 1)
    msg = str(exc.value)
    assert "the given L_x[1][2] = 0.45 (component 1 of the successor along x[2]) is contradicted" in msg, msg
    m = re.search(r"slope ([0-9.]+) observed at state cell \d+ \(x in .*\), input u=\[.*\]", msg)
    assert m and 0.45 < float(m[1]) <= 0.9, msg
    pair = re.search(r"the samples \(x = \[([^\]]*)\]\) and \(x = \[([^\]]*)\]\)", msg)
    assert pair, msg
    a, b = (np.array([float(v) for v in g.split(",")]) for g in pair.groups())
    assert a[:2].tolist() == b[:2].tolist() and a[2] != b[2]  # neighbours along the heading only
    ya, yb = (sub.dynamics(p[None], np.array([[0.0]]), np.zeros((1, 0)))[0, 1] for p in (a, b))
    assert abs(ya - yb) / abs(a[2] - b[2]) == pytest.approx(float(m[1]), rel=1e-5)
    assert "L_x[1][2] >= " in msg and "on_violation: raise" in msg
    # on request it is raised instead, entry by entry, and said so
    sub = _heading(small, lipschitz={"x": small, "on_violation": "raise"})
    consts = _constants(sub)
    rel, info = _abstract_subsystem([sub], consts, InProcess(), None, lambda *a: None, 0, 1)
    lx = info["lipschitz"]["x"]
    assert lx["source"] == "raised" and lx["given"] == small
    raised = np.array(lx["matrix"])
    assert raised[1, 2] > 0.45 and np.array_equal(np.delete(raised.ravel(), 5), np.delete(np.array(small).ravel(), 5))
    assert audit_subsystem(sub, rel, 20_000, np.random.default_rng(1)).violations == 0


@pytest.mark.parametrize("method", ["lipschitz", "hull"])
def test_without_the_check_the_audit_catches_a_contradicted_entry(method):
    """The relation built with d x' / d theta = 0 (the data check left out) loses successors: the audit finds them."""
    sub = _heading(TRUE)
    wrong = LipschitzMatrix([[1, 0, 0], [0, 1, 0.9], [0, 0, 1]])
    rel, res = _relation(sub, growth_bound(method, wrong, LipschitzMatrix.scalar(0.0, 3, 0)))
    consts = {"x": ConstantRecord(wrong, "given", given=wrong), "w": ConstantRecord(LipschitzMatrix.scalar(0, 3, 0),
                                                                                  "unused")}
    with pytest.raises(LipschitzError, match=r"L_x\[0\]\[2\] = 0 "):
        check_constants(sub, "car", consts, _slopes(res))
    result = audit_subsystem(sub, rel, 50_000, np.random.default_rng(2))
    assert result.violations > 0, result


# ------------------------------------------------------------------------------------- the constants themselves
def test_a_scalar_constant_gives_the_bits_of_one_constant():
    rng = np.random.default_rng(3)
    r = rng.uniform(0, 1, (50, 3))
    L = LipschitzMatrix.scalar(1.37, 2, 3)
    assert L.is_scalar and float(L) == 1.37
    np.testing.assert_array_equal(L.deviation(r), np.broadcast_to((1.37 * r.max(axis=1))[:, None], (50, 2)))
    M = LipschitzMatrix([[1, 0, 0.3], [0.2, 0.1, 0]])
    np.testing.assert_allclose(M.deviation(r), np.minimum(M.norm * r.max(axis=1)[:, None], r @ M.entries.T))
    assert M.norm == pytest.approx(1.3) and not M.is_scalar
    assert pickle.loads(pickle.dumps(M)) == M and hash(pickle.loads(pickle.dumps(M))) == hash(M)


def test_a_raised_matrix_names_every_raise_by_its_float():
    M = LipschitzMatrix([[1, 0.3], [0, 1]])
    assert M.raised(np.array([[0.5, 0.2], [0, 1.0]]), 0.0, 1.1) == M  # nothing contradicted: nothing raised
    up = M.raised(np.array([[0, 0], [0.4, 0]]), 0.0, 1.1)  # a row that is not the largest: its sum stays below
    assert up.entries[1, 0] == pytest.approx(0.44) and float(up) > float(M) == 1.3
    E = LipschitzMatrix([[1, 0.3], [0, 1]], 1.2)  # an estimated norm, below the row sums
    up = E.raised(np.array([[0, 0], [0.1, 0]]), 0.0, 1.1)
    assert float(up) > 1.2 and float(up) == pytest.approx(1.2)  # named, not made a row sum
    S = LipschitzMatrix.scalar(1.0, 2, 2).raised(np.full((2, 2), 1.5), 1.5, 1.1)
    assert S.is_scalar and float(S) == pytest.approx(1.65)


def test_slope_records_merge_per_entry_and_survive_json():
    a = SlopeRecord(2.0, 1, 0, 0, ((2.0, 1, 0, 0), (0.5, 1, 0, 0)), (1, 2))
    b = SlopeRecord(1.0, 7, 1, 0, ((1.0, 7, 1, 0), (0.9, 8, 1, 0)), (1, 2))
    m = a.merge(b)
    assert (m.slope, m.x_cell) == (2.0, 1) and m.entries == ((2.0, 1, 0, 0), (0.9, 8, 1, 0))
    assert SlopeRecord.from_dict(m.as_dict()) == m
    assert a.merge(SlopeRecord(3.0, 5, 0, 0)).entries == ()  # a part without entries: entries unknown


def test_a_matrix_of_the_wrong_shape_is_refused_naming_the_field():
    sub = _heading([[1, 0], [0, 1]])
    with pytest.raises(SpecError, match=r"lipschitz\.x: .* 3 x 3 here, got 2 rows of lengths \[2, 2\]"):
        resolve_constant(sub, "x", np.random.default_rng(0))
    with pytest.raises(Exception, match=r"entry \[0\]\[1\] = -1"):
        _heading([[1, -1, 0], [0, 1, 0], [0, 0, 1]])


def test_estimated_entries_bound_the_data_and_see_the_structure():
    sub = _heading("estimate", lipschitz={"x": "estimate", "batches": 10, "pairs": 60})
    est = estimate_entries(sub, "x", np.random.default_rng(4), batches=10, pairs=50)
    assert (est.value >= est.max_slope).all()
    assert est.value[2, 0] == 0 and est.value[2, 1] == 0 and est.value[0, 1] == 0  # heading moves, is not moved
    assert 0.8 < est.max_slope[0, 2] <= 0.9 and 0.8 < est.max_slope[1, 2] <= 0.9
    consts = _constants(sub)
    L = consts["x"].value
    assert consts["x"].source == "estimated" and not L.is_scalar and "entries" in consts["x"].estimate
    rel, res = _relation(sub, HullBound(L, consts["w"].value))
    check_constants(sub, "car", consts, _slopes(res))
    assert audit_subsystem(sub, rel, 20_000, np.random.default_rng(5)).violations == 0


def test_standard_bounds_put_the_chosen_one_first():
    L, W = LipschitzMatrix(TRUE), LipschitzMatrix.scalar(0.0, 3, 0)
    names = [b.name for b in standard_bounds(ScpBound(L, W, "radius"))]
    assert names == ["scp_radius", "lipschitz", "hull", "scp"]
    assert growth_bound("scp", L, W, "radius") == ScpBound(L, W, "radius") != ScpBound(L, W, "paper")


def test_validate_refuses_a_matrix_of_the_wrong_shape(tmp_path, capsys):
    """``compabs validate`` refuses a Lipschitz matrix that does not fit the subsystem, naming the field and the
    shape expected, before any black-box evaluation (one error line, exit 2)."""
    import yaml

    from service.cli import main

    from .conftest import EXAMPLES

    data = yaml.safe_load((EXAMPLES / "vehicle.yaml").read_text())
    data["subsystems"][0]["lipschitz"]["x"] = [[1, 0], [0, 1]]
    spec = tmp_path / "vehicle.yaml"
    spec.write_text(yaml.safe_dump(data))
    assert main(["validate", str(spec)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: subsystems[car].lipschitz.x: a matrix of Lipschitz constants")
    assert "3 x 3 here, got 2 rows of lengths [2, 2]" in err[0]
