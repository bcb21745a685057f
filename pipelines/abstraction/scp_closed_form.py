"""The scalar scenario program of Theorem 4.4 in closed form (docs/method.md §2), and its LP reference.

The SCP's pair constraints only bind through the largest successor spread ``E_k`` at each sample distance ``k``
(:func:`pair_maxima_scalar`, :func:`pair_maxima_batch_last`); its optimum is a supporting line of the points
``(d_k, E_k)``, computed exactly for a batch of cells (:func:`scp_parameters_scalar`,
:func:`scp_parameters_batch_last`). :func:`scp_reference` solves the same LP with HiGHS: the tests and
``bench/run.py --cases scp`` compare the two. :mod:`.growth_bound` applies them per output row.
"""

from __future__ import annotations

import numpy as np


def pair_maxima_scalar(values: np.ndarray) -> np.ndarray:
    """``E_k = max |x'_l - x'_m|`` over sample pairs whose ``x`` indices differ by ``k``, for a scalar state.

    Parameters
    ----------
    values : ndarray, shape (B, m_x, s_w)
        Successor values on the sample grid: ``m_x`` state samples, ``s_w`` internal-input samples each.

    Returns
    -------
    ndarray, shape (B, m_x)
        ``E[:, k]`` for ``k = 0 .. m_x - 1``; the pair constraints of the SCP depend on a pair only through
        ``|x_l - x_m| = k h_x`` and ``|x'_l - x'_m|``, so these maxima are all the SCP needs.

    Notes
    -----
    Computed by :func:`pair_maxima_batch_last` on a transposed copy (the batch on the contiguous last axis:
    numpy reduces short axes one row at a time, which is slow); maxima and differences are exact, so the
    result is bit-identical to any evaluation order.
    """
    vt = np.ascontiguousarray(np.moveaxis(values, 0, -1))  # (m_x, s_w, B)
    return np.ascontiguousarray(pair_maxima_batch_last(vt.max(axis=1), vt.min(axis=1)).T)


def pair_maxima_batch_last(vmax: np.ndarray, vmin: np.ndarray) -> np.ndarray:
    """:func:`pair_maxima_scalar` from the per-``x``-sample extremes, batch on the last axis.

    Parameters
    ----------
    vmax, vmin : ndarray, shape (m_x, B)
        ``max`` / ``min`` of the successors over the internal-input samples at each state sample.

    Returns
    -------
    ndarray, shape (m_x, B)
        ``E[k] = max_l max(vmax[l + k] - vmin[l], vmax[l] - vmin[l + k])`` (``E[0] = max_l vmax[l] - vmin[l]``).
    """
    m = vmax.shape[0]
    out = np.empty(vmax.shape)
    np.max(vmax - vmin, axis=0, out=out[0])
    for k in range(1, m):
        up = (vmax[k:] - vmin[:-k]).max(axis=0)
        down = (vmax[:-k] - vmin[k:]).max(axis=0)
        np.maximum(up, down, out=out[k])
    return out


#: Largest table (elements, 128 KB) :func:`scp_parameters_batch_last` builds at once; above it, it loops over ``i``.
SMALL_TABLE = 1 << 14

#: Relative tolerance below which a sample distance ``d_k = k h_x`` counts as equal to the objective weight
#: ``w`` in :func:`scp_parameters_scalar` (``w`` is often ``(m/2) h_x`` computed another way). It only
#: decides which of several optimal ``theta`` is returned; the optimal value does not depend on it.
SCP_TIE_RTOL = 1e-12


def scp_parameters_scalar(
    E: np.ndarray, h_x: np.ndarray, rho: np.ndarray, L_x: float, weight_theta1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the corrected SCP (Eq. 4.5, docs/method.md §2) exactly for a scalar state, in batch.

    The LP per cell, with ``d_k = k h_x`` and ``r_k = E_k + rho``::

        min  w theta1 + theta2                       (w = weight_theta1)
        s.t. theta1 d_k + theta2 >= r_k              for k = 0 .. m-1
             0 <= theta1 <= L_x,   theta2 >= 0

    Closed form (ENGINEERING.md "Many tiny LPs"). For a fixed ``theta1`` the best ``theta2`` is
    ``max_k (r_k - theta1 d_k)`` (``>= r_0 >= 0``, so ``theta2 >= 0`` never binds), and the objective
    ``g(theta1) = max_k (r_k + theta1 (w - d_k))`` is convex and piecewise linear. Split the points at ``w``:
    ``Lf(theta) = max_{d_i <= w} (...)`` is non-decreasing in ``theta``, ``Rf(theta) = max_{d_j > w} (...)``
    strictly decreasing, and ``g = max(Lf, Rf)``. The smallest minimiser of ``g`` over the reals is the
    smallest ``theta`` with ``Lf >= Rf``, i.e. ``∃ i ∀ j: theta >= s_ij``::

        theta* = min_{d_i <= w} max_{d_j > w} s_ij,     s_ij = (r_j - r_i) / (d_j - d_i)

    — the smallest slope of a line supporting the upper concave envelope of the points ``(d_k, r_k)`` at
    ``d = w``, whose value there is the optimum (``-inf`` when no point lies right of ``w``). ``g`` is
    convex, so ``clip(theta*, 0, L_x)`` is the smallest minimiser on ``[0, L_x]``; then ``theta2`` is the
    smallest feasible one. When the optimum is not unique (``w`` equal to an envelope vertex ``d_k``,
    decided with :data:`SCP_TIE_RTOL`) the smallest optimal ``theta1`` is returned; a generic LP solver may
    return another optimal vertex, with the same objective but another radius ``theta1 r_x + theta2``
    (both sound). :func:`scp_reference` is the same LP through HiGHS; the tests compare the two.

    Cost: one quotient per pair ``d_i <= w < d_j`` (at most ``m^2 / 4`` per cell when the cells of a batch
    split alike, as equal cells do), with the batch on the contiguous axis, instead of evaluating the
    objective at every one of the ``O(m^2)`` vertices (``O(m^3)``), which the previous implementation did.
    Where that implementation's best vertex is the bridge ``s_ij`` it is the same quotient, so the same bits.

    Parameters
    ----------
    E : ndarray, shape (B, m)
        Pair maxima from :func:`pair_maxima_scalar`.
    h_x, rho : ndarray, shape (B,)
    weight_theta1 : ndarray, shape (B,)
        1 for the paper's objective ``1'theta``; the cell half-width for the radius objective.

    Returns
    -------
    theta1, theta2 : ndarray, shape (B,)
    """
    E = np.asarray(E, dtype=float)
    return scp_parameters_batch_last(np.ascontiguousarray(E.T), h_x, rho, L_x, weight_theta1)


def scp_parameters_batch_last(
    E: np.ndarray, h_x: np.ndarray, rho: np.ndarray, L_x: float, weight_theta1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`scp_parameters_scalar` with ``E`` of shape ``(m, B)`` (the batch on the contiguous axis)."""
    m, B = E.shape
    h_x = np.asarray(h_x, dtype=float)
    w = np.asarray(weight_theta1, dtype=float)
    d = np.arange(m)[:, None] * h_x[None, :]  # (m, B), the same products as k * h_x anywhere else
    r = E + np.asarray(rho, dtype=float)[None, :]
    left = d <= w * (1.0 + SCP_TIE_RTOL)  # d_0 = 0 <= w: never empty
    theta = np.full(B, -np.inf)  # no point right of w: theta1 = 0 is optimal (clipped below)
    has_right = ~left[-1]  # d increases with k: the last point is the first to be right of w
    if has_right.any():
        # Only the cells with a point right of w, on their own columns (each cell's LP is its own).
        cols = slice(None) if has_right.all() else np.flatnonzero(has_right)
        theta[cols] = _bridge_slopes(r[:, cols], d[:, cols], left[:, cols])
    theta1 = np.clip(theta, 0.0, float(L_x))
    theta2 = np.maximum(0.0, np.max(r - theta1[None, :] * d, axis=0))
    return theta1, theta2


def _bridge_slopes(r: np.ndarray, d: np.ndarray, left: np.ndarray) -> np.ndarray:
    """``min_{i left} max_{j right} (r_j - r_i) / (d_j - d_i)`` per column (see :func:`scp_parameters_scalar`).

    ``r``, ``d``, ``left`` have shape ``(m, C)``; every column has a point right of ``w`` (``~left``), and
    ``left`` is a prefix of each column (``d`` increases), with ``left[0]`` true.
    """
    m, C = r.shape
    right = ~left
    lefts = np.flatnonzero(left.any(axis=1))  # indices i left of w in some column (a prefix)
    j0 = int(np.flatnonzero(right.any(axis=1))[0])  # >= 1
    r_right = np.where(right, r, -np.inf)  # a non-right j gives slope -inf: it never raises the max
    i_end = int(lefts[-1]) + 1
    with np.errstate(divide="ignore", invalid="ignore"):
        if i_end * (m - j0) * C <= SMALL_TABLE:
            # Small batch: every (i, j) at once (a few calls instead of a few per i; the same quotients).
            s = (r_right[None, j0:] - r[:i_end, None]) / (d[None, j0:] - d[:i_end, None])  # (i, j, C)
            ahead = np.arange(j0, m)[None, :] > np.arange(i_end)[:, None]  # only j > i is a pair
            s = np.where(ahead[:, :, None], s, -np.inf).max(axis=1)
            return np.where(left[:i_end], s, np.inf).min(axis=0)
        theta = np.full(C, np.inf)
        num = np.empty((m - j0, C))
        den = np.empty((m - j0, C))
        best = np.empty(C)
        for i in map(int, lefts):
            j = max(i + 1, j0)
            if j >= m:
                break
            k = m - j
            np.subtract(r_right[j:], r[i], out=num[:k])
            np.subtract(d[j:], d[i], out=den[:k])
            np.divide(num[:k], den[:k], out=num[:k])
            np.max(num[:k], axis=0, out=best)  # max over j right of w of s_ij
            if i:  # (i = 0 is left everywhere)
                np.copyto(best, np.inf, where=~left[i])
            np.minimum(theta, best, out=theta)
    return theta


def scp_reference(
    x: np.ndarray, xn: np.ndarray, rho: float, L_x: float, weight_theta1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The corrected SCP of one cell as a plain LP over every sample pair, solved by HiGHS.

    This is the reference formulation the batched solvers are tested against. One output row ``j`` at a
    time (rows decouple): variables ``theta1[j, :]`` (n) and ``theta2[j]``.

    Parameters
    ----------
    x : ndarray, shape (S, n)
        State samples (internal-input samples need not be given: only ``|x_l - x_m|`` enters).
    xn : ndarray, shape (S, n)
        Their successors.
    weight_theta1 : ndarray, shape (n,)
        Objective weights of ``theta1[j, :]`` (ones for the paper's objective).

    Returns
    -------
    theta1 : ndarray, shape (n, n)
    theta2 : ndarray, shape (n,)
    """
    from scipy.optimize import linprog

    S, n = x.shape
    # Pairs (l, l) count: two points of the cell may share their nearest sample, so theta2 >= rho is needed.
    il, jl = np.triu_indices(S, k=0)
    D = np.abs(x[il] - x[jl])  # (P, n)
    theta1 = np.zeros((n, n))
    theta2 = np.zeros(n)
    for j in range(n):
        e = np.abs(xn[il, j] - xn[jl, j]) + rho
        # theta1 . D + theta2 >= e   ->   -D theta1 - theta2 <= -e
        A = np.hstack([-D, -np.ones((D.shape[0], 1))])
        A = np.vstack([A, np.r_[np.ones(n), 0.0][None, :]])  # ||theta1 row||_1 <= L_x
        bnd = np.r_[-e, L_x]
        c = np.r_[weight_theta1, 1.0]
        res = linprog(c, A_ub=A, b_ub=bnd, bounds=[(0, None)] * (n + 1), method="highs")
        if res.status != 0:  # pragma: no cover - the LP is always feasible (theta1 = 0, theta2 large)
            raise RuntimeError(f"reference SCP failed: {res.message}")
        theta1[j] = res.x[:n]
        theta2[j] = res.x[n]
    return theta1, theta2
