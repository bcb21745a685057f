"""The batched SCP against the reference LP, and the growth-bound helpers."""

import numpy as np
import pytest

from pipelines.abstraction.growth_bound import (
    pair_maxima_scalar,
    scp_parameters_scalar,
    scp_reference,
    scp_rho,
    subgrid_counts,
)


@pytest.mark.parametrize("samples,dims,expected", [(150, 2, (12, 12)), (100, 2, (10, 10)), (150, 1, (150,)),
                                                   (10, 3, (2, 2, 2)), (1, 2, (1, 1)), (8, 3, (2, 2, 2))])
def test_subgrid_counts(samples, dims, expected):
    counts = subgrid_counts(samples, dims)
    assert np.prod(counts) <= samples
    assert sorted(counts, reverse=True) == sorted(expected, reverse=True)


def _random_cells(rng, B, mx, mw):
    """Successor samples of B cells on an mx-by-mw sub-grid, smooth and rough."""
    x = (np.arange(mx) + 0.5) / mx
    w = (np.arange(mw) + 0.5) / mw
    a = rng.uniform(-2, 2, (B, 1, 1))
    b = rng.uniform(-1, 1, (B, 1, 1))
    bumps = rng.normal(0, rng.uniform(0, 0.3, (B, 1, 1)), (B, mx, mw))
    V = a * np.sin(3 * x)[None, :, None] + b * w[None, None, :] + bumps
    return x, V


@pytest.mark.parametrize("objective", ["paper", "radius"])
def test_batched_scp_matches_reference_lp(objective):
    rng = np.random.default_rng(1)
    B, mx, mw = 60, 7, 4
    x, V = _random_cells(rng, B, mx, mw)
    h = np.full(B, 1.0 / mx)
    L_x = rng.uniform(0.5, 5.0)
    rho = scp_rho(h[:, None], np.full((B, 1), 1.0 / mw), L_x, 0.7)
    r = np.full(B, 0.5)
    weight = np.ones(B) if objective == "paper" else r
    t1, t2 = scp_parameters_scalar(pair_maxima_scalar(V), h, rho, L_x, weight)
    worst = 0.0
    for b in range(B):
        xs = np.repeat(x, mw)[:, None]  # x-major, like the sample layout
        th1, th2 = scp_reference(xs, V[b].reshape(-1, 1), float(rho[b]), L_x, np.array([weight[b]]))
        ref_obj = weight[b] * th1[0, 0] + th2[0]
        fast_obj = weight[b] * t1[b] + t2[b]
        worst = max(worst, abs(ref_obj - fast_obj))
        # the fast solution is feasible for the full pair LP
        il, jl = np.triu_indices(xs.shape[0], 1)
        lhs = np.abs(V[b].ravel()[il] - V[b].ravel()[jl]) + rho[b]
        assert np.all(t1[b] * np.abs(xs[il, 0] - xs[jl, 0]) + t2[b] >= lhs - 1e-9)
        assert 0 <= t1[b] <= L_x + 1e-12 and t2[b] >= 0
    assert worst <= 1e-9


def test_pair_maxima_are_pair_maxima():
    rng = np.random.default_rng(2)
    V = rng.normal(size=(5, 6, 3))
    E = pair_maxima_scalar(V)
    for b in range(5):
        for k in range(6):
            best = 0.0
            for i in range(6 - k):
                best = max(best, np.abs(V[b, i][:, None] - V[b, i + k][None, :]).max())
            assert E[b, k] == pytest.approx(best)


# ----------------------------------------------------------------------------- the closed-form SCP
def _vertex_enumeration(E, h_x, rho, L_x, w):
    """The SCP LP by brute force over its vertices (the implementation before the closed form, O(m^3))."""
    B, m = E.shape
    d = np.arange(m)[None, :] * h_x[:, None]
    rhs = E + rho[:, None]
    cands = [np.zeros((B, 1)), np.full((B, 1), float(L_x))]
    iu, ju = np.triu_indices(m, k=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        if iu.size:
            cands.append((rhs[:, ju] - rhs[:, iu]) / (d[:, ju] - d[:, iu]))
        if m > 1:
            cands.append(rhs[:, 1:] / d[:, 1:])
    a = np.nan_to_num(np.clip(np.concatenate(cands, axis=1), 0.0, float(L_x)))
    b = np.maximum(0.0, np.max(rhs[:, None, :] - a[:, :, None] * d[:, None, :], axis=2))
    return np.min(w[:, None] * a + b, axis=1)


def _check_against_reference(V, h, rho, L, w, radius_too=True):
    """Closed form vs HiGHS on every cell: objective (and radius theta1 * r + theta2, r = mx h / 2) to 1e-9."""
    B, mx, mw = V.shape
    t1, t2 = scp_parameters_scalar(pair_maxima_scalar(V), h, rho, L, w)
    assert np.all(t1 >= 0) and np.all(t1 <= L) and np.all(t2 >= 0)
    r = mx * h / 2
    for b in range(B):
        xs = np.repeat((np.arange(mx) + 0.5) * h[b], mw)[:, None]
        th1, th2 = scp_reference(xs, V[b].reshape(-1, 1), float(rho[b]), L, np.array([w[b]]))
        scale = max(1.0, abs(th2[0]))
        assert abs((w[b] * t1[b] + t2[b]) - (w[b] * th1[0, 0] + th2[0])) <= 1e-9 * scale, b
        if radius_too:
            assert abs((t1[b] * r[b] + t2[b]) - (th1[0, 0] * r[b] + th2[0])) <= 1e-9 * scale, b
        # feasible for every sample pair, (l, l) included
        il, jl = np.triu_indices(xs.shape[0], 0)
        lhs = np.abs(V[b].ravel()[il] - V[b].ravel()[jl]) + rho[b]
        assert np.all(t1[b] * np.abs(xs[il, 0] - xs[jl, 0]) + t2[b] >= lhs - 1e-12 * scale)


@pytest.mark.parametrize("mx,mw", [(1, 1), (1, 6), (2, 1), (5, 3), (12, 12), (30, 2)])
def test_closed_form_scp_matches_the_reference_lp_on_random_cells(mx, mw):
    """Random cells and continuous random weights (a unique optimum almost surely): objective and radius."""
    rng = np.random.default_rng(mx * 100 + mw)
    B = 12
    _, V = _random_cells(rng, B, mx, mw)
    h = rng.uniform(0.05, 1.0, B) / mx
    L = float(rng.uniform(0.3, 4.0))
    rho = scp_rho(h[:, None], rng.uniform(0, 0.3, (B, 1)), L, 0.5)
    for w in (np.ones(B), mx * h / 2, rng.uniform(0, 1.5, B)):
        _check_against_reference(V, h, rho, L, w)


def test_closed_form_scp_degenerate_cells():
    rng = np.random.default_rng(5)
    _, V = _random_cells(rng, 6, 8, 3)
    # all distances equal (a zero-width cell: h = 0): theta1 is irrelevant, theta2 = max E + rho
    h0 = np.zeros(6)
    t1, t2 = scp_parameters_scalar(pair_maxima_scalar(V), h0, np.full(6, 0.1), 1.0, np.ones(6))
    assert np.all(t1 == 0) and np.array_equal(t2, pair_maxima_scalar(V).max(axis=1) + 0.1)
    # one sample per cell: only the pair (l, l), so theta = (0, rho + 0)
    V1 = rng.normal(size=(4, 1, 1))
    t1, t2 = scp_parameters_scalar(pair_maxima_scalar(V1), np.full(4, 0.2), np.full(4, 0.3), 1.0, np.ones(4))
    assert np.all(t1 == 0) and np.all(t2 == 0.3)
    # theta1 at its bound L_x (steep data, small L), at 0 (w beyond every sample distance), rho = 0
    steep = 50 * np.arange(6, dtype=float)[None, :, None] + np.zeros((3, 6, 2))
    h = np.full(3, 0.1)
    for L, w, rho in ((0.5, np.full(3, 0.2), np.full(3, 0.05)), (3.0, np.full(3, 5.0), np.zeros(3)),
                      (3.0, np.full(3, 0.25), np.zeros(3))):
        t1, t2 = scp_parameters_scalar(pair_maxima_scalar(steep), h, rho, L, w)
        if L == 0.5:
            assert np.all(t1 == 0.5)
        if w[0] == 5.0:
            assert np.all(t1 == 0)
        _check_against_reference(steep, h, rho, L, w)


def test_closed_form_scp_ties_keep_the_optimal_value():
    """w exactly on a sample distance (a kink of the envelope): several optima; the value is the LP's and the
    smallest optimal theta1 is returned."""
    rng = np.random.default_rng(9)
    B, mx = 40, 10
    _, V = _random_cells(rng, B, mx, 4)
    h = np.full(B, 0.1)
    w = rng.integers(0, mx + 2, B) * 0.1  # on the grid of distances (up to rounding)
    rho = np.full(B, 0.02)
    _check_against_reference(V, h, rho, 1.76, w, radius_too=False)
    E = pair_maxima_scalar(V)
    t1, t2 = scp_parameters_scalar(E, h, rho, 1.76, w)
    best = _vertex_enumeration(E, h, rho, 1.76, w)
    np.testing.assert_allclose(w * t1 + t2, best, rtol=1e-12, atol=1e-14)
    # no smaller theta1 reaches the optimum
    d = np.arange(mx)[None, :] * h[:, None]
    smaller = np.maximum(t1 - 1e-6, 0)
    obj = w * smaller + np.max(E + rho[:, None] - smaller[:, None] * d, axis=1)
    assert np.all((obj > best + 1e-12) | (t1 == 0))


def test_closed_form_scp_equals_vertex_enumeration_in_batch():
    rng = np.random.default_rng(3)
    for B, mx, mw in ((500, 10, 10), (200, 30, 5), (300, 3, 3)):
        _, V = _random_cells(rng, B, mx, mw)
        E = pair_maxima_scalar(V)
        h = rng.uniform(0.01, 1, B) / mx
        h[:5] = 0
        rho = rng.uniform(0, 0.2, B)
        rho[5:10] = 0
        L = float(rng.uniform(0.1, 3))
        for w in (np.ones(B), mx * h / 2, rng.uniform(0, 1.2, B), rng.integers(0, mx + 2, B) * h):
            t1, t2 = scp_parameters_scalar(E, h, rho, L, w)
            np.testing.assert_allclose(w * t1 + t2, _vertex_enumeration(E, h, rho, L, w), rtol=1e-12, atol=1e-14)


def test_pair_maxima_batch_last_is_exact():
    from pipelines.abstraction.growth_bound import pair_maxima_batch_last

    rng = np.random.default_rng(4)
    V = rng.normal(size=(7, 9, 4))
    E = pair_maxima_scalar(V)
    brute = np.zeros((7, 9))
    for k in range(9):
        for i in range(9 - k):
            d = np.maximum(V[:, i + k][:, :, None] - V[:, i][:, None, :], V[:, i][:, :, None] - V[:, i + k][:, None, :])
            brute[:, k] = np.maximum(brute[:, k], d.max(axis=(1, 2)))
    np.testing.assert_array_equal(E, brute)
    vt = np.moveaxis(V, 0, -1)
    np.testing.assert_array_equal(pair_maxima_batch_last(vt.max(axis=1), vt.min(axis=1)), E.T)


def test_small_and_large_batches_take_different_paths_to_the_same_bits(monkeypatch):
    import pipelines.abstraction.growth_bound as gb

    rng = np.random.default_rng(8)
    _, V = _random_cells(rng, 300, 12, 4)
    E = pair_maxima_scalar(V)
    h = rng.uniform(0.01, 1, 300) / 12
    rho = rng.uniform(0, 0.2, 300)
    for w in (np.ones(300), 6 * h, rng.uniform(0, 1.2, 300)):
        out = []
        for small in (0, 1 << 30):
            monkeypatch.setattr(gb, "SMALL_TABLE", small)
            out.append(scp_parameters_scalar(E, h, rho, 1.3, w))
        np.testing.assert_array_equal(out[0][0], out[1][0])
        np.testing.assert_array_equal(out[0][1], out[1][1])
