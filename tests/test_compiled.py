"""The compiled kernels of the per-cell stage against their numpy references, bit for bit."""

import numpy as np
import pytest

import pipelines.abstraction.block as block_module
import pipelines.abstraction.cells as subsystem
import pipelines.abstraction.growth_bound as gb
import pipelines.abstraction.kernels as compiled
from pipelines.abstraction.cells import abstract_cells
from pipelines.abstraction.relation import chunk_ranges
from pipelines.errors import BlackBoxError
from pipelines.network import build_network
from pipelines.spec.model import load_spec, parse_spec

from .conftest import EXAMPLES

SHAPES = [(12, 12, 700), (13, 1, 50), (1, 5, 30), (7, 9, 1), (1, 1, 4), (2, 3, 17)]


def _samples(shape, rng, kind):
    if kind == "normal":
        return rng.normal(size=shape)
    if kind == "ties":  # few distinct values: equal extremes, zero differences, +0.0 and -0.0
        return rng.integers(-2, 3, size=shape) * 0.5 + np.where(rng.random(shape) < 0.3, -0.0, 0.0)
    return np.full(shape, 3.25)  # constant: every difference 0


@pytest.mark.parametrize("kind", ["normal", "ties", "constant"])
@pytest.mark.parametrize("shape", SHAPES)
def test_sample_pass_pair_maxima_and_hull_equal_numpy(shape, kind, monkeypatch):
    rng = np.random.default_rng(hash((shape, kind)) % 2**32)
    V = _samples(shape, rng, kind)
    got = compiled.scalar_sample_pass(V)
    for small in (0, 1 << 40):  # both paths of the numpy pass
        monkeypatch.setattr(block_module, "SMALL_PASS", small)
        want = block_module._scalar_sample_pass(V)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
    vmax, vmin = got[0], got[1]
    np.testing.assert_array_equal(compiled.pair_maxima_batch_last(vmax, vmin), gb.pair_maxima_batch_last(vmax, vmin))
    half = shape[0] // 2
    lo, hi, bound = compiled.hull_and_bound(vmax, vmin, half)
    np.testing.assert_array_equal(lo, vmin.min(axis=0))
    np.testing.assert_array_equal(hi, vmax.max(axis=0))
    want = np.max(vmax - vmin, axis=0)
    if half:
        want = np.maximum(want, np.maximum((vmax[half:] - vmin[:-half]).max(axis=0),
                                           (vmax[:-half] - vmin[half:]).max(axis=0)))
    np.testing.assert_array_equal(bound, want)


@pytest.mark.parametrize("m", [1, 2, 5, 12, 40])
def test_scp_parameters_equal_numpy(m):
    """Random pair maxima and spacings; objective weights that fall on a sample distance (the tie rule), left of
    every point, right of every point; degenerate spacings; a column subset (strided input)."""
    rng = np.random.default_rng(m)
    B = 300
    V = rng.normal(size=(m, 3, B))
    E = gb.pair_maxima_batch_last(V.max(axis=1), V.min(axis=1))
    h = rng.uniform(0.01, 1.0, B)
    h[:10] = 0.0
    rho = rng.uniform(0.0, 0.5, B)
    k = rng.integers(0, m, B)
    for w in (np.ones(B), k * h, (m / 2) * h, np.zeros(B), np.full(B, 1e9), rng.uniform(0, m, B) * h):
        for L in (0.3, 1.0, 50.0):
            want = gb.scp_parameters_batch_last(E, h, rho, L, w)
            got = compiled.scp_parameters_batch_last(E, h, rho, L, w, gb.SCP_TIE_RTOL)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
    cols = np.flatnonzero(rng.random(B) < 0.3)
    want = gb.scp_parameters_batch_last(E[:, cols], h[cols], rho[cols], 1.0, np.ones(cols.size))
    got = compiled.scp_parameters_batch_last(E[:, cols], h[cols], rho[cols], 1.0, np.ones(cols.size),
                                               gb.SCP_TIE_RTOL)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def _scalar_subsystems():
    subs = []
    for name in ("tanks", "consensus", "scalability", "small"):
        net = build_network(load_spec(EXAMPLES / f"{name}.yaml"), None)
        subs += [(f"{name}:{g[0].name}", g[0]) for g in net.unique_subsystems().values()]
    spec = parse_spec({  # no internal input (an empty internal cell), cells clipped at an upper bound off the grid
        "subsystems": [{"name": "leaky", "state": {"lb": 0, "ub": 9.7, "eta": 0.5}, "input": {"lb": 0, "ub": 1, "eta": 0.5},
                        "dynamics": "0.9 * x[0] + u[0] - 0.2 * sin(3 * x[0])", "lipschitz": {"x": 1.5},
                        "samples": 20}],
        "interconnection": {"map": "[x[0]]", "internal": {"lb": 0, "ub": 10, "eta": 1}, "error": "linear"},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": 0, "ub": 9.7}]}},
    })
    subs.append(("leaky", build_network(spec, None).subsystems[0]))
    return subs


def _constants(sub):
    return float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w) if sub.internal_grid is not None else 0.0


@pytest.mark.parametrize("name,sub", _scalar_subsystems(), ids=lambda v: v if isinstance(v, str) else "")
def test_scalar_block_equals_the_generic_numpy_path(name, sub, monkeypatch):
    """The compiled pass of a scalar subsystem gives the generic path's relation, successor statistics of all
    four growth bounds and slope records, for every growth bound that can build the relation and for blocks
    that split state cells."""
    L_x, L_w = _constants(sub)
    samples = int(np.prod(gb.subgrid_counts(sub.spec.samples, sub.n + sub.p)))
    for block in (subsystem.BLOCK_POINTS, 5 * samples):
        monkeypatch.setattr(subsystem, "BLOCK_POINTS", block)
        for method, objective in (("scp", "paper"), ("scp", "radius"), ("lipschitz", "paper"), ("hull", "paper")):
            out = []
            for use in (True, False):
                monkeypatch.setattr(block_module, "_USE_SCALAR_KERNEL", use)
                out.append([abstract_cells(sub, a, b, L_x, L_w, method, objective)
                            for a, b in chunk_ranges(sub, None)[:2]])
            for k, g in zip(out[0], out[1]):
                for f in ("lo", "hi", "blocking"):
                    np.testing.assert_array_equal(getattr(k, f), getattr(g, f), err_msg=f"{name} {method} {f}")
                assert k.lo.dtype == g.lo.dtype and k.hi.dtype == g.hi.dtype
                assert k.successors == g.successors, (name, method)
                assert k.slope_x == g.slope_x and k.slope_w == g.slope_w, (name, method)


def test_scalar_block_flags_a_box_that_leaves_the_grid_as_blocking(monkeypatch):
    """A subsystem pushed out of its state box: the kernel and the generic path agree that the triples near the
    top block, with the empty range (0, -1)."""
    spec = parse_spec({
        "subsystems": [{"name": "push", "state": {"lb": 0, "ub": 4, "eta": 1}, "input": {"lb": 0, "ub": 1, "eta": 1},
                        "dynamics": "x[0] + u[0]", "lipschitz": {"x": 1.0}, "samples": 8}],
        "interconnection": {"map": "[x[0]]", "internal": {"lb": 0, "ub": 4, "eta": 1}, "error": "linear"},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": 0, "ub": 4}]}},
    })
    sub = build_network(spec, None).subsystems[0]
    res = abstract_cells(sub, 0, sub.state_grid.size, 1.0, 0.0, "scp", "paper")
    monkeypatch.setattr(block_module, "_USE_SCALAR_KERNEL", False)
    ref = abstract_cells(sub, 0, sub.state_grid.size, 1.0, 0.0, "scp", "paper")
    assert res.blocking[-1, -1, 0] and res.blocking.any() and not res.blocking.all()
    assert (res.lo[res.blocking] == 0).all() and (res.hi[res.blocking] == -1).all()
    np.testing.assert_array_equal(res.blocking, ref.blocking)
    np.testing.assert_array_equal(res.lo, ref.lo)


@pytest.mark.parametrize("dynamics", ["where(x[0] > 20.3, sqrt(19 - x[0]), x[0])",
                                      "where(w[0] > 27.6, 1 / (x[0] - x[0]), x[0])",
                                      "where(x[0] < 0.6, -1 / (x[0] - x[0]), x[0])"])
def test_a_non_finite_sample_gives_the_black_boxs_error_on_both_paths(dynamics, monkeypatch):
    """A black box that returns NaN or an infinity at some samples: the kernel path raises the generic path's
    error, naming the same sample, its arguments and its cell (the compiled pass's comparisons would drop a
    NaN silently, so the samples must be checked before it runs)."""
    spec = load_spec(EXAMPLES / "consensus.yaml", {"N": 2})
    data = spec.model_dump(mode="json", exclude_none=True)
    data["subsystems"][0]["dynamics"] = dynamics
    sub = build_network(parse_spec(data), None).subsystems[0]
    L_x, L_w = _constants(sub)
    messages = []
    for use in (True, False):
        monkeypatch.setattr(block_module, "_USE_SCALAR_KERNEL", use)
        with pytest.raises(BlackBoxError, match=r"\(not finite\) at x=.* \(state cell \d+, input \d, internal") as e:
            abstract_cells(sub, 0, sub.state_grid.size, L_x, L_w, "scp", "paper")
        messages.append(str(e.value))
    assert messages[0] == messages[1]


def _box_subsystems():
    """Subsystems the compiled box pass takes: several state coordinates (2-D, 3-D under a matrix of constants,
    4-D), internal inputs (the platoon's followers), a scalar state with two internal-input axes; cells clipped
    at the grid's edges (dcdc's grid holds every point whose cell meets the box)."""
    subs = []
    for name, override in (("dcdc", {"eta": 0.02}), ("vehicle", {"eta": 1.0}), ("double_integrator", None),
                           ("platoon", None)):
        data = load_spec(EXAMPLES / f"{name}.yaml").model_dump(mode="json", exclude_none=True)
        if override:
            data["subsystems"][0]["state"].update(override)
        net = build_network(parse_spec(data), None)
        subs += [(f"{name}:{g[0].name}", g[0]) for g in net.unique_subsystems().values()]
    spec = parse_spec({
        "subsystems": [{"name": "mixer", "replicate": 3, "reads": [0, 1], "state": {"lb": 0, "ub": 4, "eta": 0.5},
                        "input": {"lb": 0, "ub": 1, "eta": 0.5}, "samples": 27,
                        "dynamics": "0.5 * x[0] + 0.2 * w[0] - 0.1 * w[1] * w[1] + u[0]",
                        "lipschitz": {"x": 0.5, "w": [[0.2, 0.8]]}}],
        "interconnection": {"map": "x", "internal": {"lb": 0, "ub": 4, "eta": 1}, "error": "linear"},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": 0, "ub": 4}]}},
    })
    subs.append(("mixer", build_network(spec, None).subsystems[0]))
    return subs


@pytest.mark.parametrize("name,sub", _box_subsystems(), ids=lambda v: v if isinstance(v, str) else "")
def test_box_block_equals_the_generic_numpy_path(name, sub, monkeypatch):
    """The compiled pass of the Lipschitz and hull bounds gives the generic path's relation, successor statistics
    (the SCP's on the statistics sample or on every triple) and slope records, for blocks that split cells."""
    from pipelines.abstraction.constants import LipschitzMatrix

    lip = sub.spec.lipschitz
    L_x = LipschitzMatrix.given(lip.x, sub.n, sub.n, "x")
    L_w = LipschitzMatrix.given(lip.w if sub.p else 0.0, sub.n, sub.p, "w")
    samples = int(np.prod(gb.subgrid_counts(sub.spec.samples, sub.n + sub.p)))
    cells = min(sub.state_grid.size, max(4, 3000 * sub.state_grid.size // sub.triples))  # about 3,000 triples
    start = (sub.state_grid.size - cells) // 2  # the middle of the grid: some triples stay inside it
    for block in (subsystem.BLOCK_POINTS, 7 * samples):
        monkeypatch.setattr(subsystem, "BLOCK_POINTS", block)
        for method in ("lipschitz", "hull"):
            for full in (None, True):
                out = []
                for use in (True, False):
                    monkeypatch.setattr(block_module, "_USE_BOX_KERNEL", use)
                    out.append(subsystem.abstract_chunk(sub, start, start + cells,
                                                        subsystem.bound_of(sub, L_x, L_w, method, "paper"),
                                                        full_statistics=full))
                k, g = out
                for f in ("lo", "hi", "blocking"):
                    np.testing.assert_array_equal(getattr(k, f), getattr(g, f), err_msg=f"{name} {method} {f}")
                assert k.lo.dtype == g.lo.dtype and k.hi.dtype == g.hi.dtype
                assert k.successors == g.successors, (name, method)
                assert k.slope_x == g.slope_x and k.slope_w == g.slope_w, (name, method)
                assert (~k.blocking).any()
