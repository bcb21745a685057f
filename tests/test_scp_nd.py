"""The batched n-D SCP (pipelines.abstraction.scp) against the reference LPs: HiGHS on every sample pair and the
stacked cvxpy formulation."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipelines.abstraction.growth_bound import scp_reference
from pipelines.abstraction.scp import (
    displacement_classes,
    pair_maxima_nd,
    scp_constraints,
    scp_cvxpy,
    scp_parameters_nd,
    scp_radii_nd,
)

SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _instance(rng, counts, mw, B):
    """B cells of a random smooth-plus-rough map on a ``counts`` state sub-grid with ``mw`` internal samples."""
    n = len(counts)
    S = int(np.prod(counts))
    idx = np.stack(np.unravel_index(np.arange(S), counts), axis=-1)
    h = rng.uniform(0.02, 1.0, (B, n)) * (rng.uniform(size=(B, n)) > 0.05)  # a few degenerate axes
    xs = (idx[None] + 0.5) * h[:, None, :]  # (B, S, n)
    A = rng.normal(0, rng.uniform(0.1, 3), (B, n, n))
    V = np.einsum("bsa,bja->bsj", np.sin(xs) + xs, A)[:, :, None, :] \
        + rng.normal(0, rng.uniform(0, 0.5), (B, S, mw, n))  # (B, S, mw, n)
    vmax = np.ascontiguousarray(V.max(axis=2).transpose(1, 2, 0))
    vmin = np.ascontiguousarray(V.min(axis=2).transpose(1, 2, 0))
    pl, pm, cls, k = displacement_classes(tuple(counts))
    E = pair_maxima_nd(vmax, vmin, pl, pm, cls, S)
    return xs, V, h, E, k


instances = st.fixed_dictionaries({
    "counts": st.sampled_from([(2, 2), (3, 2), (3, 3), (4, 3), (2, 2, 2), (3, 2, 2), (3, 3, 2), (1, 3), (3, 1, 2)]),
    "mw": st.integers(1, 3),
    "L": st.floats(0.05, 5.0),
    "radius": st.booleans(),
    "seed": st.integers(0, 2**31 - 1),
})


@settings(max_examples=40, **SETTINGS)
@given(inst=instances)
def test_batched_scp_equals_the_reference_lps(inst):
    """Objective to 1e-9 relative against HiGHS on every pair and against cvxpy (HiGHS); feasible for every
    pair; theta >= 0 and ||theta1 row||_1 <= L_x."""
    rng = np.random.default_rng(inst["seed"])
    counts, mw, L = inst["counts"], inst["mw"], inst["L"]
    n, B = len(counts), 4
    xs, V, h, E, k = _instance(rng, counts, mw, B)
    rho = rng.uniform(0, 0.5, B)
    W = h * np.asarray(counts) / 2 if inst["radius"] else np.ones((B, n))
    t1, t2 = scp_parameters_nd(E, k, h, rho, L, W)
    d, r = scp_constraints(E, k, h, rho)  # (B, K, n), (B, n, K)
    K = k.shape[0]
    c1, c2 = scp_cvxpy(np.repeat(d, n, axis=0), r.reshape(B * n, K), L, np.repeat(W, n, axis=0))
    for b in range(B):
        x_all = np.repeat(xs[b], mw, axis=0)
        v_all = V[b].reshape(-1, n)
        th1, th2 = scp_reference(x_all, v_all, float(rho[b]), L, W[b])
        il, jl = np.triu_indices(x_all.shape[0])
        D = np.abs(x_all[il] - x_all[jl])
        for j in range(n):
            fast = W[b] @ t1[b, j] + t2[b, j]
            for ref in (W[b] @ th1[j] + th2[j], W[b] @ c1[b * n + j] + c2[b * n + j]):
                assert abs(fast - ref) <= 1e-9 * max(1.0, abs(ref)), (b, j, fast, ref)
            lhs = np.abs(v_all[il, j] - v_all[jl, j]) + rho[b]
            # theta2 is recomputed from the constraints, so every pair holds up to the rounding of |x_l - x_m|
            # against k h (a few ulps; the successor boxes are widened by FP_RTOL = 1e-12 relative)
            assert np.all(D @ t1[b, j] + t2[b, j] >= lhs * (1 - 1e-14))
            assert np.all(t1[b, j] >= 0) and t1[b, j].sum() <= L and t2[b, j] >= 0


@pytest.mark.parametrize("counts", [(3, 3), (2, 3, 2)])
def test_clarabel_agrees_to_its_accuracy(counts):
    rng = np.random.default_rng(3)
    B, n = 5, len(counts)
    _, _, h, E, k = _instance(rng, counts, 2, B)
    rho = np.full(B, 0.1)
    W = np.ones((B, n))
    t1, t2 = scp_parameters_nd(E, k, h, rho, 2.0, W)
    d, r = scp_constraints(E, k, h, rho)
    c1, c2 = scp_cvxpy(np.repeat(d, n, axis=0), r.reshape(B * n, -1), 2.0, np.repeat(W, n, axis=0), "CLARABEL")
    fast = (t1.sum(axis=2) + t2).ravel()
    ref = c1.sum(axis=1) + c2
    np.testing.assert_allclose(fast, ref, rtol=1e-6, atol=1e-7)


@settings(max_examples=30, **SETTINGS)
@given(counts=st.sampled_from([(3, 3), (2, 4), (3, 2, 2), (2, 2, 2)]), mw=st.integers(1, 3),
       seed=st.integers(0, 2**31 - 1))
def test_pair_maxima_are_the_maxima_over_every_pair_of_a_class(counts, mw, seed):
    """E_k over |idx_l - idx_m| = k, with every sign pattern ((k1, k2) and (k1, -k2) are different pairs)."""
    rng = np.random.default_rng(seed)
    B = 3
    S = int(np.prod(counts))
    _, V, _, E, _ = _instance(rng, counts, mw, B)
    idx = np.stack(np.unravel_index(np.arange(S), counts), axis=-1)
    brute = np.full(E.shape, -np.inf)
    for a in range(S):
        for b in range(S):
            c = np.ravel_multi_index(tuple(np.abs(idx[a] - idx[b])), counts)
            diff = np.abs(V[:, a, :, None, :] - V[:, b, None, :, :]).max(axis=(1, 2))  # (B, n)
            brute[c] = np.maximum(brute[c], diff.T)
    np.testing.assert_array_equal(E, brute)


@pytest.mark.parametrize("counts", [(3, 3), (5, 5), (3, 3, 3)])
def test_radii_are_the_lp_radius_or_the_lipschitz_radius(counts):
    """scp_radii_nd = min(theta1 . r_x + theta2, lip), the LP skipped where it cannot beat lip."""
    rng = np.random.default_rng(5)
    B, n = 200, len(counts)
    _, _, h, E, k = _instance(rng, counts, 2, B)
    r_x = h * np.asarray(counts) / 2
    rho = rng.uniform(0, 0.3, B)
    lip = rng.uniform(0.5, 6, B)
    for W in (np.ones((B, n)), r_x):
        t1, t2 = scp_parameters_nd(E, k, h, rho, 3.0, W)
        full = np.minimum(np.einsum("bja,ba->bj", t1, r_x) + t2, lip[:, None])
        rad = scp_radii_nd(E, k, h, rho, 3.0, W, r_x, lip, 1e-9)
        assert np.all(rad <= lip[:, None])
        skipped = rad == lip[:, None]
        np.testing.assert_allclose(rad[~skipped], full[~skipped], rtol=1e-13)  # the order of a 2-3 term sum
        np.testing.assert_allclose(rad, full, rtol=1e-9)
        assert skipped.any() and (~skipped).any()  # both branches exercised
