"""The batched SCP against the reference LP, and the growth-bound helpers."""

import numpy as np
import pytest

from pipelines.growth_bound import (
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
