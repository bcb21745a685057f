"""Growth bounds (Definition 4.1): boxes that contain ``{f(x, u, w) : x in cell(x̂), w in cell(ŵ)}``.

Three methods, all sound given Lipschitz constants ``L_x``, ``L_w`` in the infinity norm (METHOD §2):

``lipschitz``
    Lemma 4.3, the paper's conservative baseline: radius ``L_x ||r_x|| + L_w ||r_w||`` around
    ``c = f(x̂, û, ŵ)``, where ``r`` are the half-widths of the (clipped) cells.
``scp``
    Theorem 4.4, the paper's method, corrected so that it is feasible (see :func:`scp_parameters`).
``hull``
    Beyond the paper: ``[min_l x'_l - rho_h, max_l x'_l + rho_h]``, ``rho_h = L_x ||h_x/2|| + L_w ||h_w/2||``,
    where ``h`` are the sub-cell spacings of the samples.

All functions work on batches of cells: arrays carry the batch along axis 0.
"""

from __future__ import annotations

import numpy as np

#: Outward floating-point margin, relative to the magnitude of a bound. Radii and sample values are
#: computed in float64 with a handful of operations; 1e-12 relative is orders above their rounding error.
FP_RTOL = 1e-12


def widen(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Round a box outwards by a relative floating-point margin (never shrinks it)."""
    scale = np.maximum(np.abs(lo), np.abs(hi))
    return lo - FP_RTOL * scale, hi + FP_RTOL * scale


def subgrid_counts(samples: int, dims: int) -> tuple[int, ...]:
    """Points per dimension of a sub-grid with at most ``samples`` points in all, as even as possible.

    With ``dims = dim(x) + dim(w)`` this is how the ``N_C`` samples of a joint cell are laid out
    (Theorem 4.4 uses ``eta_x / N_C^(1/dim)`` spacings; we sample ``x`` and ``w`` jointly, METHOD §2).
    """
    if dims == 0:
        return ()
    m = max(1, int(np.floor(samples ** (1.0 / dims) + 1e-9)))
    while m ** dims > samples:  # guard the float root
        m -= 1
    counts = [m] * dims
    for i in range(dims):
        trial = counts.copy()
        trial[i] += 1
        if np.prod(trial) <= samples:
            counts = trial
    return tuple(counts)


def lipschitz_radius(r_x: np.ndarray, r_w: np.ndarray, L_x: float, L_w: float) -> np.ndarray:
    """Radius of Lemma 4.3, shape (B,): ``L_x ||r_x||_inf + L_w ||r_w||_inf`` (the same in every component).

    Parameters
    ----------
    r_x : ndarray, shape (B, n)
        Half-widths of the clipped state cells.
    r_w : ndarray, shape (B, p)
        Half-widths of the clipped internal-input cells (``p`` may be 0).
    """
    rad = L_x * np.max(r_x, axis=1)
    if r_w.shape[1]:
        rad = rad + L_w * np.max(r_w, axis=1)
    return rad


def scp_rho(h_x: np.ndarray, h_w: np.ndarray, L_x: float, L_w: float) -> np.ndarray:
    """The margin ``rho`` of the corrected SCP, shape (B,).

    For any ``x_1, x_2`` in the cell and ``w_1, w_2`` in the internal-input cell, take the nearest samples
    ``(x_l, w_l)``, ``(x_m, w_m)``: each is within ``h/2`` per component. Then

    ``|f(x_1,w_1) - f(x_2,w_2)| <= |x'_l - x'_m| + L_x ||h_x|| + L_w ||h_w||``  (two Lipschitz steps of h/2),

    and since ``|x_l - x_m| <= |x_1 - x_2| + h_x`` and ``||theta_1|| <= L_x``,

    ``theta_1 |x_l - x_m| <= theta_1 |x_1 - x_2| + L_x ||h_x||``.

    So if every sample pair satisfies ``|x'_l - x'_m| <= theta_1 |x_l - x_m| + theta_2 - rho`` with
    ``rho = 2 L_x ||h_x|| + L_w ||h_w||``, every pair of the cell satisfies the growth-bound inequality (4.2).
    The paper's ``rho = 4 L_x eta_hat + 2 L_w ||eta_w||`` bounds ``||x_1 - x_l||`` by a whole sub-cell and
    ``||w_1 - w_l||`` by a whole cell (it does not sample ``w``); ours is the same argument with ``w`` sampled.
    """
    rho = 2.0 * L_x * np.max(h_x, axis=1)
    if h_w.shape[1]:
        rho = rho + L_w * np.max(h_w, axis=1)
    return rho


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
    """
    vmax = values.max(axis=2)
    vmin = values.min(axis=2)
    m = values.shape[1]
    out = np.empty(values.shape[:2])
    out[:, 0] = np.max(vmax - vmin, axis=1)
    for k in range(1, m):
        up = vmax[:, k:] - vmin[:, :-k]
        down = vmax[:, :-k] - vmin[:, k:]
        out[:, k] = np.maximum(up.max(axis=1), down.max(axis=1))
    return out


def scp_parameters_scalar(
    E: np.ndarray, h_x: np.ndarray, rho: np.ndarray, L_x: float, weight_theta1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the corrected SCP (Eq. 4.5, METHOD §2) exactly for a scalar state, in batch.

    The LP per cell, with ``d_k = k h_x``::

        min  weight_theta1 * theta1 + theta2
        s.t. theta1 * d_k + theta2 >= E_k + rho     for k = 0 .. m-1
             0 <= theta1 <= L_x,   theta2 >= 0

    It has two variables, so its optimum is a vertex: ``theta1`` is 0, ``L_x``, the slope through two
    constraint lines' intersection points ``(d_k, E_k + rho)``, or the slope of such a point seen from
    ``(0, 0)`` (where ``theta2 >= 0`` is active). We evaluate the objective at every candidate (clipped to
    the bounds, with the smallest feasible ``theta2``) and take the minimum, so the result is the LP optimum
    up to rounding; :func:`scp_reference` is the same LP through HiGHS, which the tests compare against.

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
    B, m = E.shape
    d = np.arange(m)[None, :] * h_x[:, None]  # (B, m)
    rhs = E + rho[:, None]
    cands = [np.zeros((B, 1)), np.full((B, 1), float(L_x))]
    iu, ju = np.triu_indices(m, k=1)
    if iu.size:
        cands.append((rhs[:, ju] - rhs[:, iu]) / (d[:, ju] - d[:, iu]))
    if m > 1:
        cands.append(rhs[:, 1:] / d[:, 1:])
    a = np.clip(np.concatenate(cands, axis=1), 0.0, float(L_x))  # (B, C)
    best_obj = np.full(B, np.inf)
    best_a = np.zeros(B)
    best_b = np.zeros(B)
    step = max(1, 4_000_000 // max(1, B * m))
    for s in range(0, a.shape[1], step):
        ab = a[:, s : s + step]  # (B, c)
        b = np.maximum(0.0, np.max(rhs[:, None, :] - ab[:, :, None] * d[:, None, :], axis=2))
        obj = weight_theta1[:, None] * ab + b
        j = np.argmin(obj, axis=1)
        o = obj[np.arange(B), j]
        better = o < best_obj
        best_obj = np.where(better, o, best_obj)
        best_a = np.where(better, ab[np.arange(B), j], best_a)
        best_b = np.where(better, b[np.arange(B), j], best_b)
    return best_a, best_b


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
