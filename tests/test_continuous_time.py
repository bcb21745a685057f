"""Continuous-time subsystems (``ode``): the Runge-Kutta 4 sampled map, its checks, and sound abstractions of it."""

import math
import pickle

import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipelines.abstraction.cells import abstract_cells
from pipelines.abstraction.relation import assemble, chunk_ranges
from pipelines.errors import BlackBoxError, SpecError
from pipelines.integrators import SampledFlow, rk4
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.verification.audit import audit_subsystem

A = np.array([[-1.0, 2.0], [-0.5, -0.3]])
RHS = "[-1.0 * x[0] + 2.0 * x[1] + u[0], -0.5 * x[0] - 0.3 * x[1] + w[0]]"


def _exact_linear(x, u, w, tau):
    """x(tau) of dx/dt = A x + (u, w) with u, w held: expm of the augmented matrix [[A, b], [0, 0]]."""
    out = np.empty_like(x)
    for k in range(x.shape[0]):  # a handful of reference points
        M = np.zeros((3, 3))
        M[:2, :2], M[:2, 2] = A, [u[k, 0], w[k, 0]]
        out[k] = (scipy.linalg.expm(M * tau) @ np.append(x[k], 1.0))[:2]
    return out


def test_rk4_of_a_linear_ode_matches_the_matrix_exponential():
    flow = SampledFlow("test ode", RHS, {"x": 2, "u": 1, "w": 1}, 2, sampling_time=0.05, substeps=5)
    rng = np.random.default_rng(0)
    x, u, w = rng.uniform(-3, 3, (20, 2)), rng.uniform(-1, 1, (20, 1)), rng.uniform(-1, 1, (20, 1))
    # Local error (h ||A||)^5 / 5! ~ 3e-11 per step for h = 0.01: 1e-9 holds with room.
    np.testing.assert_allclose(flow(x, u, w), _exact_linear(x, u, w, 0.05), rtol=0, atol=1e-9)


def test_more_substeps_converge_at_fourth_order():
    rng = np.random.default_rng(1)
    x, u, w = rng.uniform(-3, 3, (10, 2)), rng.uniform(-1, 1, (10, 1)), rng.uniform(-1, 1, (10, 1))
    exact = _exact_linear(x, u, w, 1.0)
    errors = [np.abs(SampledFlow("o", RHS, {"x": 2, "u": 1, "w": 1}, 2, sampling_time=1.0, substeps=k)(x, u, w)
                     - exact).max() for k in (4, 8)]
    assert 12 < errors[0] / errors[1] < 20  # 2^4 = 16


def test_broadcast_batches_equal_row_by_row_evaluation():
    """The per-cell stage passes x as (Sx, 1, B, n), w as (Sw, B, p), u as (B, m): x is materialised once."""
    flow = SampledFlow("o", "[x[0] * x[1] + u[0], sin(x[0]) - w[0]]", {"x": 2, "u": 1, "w": 1}, 2,
                       sampling_time=0.3, substeps=3)
    rng = np.random.default_rng(2)
    X, U, W = rng.normal(size=(3, 1, 4, 2)), rng.normal(size=(4, 1)), rng.normal(size=(2, 4, 1))
    out = flow(X, U, W)
    assert out.shape == (3, 2, 4, 2)
    rows = np.broadcast_to(X, (3, 2, 4, 2)).reshape(-1, 2)
    flat = flow(rows, np.broadcast_to(U, (3, 2, 4, 1)).reshape(-1, 1), np.broadcast_to(W, (3, 2, 4, 1)).reshape(-1, 1))
    np.testing.assert_array_equal(out.reshape(-1, 2), flat)


def test_a_module_function_rhs_integrates_like_the_expression():
    expr = SampledFlow("e", "[-x[0] + u[0]]", {"x": 1, "u": 1, "w": 0}, 1, sampling_time=0.2, substeps=4)
    mod = SampledFlow("m", "tests.test_continuous_time:decay", {"x": 1, "u": 1, "w": 0}, 1, None, None,
                      sampling_time=0.2, substeps=4)
    x, u = np.linspace(-1, 1, 7)[:, None], np.full((1, 1), 0.5)
    np.testing.assert_allclose(mod(x, u, np.zeros((1, 0))), expr(x, u, np.zeros((1, 0))), rtol=1e-15)


def decay(x, u, w):
    return -x + u


def test_rk4_is_the_classical_scheme():
    # dx/dt = x from 1 over one step h: 1 + h + h^2/2 + h^3/6 + h^4/24
    h = 0.3
    assert rk4(lambda y: y, np.ones(1), h, 1)[0] == pytest.approx(sum(h**k / math.factorial(k) for k in range(5)))


def test_a_flow_pickles_as_its_source():
    flow = SampledFlow("o", RHS, {"x": 2, "u": 1, "w": 1}, 2, sampling_time=0.1, substeps=7)
    state = flow.__getstate__()
    assert state["_fn"] is None and state["_source"] == RHS
    back = pickle.loads(pickle.dumps(flow))
    assert (back.sampling_time, back.substeps) == (0.1, 7)
    pts = np.ones((3, 2)), np.ones((3, 1)), np.ones((3, 1))
    np.testing.assert_array_equal(back(*pts), flow(*pts))


def _spec(sub, **extra):
    base = {
        "name": "s", "state": {"lb": -2, "ub": 2, "eta": 0.25}, "input": {"lb": -1, "ub": 1, "eta": 0.5},
        "lipschitz": {"x": 1.5}, "samples": 10,
    }
    return {"subsystems": [{**base, **sub}], "specification": {"kind": "safe", "safe": {"boxes": [{"lb": -1, "ub": 1}]}},
            **extra}


def test_a_blow_up_during_integration_names_the_cell():
    net = build_network(parse_spec(_spec({"ode": "exp(3 * x[0])", "sampling_time": 2.0, "substeps": 2})))
    sub = net.subsystems[0]
    assert isinstance(sub.dynamics, SampledFlow)
    with pytest.raises(BlackBoxError, match=r"subsystem 's' ode: integrated over the sampling time to .*not finite.*"
                                            r"state cell \d+"):
        abstract_cells(sub, 0, sub.state_grid.size, 1.5, 0.0, "hull", "paper")


@pytest.mark.parametrize("sub,message", [
    ({"ode": "-x[0]"}, "an 'ode' needs 'sampling_time'"),
    ({"ode": "-x[0]", "dynamics": "x[0]", "sampling_time": 0.1}, "give either 'dynamics'.*not both"),
    ({}, "give either 'dynamics'.*none is given"),
    ({"dynamics": "x[0]", "sampling_time": 0.1}, "'sampling_time' belongs to an 'ode'"),
    ({"dynamics": "x[0]", "substeps": 3}, "'substeps' belongs to an 'ode'"),
    ({"ode": "-x[0]", "sampling_time": 0}, "sampling_time: Input should be greater than 0"),
    ({"ode": "-x[0]", "sampling_time": 0.1, "substeps": 0}, "substeps: Input should be greater than or equal to 1"),
    ({"ode": "-x[0]", "sampling_time": 0.1, "substeps": 1001}, "substeps: Input should be less than or equal to 1000"),
])
def test_spec_errors_are_one_clear_message(sub, message):
    with pytest.raises(SpecError, match=message) as info:
        parse_spec(_spec(sub))
    assert str(info.value).count("\n") == 1  # "invalid spec:" and one line about the subsystem


def test_an_ode_of_the_wrong_dimension_is_a_spec_error():
    """A state box given per dimension fixes the dimension (a box of numbers would take the ODE's two)."""
    box = {"lb": [-2], "ub": [2], "eta": [0.25]}
    with pytest.raises(SpecError, match="returns 2 components, expected 1"):
        build_network(parse_spec(_spec({"ode": "[x[0], u[0]]", "sampling_time": 0.1, "state": box})))


def test_discrete_time_specs_dump_as_before():
    """spec_hash and the subsystem keys of specs written before ``ode`` existed do not change."""
    dumped = parse_spec(_spec({"dynamics": "x[0]"})).subsystems[0].model_dump(mode="json")
    assert not {"ode", "sampling_time", "substeps"} & set(dumped)
    dumped = parse_spec(_spec({"ode": "-x[0]", "sampling_time": 0.1})).subsystems[0].model_dump(mode="json")
    assert "dynamics" not in dumped and dumped["substeps"] == 5


SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], max_examples=60)
coef = st.floats(-1.5, 1.5, allow_nan=False).map(lambda v: round(v, 3))


def _linear_network(a, d, tau, substeps, method):
    """dx/dt = a x + u + d w, scalar, reading one internal variable: L of the sampled map is e^{|a| tau} in x,
    |d| tau e^{|a| tau} in w (for the RK4 map as for the flow: each step's factor is below e^{|a| h})."""
    L_x = math.exp(abs(a) * tau)
    L_w = abs(d) * tau * math.exp(abs(a) * tau)
    spec = parse_spec({
        "subsystems": [{
            "name": "s", "state": {"lb": -2, "ub": 2, "eta": 0.4}, "input": {"lb": -1, "ub": 1, "eta": 0.5},
            "reads": [0], "ode": f"{a} * x[0] + u[0] + {d} * w[0]", "sampling_time": tau, "substeps": substeps,
            "lipschitz": {"x": L_x, "w": L_w}, "samples": 8, "growth_bound": method,
        }],
        "interconnection": {"map": "[x[0]]", "internal": {"lb": -2, "ub": 2, "eta": 1.0}, "error": "linear"},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": -1, "ub": 1}]}},
    })
    return build_network(spec), L_x, L_w


@settings(**SETTINGS)
@given(a=coef, d=coef, tau=st.floats(0.05, 0.6).map(lambda v: round(v, 3)), substeps=st.integers(1, 6),
       method=st.sampled_from(["lipschitz", "scp", "hull"]), seed=st.integers(0, 2**31 - 1))
def test_ode_subsystems_abstract_soundly(a, d, tau, substeps, method, seed):
    """Every concrete transition of the RK4 map (the audit draws them) is in the abstraction, and so is every
    transition of the exact flow up to the RK4 error bound."""
    net, L_x, L_w = _linear_network(a, d, tau, substeps, method)
    sub = net.subsystems[0]
    rel = assemble([abstract_cells(sub, lo, hi, L_x, L_w, method, "paper") for lo, hi in chunk_ranges(sub, None)],
                   sub.state_grid.size, method, L_x, L_w)
    rng = np.random.default_rng(seed)
    result = audit_subsystem(sub, rel, 5_000, rng)
    assert result.violations == 0, result.first_violation

    # The exact flow: x(tau) = e^{a tau} x + (e^{a tau} - 1)/a * v with v = u + d w held.
    xg, ug, wg = sub.state_grid, sub.input_grid, sub.internal_grid
    B = 2_000
    x = rng.uniform(xg.lb[0], xg.ub[0], (B, 1))
    ui = rng.integers(0, ug.size, B)
    u = ug.points(ug.unravel(ui))
    w = rng.uniform(wg.lb[0], wg.ub[0], (B, 1))
    v = u + d * w
    z = a * tau
    phi = tau if a == 0 else math.expm1(z) / a
    exact = math.exp(z) * x + phi * v
    # The RK4 error bound: RK4 of a linear ODE multiplies by T4(ah) and adds h S4(ah) v per step (T4 the Taylor
    # polynomial of e^y of degree 4, S4(y) = (T4(y) - 1)/y), the flow by e^{ah} and adds h (e^{ah} - 1)/(ah) v.
    # Taylor's remainder bounds the differences by |ah|^5/5! e^{|ah|} and h |ah|^4/5! e^{|ah|}; with |x| <= X on
    # the way (|x0| <= 2, |v| <= V = 1 + 1.5 * 2) and |T4(ah)| <= e^{|a|h}, the errors add up to at most
    # substeps * e^{|a| tau} * (local error).
    h = tau / substeps
    y = abs(a) * h
    V = 4.0
    X = math.exp(abs(a) * tau) * (2 + V * tau)
    local = y**5 / 120 * math.exp(y) * X + h * y**4 / 120 * math.exp(y) * V
    delta = substeps * math.exp(abs(a) * tau) * local + 1e-12
    assert np.abs(sub.dynamics(x, u, w) - exact).max() <= delta
    xi = xg.ravel(xg.cell_of(x, "lower")[0])
    wi = wg.ravel(wg.cell_of(w, "lower")[0])
    lo, hi, block = rel.successor_ranges(xi, ui, wi)
    live = ~block[:, None]
    eta = xg.eta[0]
    low = np.asarray(xg.points(lo)) - eta / 2 - delta
    high = np.asarray(xg.points(hi)) + eta / 2 + delta
    inside = (exact >= low) & (exact <= high)
    assert np.all(inside | ~live)
