"""The corrected SCP (Theorem 4.4, Eq. 4.5, docs/method.md §2) for any ``dim(x)``, solved exactly in batch.

Per triple and output row ``j`` the LP is::

    min  w . theta1 + theta2
    s.t. theta1 . |x_l - x_m| + theta2 >= |x'_{l,j} - x'_{m,j}| + rho_j   for every sample pair (l, m)
         theta1 >= 0,  a . theta1 <= L_j,  theta2 >= 0

with ``w = 1`` (the paper's objective ``1'theta``) or ``w = r_x`` (the radius objective). The budget
``a . theta1 <= L_j`` is what the margin ``rho_j`` pays for (``growth_bound.ScpBound``): ``a = 1``, ``L_j = L_x``
with one Lipschitz constant in the infinity norm (``sum(theta1) <= L_x``, the paper's bound), or ``a = h`` (the
sub-grid spacings), ``L_j = sum_i L_ji h_i`` with per-component constants. The state samples lie
on a regular sub-grid of the cell (``counts`` points per axis, spacing ``h``), so a pair enters only through
its index displacement ``k = |idx_l - idx_m|`` (component-wise): ``|x_l - x_m| = k h``. The pairs of one
displacement class give one constraint, ``theta1 . d_k + theta2 >= r_k`` with ``d_k = k h`` and
``r_k = E_k + rho``, ``E_{k,j}`` the largest ``|x'_{l,j} - x'_{m,j}|`` over the class and over the
internal-input samples (:func:`pair_maxima_nd`). Signs do not matter: for ``n = 2`` the displacements
``(k1, k2)`` and ``(k1, -k2)`` are different pair sets with the same ``d_k``, so both go into ``E_k``. That
leaves ``prod(counts)`` constraints and ``n + 1`` variables: the LP of all pairs with its duplicate rows merged,
so the same optimum.

Each tiny LP is solved exactly by the simplex method on its dual (:func:`_solve_row`), compiled with numba and
run over the whole batch. What it returns is then made sound by construction (clip, scale, recompute
``theta2``), so a rounding error can only cost optimality, never soundness. :func:`scp_cvxpy` is the same LP
stacked for a batch in one cvxpy problem (the reference the tests compare against, besides
:func:`pipelines.abstraction.growth_bound.scp_reference`).
"""

from __future__ import annotations

import functools

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True, error_model="numpy")

#: Reduced costs above ``-SIMPLEX_TOL * scale`` count as non-negative (optimal); pivot entries below
#: ``SIMPLEX_TOL`` times their column's largest are not pivoted on. Only optimality depends on them: the
#: solution is repaired to a feasible one afterwards.
SIMPLEX_TOL = 1e-12

#: Pivots after which the simplex stops (Bland's rule terminates far earlier: the dual has ``n + 1`` rows).
MAX_PIVOTS = 500


@functools.lru_cache(maxsize=32)
def displacement_classes(counts: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The unordered pairs ``l <= m`` of state samples and their displacement classes.

    Parameters
    ----------
    counts : tuple of int
        Sub-grid points per state axis (samples flat in row-major order).

    Returns
    -------
    pl, pm : ndarray of int64, shape (P,)
        The pairs, ``P = S (S + 1) / 2`` with ``S = prod(counts)`` (``l = m`` included: two points of a cell
        may share their nearest sample, so ``theta2 >= rho`` is needed).
    cls : ndarray of int64, shape (P,)
        Class of each pair: the row-major flat index of ``|idx_l - idx_m|`` in ``counts``.
    k : ndarray of float64, shape (prod(counts), n)
        The displacement of each class, in sub-grid steps.
    """
    shape = tuple(int(c) for c in counts)
    S = int(np.prod(shape))
    idx = np.stack(np.unravel_index(np.arange(S), shape), axis=-1)  # (S, n)
    pl, pm = np.triu_indices(S)
    cls = np.ravel_multi_index(tuple(np.abs(idx[pl] - idx[pm]).T), shape)
    k = np.stack(np.unravel_index(np.arange(S), shape), axis=-1).astype(float)
    out = (pl.astype(np.int64), pm.astype(np.int64), cls.astype(np.int64), k)
    for a in out:
        a.setflags(write=False)
    return out


@_jit
def pair_maxima_nd(vmax: np.ndarray, vmin: np.ndarray, pl: np.ndarray, pm: np.ndarray, cls: np.ndarray,
                   classes: int) -> np.ndarray:
    """``E[k, j, b]``: the largest ``|x'_{l,j} - x'_{m,j}|`` over the pairs of displacement class ``k`` and any
    internal-input samples, from the per-state-sample extremes (the n-D
    :func:`pipelines.abstraction.growth_bound.pair_maxima_batch_last`).

    Parameters
    ----------
    vmax, vmin : ndarray, shape (S_x, n, B), finite
        Extremes of each successor component over the internal-input samples at each state sample.
    pl, pm, cls : ndarray of int64, shape (P,)
        Pairs and classes from :func:`displacement_classes`.
    classes : int
        Number of classes, ``S_x``.

    Returns
    -------
    ndarray, shape (classes, n, B)
    """
    _, n, B = vmax.shape
    out = np.full((classes, n, B), -np.inf)
    for q in range(pl.shape[0]):
        o = out[cls[q]]
        hl, ll = vmax[pl[q]], vmin[pl[q]]
        hm, lm = vmax[pm[q]], vmin[pm[q]]
        for j in range(n):
            oj, a, b_, c, d = o[j], hm[j], ll[j], hl[j], lm[j]
            for b in range(B):
                oj[b] = max(oj[b], a[b] - b_[b], c[b] - d[b])
    return out


@_jit
def _solve_row(d: np.ndarray, r: np.ndarray, w: np.ndarray, L: float, coef: np.ndarray, tab: np.ndarray,
               basis: np.ndarray, theta1: np.ndarray) -> float:
    """One LP of the module docstring, exactly, by the primal simplex on its dual; writes ``theta1`` and returns
    ``theta2``, both repaired to a feasible point.

    The dual, ``max r'lam - L mu  s.t.  sum_k lam_k d_{k,a} - coef_a mu <= w_a (a < n),  sum_k lam_k <= 1,
    lam, mu >= 0``, has a non-negative right-hand side ``(w, 1)``, so its slack basis is feasible: no phase 1.
    Bland's rule (smallest entering index, smallest leaving basic index on ties) rules out cycling. At the
    optimum the reduced costs of the slacks are the primal solution ``(theta1, theta2)``.

    Parameters
    ----------
    d : ndarray, shape (K, n)
        ``d_k``, non-negative.
    r : ndarray, shape (K,)
        ``r_k``.
    w : ndarray, shape (n,)
        Objective weights of ``theta1``, non-negative.
    L : float
        The budget of ``coef . theta1``.
    coef : ndarray, shape (n,)
        Positive weights of the budget (ones: ``sum(theta1) <= L``).
    tab : ndarray, shape (n + 2, K + n + 3)
        Workspace (rows: the n + 1 constraints, then the reduced costs; last column the right-hand side).
    basis : ndarray of int64, shape (n + 1,)
        Workspace.
    theta1 : ndarray, shape (n,)
        Output.
    """
    K, n = d.shape
    rows = n + 1
    cols = K + 1 + rows  # lam (K), mu, slacks (n + 1)
    rhs = cols
    tab[:, :] = 0.0
    scale = L
    for k in range(K):
        scale = max(scale, abs(r[k]))
        for a in range(n):
            tab[a, k] = d[k, a]
        tab[n, k] = 1.0
        tab[rows, k] = -r[k]
    for a in range(n):
        tab[a, K] = -coef[a]
        tab[a, rhs] = w[a]
    tab[rows, K] = L
    tab[n, rhs] = 1.0
    for i in range(rows):
        tab[i, K + 1 + i] = 1.0
        basis[i] = K + 1 + i
    tol = SIMPLEX_TOL * scale
    for _ in range(MAX_PIVOTS):
        enter = -1
        for c in range(cols):
            if tab[rows, c] < -tol:
                enter = c
                break
        if enter < 0:
            break
        big = 0.0
        for i in range(rows):
            big = max(big, abs(tab[i, enter]))
        leave = -1
        best = np.inf
        for i in range(rows):
            a = tab[i, enter]
            if a > SIMPLEX_TOL * big:
                ratio = tab[i, rhs] / a
                if ratio < best or (ratio == best and basis[i] < basis[leave]):
                    best = ratio
                    leave = i
        if leave < 0:  # unbounded dual: impossible (theta1 = 0, theta2 = max r is primal feasible)
            break
        p = tab[leave, enter]
        for c in range(cols + 1):
            tab[leave, c] /= p
        for i in range(rows + 1):
            if i != leave:
                f = tab[i, enter]
                if f != 0.0:
                    for c in range(cols + 1):
                        tab[i, c] -= f * tab[leave, c]
        basis[leave] = enter
    # Repair: theta1 >= 0 with coef . theta1 <= L (the proof of rho needs it), then the smallest feasible theta2,
    # so that every pair constraint holds whatever the rounding of the pivots.
    total = 0.0
    for a in range(n):
        theta1[a] = max(tab[rows, K + 1 + a], 0.0)
        total += theta1[a] * coef[a]
    if total > L:
        f = L / total * (1.0 - 1e-15)
        for a in range(n):
            theta1[a] *= f
    theta2 = 0.0
    for k in range(K):
        s = r[k]
        for a in range(n):
            s -= theta1[a] * d[k, a]
        theta2 = max(theta2, s)
    return theta2


@_jit
def _row_workspace(K: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The arrays :func:`_solve_row` works in for ``K`` classes and ``n`` coordinates, made once per call and reused
    for every row: the tableau, its basis, the constraints ``d`` and ``r``, and the unit coefficients."""
    return np.empty((n + 2, K + n + 3)), np.empty(n + 1, dtype=np.int64), np.empty((K, n)), np.empty(K), np.ones(n)


@_jit
def scp_parameters_rows(E: np.ndarray, k: np.ndarray, h: np.ndarray, rho: np.ndarray, budget: np.ndarray,
                        by_spacing: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The SCP of every triple and output row: ``theta1`` of shape (B, n, n) and ``theta2`` of shape (B, n).

    Parameters
    ----------
    E : ndarray, shape (K, n, B)
        Pair maxima (:func:`pair_maxima_nd`).
    k : ndarray, shape (K, n)
        Displacement of each class in sub-grid steps (:func:`displacement_classes`).
    h : ndarray, shape (B, n)
        Sub-grid spacings.
    rho, budget : ndarray, shape (B, n)
        Margin and budget ``L_j`` of each row (module docstring).
    by_spacing : ndarray of bool, shape (B, n)
        Whether a row's budget weighs ``theta1`` by the spacings (``h . theta1 <= L_j``) or not (``sum(theta1) <=
        L_j``).
    W : ndarray, shape (B, n)
        Objective weights of ``theta1`` (ones: the paper's objective; the half-widths: the radius objective).
    """
    K, n, B = E.shape
    theta1 = np.zeros((B, n, n))
    theta2 = np.zeros((B, n))
    tab, basis, d, r, ones = _row_workspace(K, n)
    for b in range(B):
        for q in range(K):
            for a in range(n):
                d[q, a] = k[q, a] * h[b, a]
        for j in range(n):
            for q in range(K):
                r[q] = E[q, j, b] + rho[b, j]
            coef = h[b] if by_spacing[b, j] else ones
            theta2[b, j] = _solve_row(d, r, W[b], budget[b, j], coef, tab, basis, theta1[b, j])
    return theta1, theta2


def scp_parameters_nd(E: np.ndarray, k: np.ndarray, h: np.ndarray, rho: np.ndarray, L_x: float,
                      W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`scp_parameters_rows` with one constant in the infinity norm: margin ``rho`` (shape (B,)) and budget
    ``sum(theta1) <= L_x`` for every row."""
    B, n = h.shape
    return scp_parameters_rows(E, k, h, _rows(rho, n), np.full((B, n), float(L_x)), np.zeros((B, n), dtype=np.bool_),
                               W)


def _rows(v: np.ndarray, n: int) -> np.ndarray:
    """A per-triple value, shape (B,), as the same value in every row, shape (B, n), contiguous."""
    return np.ascontiguousarray(np.broadcast_to(np.asarray(v, dtype=float)[:, None], (v.shape[0], n)))


@_jit
def scp_radii_rows(E: np.ndarray, k: np.ndarray, h: np.ndarray, rho: np.ndarray, budget: np.ndarray,
                   by_spacing: np.ndarray, W: np.ndarray, r_x: np.ndarray, lip: np.ndarray,
                   skip_rtol: float) -> np.ndarray:
    """The SCP radius ``min(theta1_j . r_x + theta2_j, lip_j)`` of every triple and output row, shape (B, n).

    A row whose LP cannot beat its Lipschitz radius is not solved: every feasible ``theta`` has
    ``theta1 . r_x + theta2 >= theta1 . d_k + theta2 >= r_k`` for a class with ``d_k <= r_x`` (``2 k_a <= counts_a``,
    ``theta1 >= 0``), so where ``max`` of those ``r_k`` exceeds ``lip_j`` by the relative margin ``skip_rtol`` (far
    above the rounding of ``d_k``) the minimum is ``lip_j``, to the bit.

    Parameters
    ----------
    E, k, h, rho, budget, by_spacing, W
        As :func:`scp_parameters_rows`.
    r_x : ndarray, shape (B, n)
        Half-widths of the state cells.
    lip : ndarray, shape (B, n)
        Lipschitz radius of each row (Lemma 4.3, per component).
    """
    K, n, B = E.shape
    counts = np.empty(n)
    for a in range(n):
        counts[a] = 1.0
        for q in range(K):
            counts[a] = max(counts[a], k[q, a] + 1.0)
    near = np.ones(K, dtype=np.bool_)
    for q in range(K):
        for a in range(n):
            if 2.0 * k[q, a] > counts[a]:
                near[q] = False
    rad = np.empty((B, n))
    tab, basis, d, r, ones = _row_workspace(K, n)
    theta1 = np.empty(n)
    for b in range(B):
        filled = False
        for j in range(n):
            bound = -np.inf
            for q in range(K):
                if near[q]:
                    bound = max(bound, E[q, j, b])
            if bound + rho[b, j] >= lip[b, j] * (1.0 + skip_rtol):
                rad[b, j] = lip[b, j]
                continue
            if not filled:
                for q in range(K):
                    for a in range(n):
                        d[q, a] = k[q, a] * h[b, a]
                filled = True
            for q in range(K):
                r[q] = E[q, j, b] + rho[b, j]
            coef = h[b] if by_spacing[b, j] else ones
            t2 = _solve_row(d, r, W[b], budget[b, j], coef, tab, basis, theta1)
            s = t2
            for a in range(n):
                s += theta1[a] * r_x[b, a]
            rad[b, j] = min(s, lip[b, j])  # both bounds are sound: so is their minimum
    return rad


def scp_radii_nd(E: np.ndarray, k: np.ndarray, h: np.ndarray, rho: np.ndarray, L_x: float, W: np.ndarray,
                 r_x: np.ndarray, lip: np.ndarray, skip_rtol: float) -> np.ndarray:
    """:func:`scp_radii_rows` with one constant in the infinity norm: margin ``rho`` and Lipschitz radius ``lip``
    of shape (B,), budget ``sum(theta1) <= L_x``, for every row."""
    B, n = h.shape
    return scp_radii_rows(E, k, h, _rows(rho, n), np.full((B, n), float(L_x)), np.zeros((B, n), dtype=np.bool_),
                          W, r_x, _rows(lip, n), skip_rtol)


def pair_maxima_of(V: np.ndarray, counts: tuple[int, ...]) -> np.ndarray:
    """:func:`pair_maxima_nd` of successor samples ``V`` of shape (S_x, S_w, B, n), state samples row-major in
    ``counts``: shape (S_x, n, B)."""
    pl, pm, cls, k = displacement_classes(counts)
    # per state sample and component, extremes over the internal-input samples, the triples contiguous
    vmax = np.ascontiguousarray(V.max(axis=1).transpose(0, 2, 1))
    vmin = np.ascontiguousarray(V.min(axis=1).transpose(0, 2, 1))
    return pair_maxima_nd(vmax, vmin, pl, pm, cls, k.shape[0])


def scp_constraints(E: np.ndarray, k: np.ndarray, h: np.ndarray, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The merged constraints of every triple and row as arrays: ``d`` of shape (B, K, n), ``r`` of shape (B, n, K)."""
    d = k[None, :, :] * h[:, None, :]
    r = np.moveaxis(E, (0, 1, 2), (2, 1, 0)) + rho[:, None, None]
    return d, r


@functools.lru_cache(maxsize=8)
def _cvxpy_problem(P: int, K: int, n: int) -> tuple:
    """One stacked, parametrised problem of ``P`` LPs (DPP: compiled once, re-solved with new parameters)."""
    import cvxpy as cp

    T1 = cp.Variable((P, n), nonneg=True)
    T2 = cp.Variable(P, nonneg=True)
    D = cp.Parameter((P * K, n), nonneg=True)
    R = cp.Parameter(P * K)
    Wp = cp.Parameter((P, n), nonneg=True)
    L = cp.Parameter(nonneg=True)
    owner = np.repeat(np.arange(P), K)
    constraints = [
        cp.sum(cp.multiply(D, T1[owner]), axis=1) + T2[owner] >= R,
        cp.sum(T1, axis=1) <= L,
    ]
    problem = cp.Problem(cp.Minimize(cp.sum(cp.multiply(Wp, T1)) + cp.sum(T2)), constraints)
    return problem, T1, T2, D, R, Wp, L


def scp_cvxpy(d: np.ndarray, r: np.ndarray, L_x: float, w: np.ndarray, solver: str = "HIGHS"
              ) -> tuple[np.ndarray, np.ndarray]:
    """A batch of the LPs of the module docstring as one cvxpy problem (the reference formulation).

    Parameters
    ----------
    d : ndarray, shape (P, K, n)
        Constraint rows ``d_k`` of each LP.
    r : ndarray, shape (P, K)
        Right-hand sides ``r_k``.
    L_x : float
    w : ndarray, shape (P, n)
        Objective weights of ``theta1``.
    solver : str
        A cvxpy LP solver, ``'HIGHS'`` (exact simplex) or ``'CLARABEL'`` (interior point, about 1e-8).

    Returns
    -------
    theta1 : ndarray, shape (P, n)
    theta2 : ndarray, shape (P,)
    """
    P, K, n = d.shape
    problem, T1, T2, D, R, Wp, L = _cvxpy_problem(P, K, n)
    D.value = np.ascontiguousarray(d.reshape(P * K, n), dtype=float)
    R.value = np.ascontiguousarray(r.reshape(P * K), dtype=float)
    Wp.value = np.asarray(w, dtype=float)
    L.value = float(L_x)
    problem.solve(solver=solver)
    if problem.status != "optimal":  # pragma: no cover - the LPs are always feasible and bounded
        raise RuntimeError(f"cvxpy SCP failed: {problem.status}")
    return np.asarray(T1.value), np.asarray(T2.value)


def warm_up() -> None:
    """Compile (or load from the disk cache) the kernels for the argument types the per-cell stage passes."""
    pl, pm, cls, k = displacement_classes((2, 2))
    v = np.zeros((4, 2, 1))
    E = pair_maxima_nd(v, v, pl, pm, cls, 4)
    one = np.ones((1, 2))
    flags = np.zeros((1, 2), dtype=np.bool_)
    scp_parameters_rows(E, k, one, one, one, flags, one)
    scp_radii_rows(E, k, one, one, one, flags, one, one, one, 0.0)

