"""Compiled kernels of the per-cell stage (numba): :func:`scalar_block`, everything ``block.abstract_block``
computes after the black box for a scalar subsystem in one pass, and the kernels it is made of (the sample pass,
the pair maxima, the closed-form SCP); :func:`box_block`, the same for the Lipschitz and hull bounds of any
subsystem; instead of a few dozen numpy calls and their temporaries.

Every kernel computes exactly the values of the numpy function named in its docstring, which stays the
reference (the tests compare the two bit for bit on random and degenerate inputs): the kernels use the same
floating-point operations on the same operands, and only maxima, minima and comparisons (exact) are
reordered. numba compiles without ``fastmath``, so no operation is contracted or reassociated.

Compilation (1-2 s for all of them) happens at the first call in a process and is cached on disk beside this
module (numba's ``cache=True``; where that directory is read-only numba uses ``NUMBA_CACHE_DIR`` or the user's
cache directory). :func:`warm_up` compiles them ahead of a timing. Tolerances come in as arguments, never as
globals of another module: numba freezes a global into the compiled code, and its disk cache only notices
changes to this file.

``bench/run.py --cases scp`` times them beside the numpy path and checks that both give the same bits
(docs/benchmarks.md).
"""

from __future__ import annotations

import numba
import numpy as np

# error_model="numpy": a float division by zero gives inf/nan as in numpy instead of raising; nogil: a Dask
# worker's other threads run while a kernel does.
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")


@_jit
def scalar_sample_pass(V: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`pipelines.abstraction.block._scalar_sample_pass` in one read of the samples.

    Parameters
    ----------
    V : ndarray, shape (S_x, S_w, B), float64, finite
        Successor samples (state sample, internal-input sample, triple). Finite: the black box guarantees it,
        and a comparison with NaN would not propagate it as ``np.max`` does.

    Returns
    -------
    vmax_w, vmin_w, dx, dw : ndarray, shapes (S_x, B), (S_x, B), (B,), (B,)
        Those of the reference: the extremes over the internal-input samples at each state sample, and the
        largest neighbour differences along the state and the internal-input axis.
    """
    Sx, Sw, B = V.shape
    vmax = np.empty((Sx, B))
    vmin = np.empty((Sx, B))
    dx = np.zeros(B)
    dw = np.zeros(B)
    for k in range(Sx):
        hi = vmax[k]
        lo = vmin[k]
        first = V[k, 0]
        # The state-axis differences in the same read (the previous state sample's rows are still cached); at
        # k = 0 a row against itself adds |v - v| = 0 (the samples are finite), which leaves dx as it is.
        up = V[k - 1, 0] if k else first
        for b in range(B):
            hi[b] = first[b]
            lo[b] = first[b]
            dx[b] = max(dx[b], abs(first[b] - up[b]))
        for j in range(1, Sw):
            row = V[k, j]
            prev = V[k, j - 1]
            up = V[k - 1, j] if k else row
            for b in range(B):
                v = row[b]
                hi[b] = max(hi[b], v)
                lo[b] = min(lo[b], v)
                dw[b] = max(dw[b], abs(v - prev[b]))
                dx[b] = max(dx[b], abs(v - up[b]))
    return vmax, vmin, dx, dw


@_jit
def hull_and_bound(vmax: np.ndarray, vmin: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sample hull and the quick lower bound of the SCP radius that :func:`pipelines.abstraction.block.abstract_block`
    tries before the pair maxima, from the per-state-sample extremes.

    Parameters
    ----------
    vmax, vmin : ndarray, shape (m_x, B), finite
    half : int
        ``m_x // 2``.

    Returns
    -------
    hull_lo, hull_hi : ndarray, shape (B,)
        ``vmin.min(axis=0)``, ``vmax.max(axis=0)``.
    bound : ndarray, shape (B,)
        ``max(E_0, E_half)`` of :func:`pair_maxima_batch_last` (only ``E_0`` when ``half == 0``).
    """
    m, B = vmax.shape
    hull_lo = vmin[0].copy()
    hull_hi = vmax[0].copy()
    bound = np.empty(B)
    for b in range(B):
        bound[b] = vmax[0, b] - vmin[0, b]
    for k in range(1, m):
        for b in range(B):
            hull_lo[b] = min(hull_lo[b], vmin[k, b])
            hull_hi[b] = max(hull_hi[b], vmax[k, b])
            bound[b] = max(bound[b], vmax[k, b] - vmin[k, b])
    if half:
        for i in range(m - half):
            for b in range(B):
                bound[b] = max(bound[b], vmax[i + half, b] - vmin[i, b], vmax[i, b] - vmin[i + half, b])
    return hull_lo, hull_hi, bound


@_jit
def pair_maxima_batch_last(vmax: np.ndarray, vmin: np.ndarray) -> np.ndarray:
    """:func:`pipelines.abstraction.growth_bound.pair_maxima_batch_last`:
    ``E[k] = max_l max(vmax[l + k] - vmin[l], vmax[l] - vmin[l + k])``.

    Parameters
    ----------
    vmax, vmin : ndarray, shape (m_x, B), finite

    Returns
    -------
    ndarray, shape (m_x, B)
    """
    m, B = vmax.shape
    out = np.empty((m, B))
    for k in range(m):
        o = out[k]
        for b in range(B):
            o[b] = vmax[k, b] - vmin[0, b]
        for i in range(m - k):
            up = vmax[i + k]
            down_hi = vmax[i]
            lo_i = vmin[i]
            lo_k = vmin[i + k]
            for b in range(B):
                o[b] = max(o[b], up[b] - lo_i[b], down_hi[b] - lo_k[b])
    return out


@_jit
def scp_parameters_batch_last(
    E: np.ndarray, h_x: np.ndarray, rho: np.ndarray, L_x: float, weight_theta1: np.ndarray, tie_rtol: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pipelines.abstraction.growth_bound.scp_parameters_batch_last`: the closed-form SCP (Eq. 4.5, docs/method.md §2) per
    column, ``theta1 = clip(min_{d_i <= w} max_{d_j > w} (r_j - r_i) / (d_j - d_i), 0, L_x)``,
    ``theta2 = max(0, max_k r_k - theta1 d_k)``, with ``d_k = k h_x``, ``r_k = E_k + rho``.

    Parameters
    ----------
    E : ndarray, shape (m, B), finite
        Pair maxima.
    h_x, rho, weight_theta1 : ndarray, shape (B,)
    L_x : float
    tie_rtol : float
        ``growth_bound.SCP_TIE_RTOL``.

    Returns
    -------
    theta1, theta2 : ndarray, shape (B,)
    """
    m, B = E.shape
    theta1 = np.empty(B)
    theta2 = np.empty(B)
    for b in range(B):
        theta1[b], theta2[b] = _scp_column(E[:, b], h_x[b], rho[b], L_x, weight_theta1[b], tie_rtol)
    return theta1, theta2


@_jit
def _scp_column(e: np.ndarray, h: float, rho: float, L_x: float, w: float, tie_rtol: float) -> tuple[float, float]:
    """``(theta1, theta2)`` of one cell's SCP from its pair maxima ``e``, shape (m,) (see
    :func:`scp_parameters_batch_last`)."""
    m = e.shape[0]
    limit = w * (1.0 + tie_rtol)
    right = m  # first k with d_k right of w (d increases with k: the left points are a prefix)
    for k in range(m):
        if not (k * h <= limit):
            right = k
            break
    theta = -np.inf  # no point right of w: theta1 = 0 is optimal (clipped below)
    if right < m:
        theta = np.inf
        for i in range(right):
            r_i = e[i] + rho
            d_i = i * h
            s = -np.inf
            for j in range(right, m):
                s = max(s, ((e[j] + rho) - r_i) / (j * h - d_i))
            theta = min(theta, s)
    t1 = min(max(theta, 0.0), L_x)
    t2 = 0.0
    for k in range(m):
        t2 = max(t2, (e[k] + rho) - t1 * (k * h))
    return t1, t2


@_jit
def _cell_range(
    lo: float, hi: float, origin: float, eta: float, k_lo: int, size: int, lb: float, ub: float, fp_rtol: float,
    snap_rtol: float,
) -> tuple[int, int, bool]:
    """Successor cells of the box ``[lo, hi]`` along one state axis (Definition 4.2), as ``abstract_block``
    computes them: :func:`pipelines.abstraction.growth_bound.widen`, :meth:`pipelines.grid.UniformGrid.cells_touching`
    (``fp_rtol = FP_RTOL``, ``snap_rtol = SNAP_RTOL``), clipped to the ``size`` cells of the grid.

    Returns
    -------
    first, last : int
    leaves : bool
        Whether the widened box leaves ``[lb, ub]`` (the triple is blocking).
    """
    scale = max(abs(lo), abs(hi))
    a = lo - fp_rtol * scale
    b = hi + fp_rtol * scale
    leaves = a < lb or b > ub
    a = (a - origin) / eta - 0.5
    b = (b - origin) / eta + 0.5
    a = a - snap_rtol * max(1.0, abs(a))
    b = b + snap_rtol * max(1.0, abs(b))
    top = size - 1
    first = min(max(np.int64(np.ceil(a)) - k_lo, 0), top)
    last = min(max(np.int64(np.floor(b)) - k_lo, 0), top)
    # Compiled, first and last are int64; typeshed's min/max cannot join a numpy integer with an int.
    return first, last, leaves  # type: ignore[return-value]


@_jit
def _successor_arrays(
    B: int, n: int, bounds: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The results a block kernel fills for ``B`` triples with ``n`` state coordinates and ``bounds`` growth
    bounds: the chosen bound's successor ranges ``lo, hi`` (int32, (B, n)), its blocking flags, and the
    per-bound successor sums and non-blocking counts (int64, zero).

    The kernels write them in their per-triple loops, not through a helper called per triple with these arrays
    and the grid's: numba compiles such a loop markedly slower (passing arrays is not free), even inlined."""
    lo = np.empty((B, n), dtype=np.int32)
    hi = np.empty((B, n), dtype=np.int32)
    return lo, hi, np.empty(B, dtype=np.bool_), np.zeros(bounds, dtype=np.int64), np.zeros(bounds, dtype=np.int64)


@_jit
def _margins(
    xl: np.ndarray, xh: np.ndarray, wl: np.ndarray, wh: np.ndarray, b: int, has_w: bool, cx: float, cw: float,
    L_x: float, L_w: float,
) -> tuple[float, float, float, float, float, float]:
    """Triple ``b``'s state half-width, sample spacings along x and w (0 without w), Lipschitz radius, hull
    margin and SCP margin, as ``abstract_block``, ``growth_bound.lipschitz_radius``, ``hull_margin`` and
    ``scp_rho`` compute them."""
    rx = (xh[b] - xl[b]) / 2
    hx = 2 * rx / cx
    hw = 0.0
    lip = L_x * rx
    rho_h = L_x * hx / 2
    rho = 2.0 * L_x * hx
    if has_w:
        rw = (wh[b] - wl[b]) / 2
        hw = 2 * rw / cw
        lip = lip + L_w * rw
        rho_h = rho_h + L_w * hw / 2
        rho = rho + L_w * hw
    return rx, hx, hw, lip, rho_h, rho


@_jit
def _scp_candidates(
    bound: np.ndarray, xl: np.ndarray, xh: np.ndarray, wl: np.ndarray, wh: np.ndarray, has_w: bool, cx: float,
    cw: float, L_x: float, L_w: float, skip_rtol: float,
) -> np.ndarray:
    """Which triples may need the SCP, shape (B,) bool: the first test of ``block.abstract_block``. Where the
    quick lower bound of the SCP radius (:func:`hull_and_bound`) plus its margin already reaches the Lipschitz
    radius, the SCP cannot beat Lemma 4.3 and its pair maxima are not computed."""
    B = bound.shape[0]
    need = np.zeros(B, dtype=np.bool_)
    for b in range(B):
        _, _, _, lip_b, _, rho_b = _margins(xl, xh, wl, wh, b, has_w, cx, cw, L_x, L_w)
        need[b] = not (bound[b] + rho_b >= lip_b * (1 + skip_rtol))
    return need


@_jit
def _scp_radii(
    e: np.ndarray, need: bool, half: int, rx: float, hx: float, rho: float, lip: float, L_x: float, tie_rtol: float,
    skip_rtol: float,
) -> tuple[float, float]:
    """One triple's SCP radius (Theorem 4.4) ``min(theta1 r_x + theta2, lip)`` under the paper's objective and
    under the radius objective, from its pair maxima ``e``; the Lipschitz radius ``lip`` itself where the SCP
    cannot beat it (both tests of ``block.abstract_block``: :func:`_scp_candidates`, then ``max_{k <= half} E_k``).
    """
    cannot = not need
    if not cannot:
        near = e[0]
        for k in range(1, half + 1):
            near = max(near, e[k])
        cannot = near + rho >= lip * (1 + skip_rtol)
    if cannot:
        return lip, lip
    # Both bounds are sound: so is their min.
    t1, t2 = _scp_column(e, hx, rho, L_x, 1.0, tie_rtol)
    paper = min(t1 * rx + t2, lip)
    t1, t2 = _scp_column(e, hx, rho, L_x, rx, tie_rtol)
    return paper, min(t1 * rx + t2, lip)


#: Order of the growth bounds in :func:`scalar_block`'s successor statistics (that of ``abstract_block``).
SCALAR_METHODS = ("lipschitz", "hull", "scp", "scp_radius")


@_jit
def scalar_block(
    V: np.ndarray,
    C: np.ndarray,
    xl: np.ndarray,
    xh: np.ndarray,
    wl: np.ndarray,
    wh: np.ndarray,
    cx: float,
    cw: float,
    L_x: float,
    L_w: float,
    chosen: int,
    grid: tuple,
    fp_rtol: float,
    snap_rtol: float,
    tie_rtol: float,
    skip_rtol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Everything :func:`pipelines.abstraction.block.abstract_block` computes after the black box, for a scalar state
    with at most one internal-input sub-grid axis, in one pass per triple: the four growth bounds (Lemma 4.3,
    the sample hull, the SCP of Theorem 4.4 under both objectives), their successor cells (Definition 4.2) and
    blocking flags, the successor statistics and the slopes for Lipschitz validation. The same values as that
    function's generic path with every statistic counted (``full_statistics=True``): the tests compare the two.

    Parameters
    ----------
    V : ndarray, shape (S_x, S_w, B), finite
        Successor samples.
    C : ndarray, shape (B,), finite
        Successor of each joint cell's centre.
    xl, xh : ndarray, shape (B,)
        Clipped state cell of each triple.
    wl, wh : ndarray, shape (B,) or (0,)
        Clipped internal-input cell of each triple; empty arrays for a subsystem without internal inputs.
    cx, cw : float
        Sub-grid points along x and along w (``cw`` unused without internal inputs).
    L_x, L_w : float
        Lipschitz constants.
    chosen : int
        Position in :data:`SCALAR_METHODS` of the growth bound whose successors are returned.
    grid : tuple of ndarray
        The state grid's ``origin, eta, k_lo, shape, lb, ub`` (``UniformGrid`` fields as arrays of shape (1,)).
    fp_rtol, snap_rtol : float
        The rounding margins ``growth_bound.FP_RTOL``, ``grid.SNAP_RTOL`` (see :func:`_cell_range`).
    tie_rtol, skip_rtol : float
        ``growth_bound.SCP_TIE_RTOL`` and ``subsystem.SCP_SKIP_RTOL``.

    Returns
    -------
    lo, hi : ndarray of int32, shape (B, 1)
        Successor range of the chosen bound, ``(0, -1)`` where blocking.
    blocking : ndarray of bool, shape (B,)
    sums, live : ndarray of int64, shape (4,)
        Per bound of :data:`SCALAR_METHODS`: successor cells summed over the non-blocking triples, and their
        number.
    slope_x, slope_w : ndarray, shape (B,)
        Largest neighbour difference quotients along x and along w (0 where a spacing is 0 or without w).
    """
    Sx, Sw, B = V.shape
    has_w = wl.shape[0] > 0
    vmax, vmin, dx, dw = scalar_sample_pass(V)
    half = Sx // 2
    hull_lo, hull_hi, bound = hull_and_bound(vmax, vmin, half)
    lo, hi, blocking, sums, live = _successor_arrays(B, 1, 4)
    slope_x = np.zeros(B)
    slope_w = np.zeros(B)
    need = _scp_candidates(bound, xl, xh, wl, wh, has_w, cx, cw, L_x, L_w, skip_rtol)
    # The pair maxima of every triple (batch on the contiguous axis: vectorised) when one needs them.
    E = pair_maxima_batch_last(vmax, vmin) if need.any() else np.empty((Sx, 0))
    box_lo = np.empty(4)  # one box per bound of SCALAR_METHODS
    box_hi = np.empty(4)
    origin, eta, k_lo, shape, lb, ub = grid
    for b in range(B):
        rx, hx, hw, lip_b, rho_h, rho_b = _margins(xl, xh, wl, wh, b, has_w, cx, cw, L_x, L_w)
        e = E[:, b] if need[b] else vmax[:0, 0]
        paper, radius = _scp_radii(e, need[b], half, rx, hx, rho_b, lip_b, L_x, tie_rtol, skip_rtol)
        c = C[b]
        box_lo[0], box_hi[0] = c - lip_b, c + lip_b
        box_lo[1], box_hi[1] = hull_lo[b] - rho_h, hull_hi[b] + rho_h
        box_lo[2], box_hi[2] = c - paper, c + paper
        box_lo[3], box_hi[3] = c - radius, c + radius
        for q in range(4):
            f, g, leaves = _cell_range(box_lo[q], box_hi[q], origin[0], eta[0], k_lo[0], shape[0], lb[0], ub[0],
                                       fp_rtol, snap_rtol)
            if not leaves:
                sums[q] += g - f + 1
                live[q] += 1
            if q == chosen:
                blocking[b] = leaves
                lo[b, 0] = 0 if leaves else f
                hi[b, 0] = -1 if leaves else g
        if hx > 0:
            slope_x[b] = dx[b] / hx
        if hw > 0:  # 0 without internal inputs
            slope_w[b] = dw[b] / hw
    return lo, hi, blocking, sums, live, slope_x, slope_w


@_jit
def box_sample_pass(V: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sample hull of every triple and the largest differences between neighbouring samples along each
    sub-grid axis, in one read of the samples (:func:`box_block`'s counterpart of :func:`scalar_sample_pass`).

    Parameters
    ----------
    V : ndarray, shape (S, B, n), finite
        Successor samples, ``S`` the joint sub-grid (row-major over ``counts``).
    counts : ndarray of int64, shape (d,)
        Sub-grid points per axis.

    Returns
    -------
    vmin, vmax : ndarray, shape (B, n)
    diff : ndarray, shape (d, B, n)
        Largest ``|ΔV_i|`` between neighbouring samples along each axis.
    """
    S, B, n = V.shape
    d = counts.shape[0]
    vmin = V[0].copy()
    vmax = V[0].copy()
    diff = np.zeros((d, B, n))
    stride = np.ones(d, dtype=np.int64)
    for a in range(d - 2, -1, -1):
        stride[a] = stride[a + 1] * counts[a + 1]
    for s in range(S):
        row = V[s]
        for b in range(B):
            for i in range(n):
                v = row[b, i]
                vmin[b, i] = min(vmin[b, i], v)
                vmax[b, i] = max(vmax[b, i], v)
        for a in range(d):
            if (s // stride[a]) % counts[a] == counts[a] - 1:  # the last sample along this axis
                continue
            nxt = V[s + stride[a]]
            da = diff[a]
            for b in range(B):
                for i in range(n):
                    da[b, i] = max(da[b, i], abs(nxt[b, i] - row[b, i]))
    return vmin, vmax, diff


@_jit
def diagonal_pass(V: np.ndarray, counts: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """Largest ``||ΔV||_∞`` per triple (shape (B,)) between diagonal neighbours of the sub-grid: one sample along
    every ``moving`` axis at once (each with two samples or more; the others fixed), in every sign pattern (the first
    moving axis forward: the opposite pattern gives the same pairs). ``V``, shape (S, B, n), is row-major over
    ``counts`` (int64, shape (d,)). The differences of :func:`pipelines.abstraction.block._diagonal_slopes`."""
    S, B, n = V.shape
    d, k = counts.shape[0], moving.shape[0]
    stride = np.ones(d, dtype=np.int64)
    for a in range(d - 2, -1, -1):
        stride[a] = stride[a + 1] * counts[a + 1]
    best = np.zeros(B)
    for pattern in range(1 << (k - 1)):
        for s in range(S):
            t = s
            ok = True
            for j in range(k):
                a = moving[j]
                position = (s // stride[a]) % counts[a]
                step = 1 if j == 0 or (pattern >> (j - 1)) & 1 == 0 else -1
                if position + step < 0 or position + step >= counts[a]:
                    ok = False
                    break
                t += step * stride[a]
            if not ok:
                continue
            row, nxt = V[s], V[t]
            for b in range(B):
                for i in range(n):
                    best[b] = max(best[b], abs(nxt[b, i] - row[b, i]))
    return best


@_jit
def box_block(
    V: np.ndarray,
    C: np.ndarray,
    lip: np.ndarray,
    rho_h: np.ndarray,
    counts: np.ndarray,
    h: np.ndarray,
    chosen: int,
    first_bound: int,
    grid: tuple,
    fp_rtol: float,
    snap_rtol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`pipelines.abstraction.block.abstract_block` computes after the black box for the Lipschitz and
    hull bounds of any subsystem (``n`` state and ``p`` internal-input coordinates), in one read of the samples:
    the sample hull, both bounds' successor cells (Definition 4.2), blocking flags and statistics, and the slopes
    along every sub-grid axis for Lipschitz validation. The same values as the generic path (the tests compare).

    Parameters
    ----------
    V : ndarray, shape (S, B, n), finite
        Successor samples, ``S`` the joint sub-grid (row-major over ``counts``: state axes, then internal-input
        axes).
    C : ndarray, shape (B, n)
        Successor of each joint cell's centre (not read when ``first_bound`` is 1).
    lip, rho_h : ndarray, shape (B, n)
        Lipschitz radius (Lemma 4.3) and hull margin per component (``GrowthBound.lipschitz_radius``, ``margin``).
    counts : ndarray of int64, shape (d,)
        Sub-grid points per axis.
    h : ndarray, shape (B, d)
        Sample spacing along each axis.
    chosen : int
        0: the Lipschitz bound's successors are returned; 1: the hull's.
    first_bound : int
        0: both bounds; 1: the hull only (the Lipschitz bound's statistics are left 0).
    grid, fp_rtol, snap_rtol
        The state grid and rounding margins (see :func:`scalar_block`).

    Returns
    -------
    lo, hi : ndarray of int32, shape (B, n)
        Successor range of the chosen bound, ``(0, -1)`` where blocking.
    blocking : ndarray of bool, shape (B,)
    sums, live : ndarray of int64, shape (2,)
        Per bound (Lipschitz, hull): successor cells summed over the non-blocking triples, and their number.
    slopes : ndarray, shape (B, n, d)
        Largest ``|ΔV_i| / h_a`` between neighbouring samples along each axis ``a`` (0 where ``h_a = 0``).
    """
    B, n = V.shape[1], V.shape[2]
    vmin, vmax, diff = box_sample_pass(V, counts)
    lo, hi, blocking, sums, live = _successor_arrays(B, n, 2)
    first = np.empty(n, dtype=np.int64)
    last = np.empty(n, dtype=np.int64)
    origin, eta, k_lo, shape, lb, ub = grid
    for b in range(B):
        for q in range(first_bound, 2):
            leaves = False
            count = np.int64(1)
            for i in range(n):
                if q == 0:
                    box_lo, box_hi = C[b, i] - lip[b, i], C[b, i] + lip[b, i]
                else:
                    box_lo, box_hi = vmin[b, i] - rho_h[b, i], vmax[b, i] + rho_h[b, i]
                f, g, out = _cell_range(box_lo, box_hi, origin[i], eta[i], k_lo[i], shape[i], lb[i], ub[i],
                                        fp_rtol, snap_rtol)
                leaves = leaves or out
                first[i] = f
                last[i] = g
                count *= g - f + 1
            if not leaves:
                sums[q] += count
                live[q] += 1
            if q == chosen:
                blocking[b] = leaves
                for i in range(n):
                    lo[b, i] = 0 if leaves else first[i]
                    hi[b, i] = -1 if leaves else last[i]
    slopes = np.zeros((B, n, counts.shape[0]))
    for b in range(B):
        for a in range(counts.shape[0]):
            if h[b, a] > 0:
                for i in range(n):
                    slopes[b, i, a] = diff[a, b, i] / h[b, a]
    return lo, hi, blocking, sums, live, slopes


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel for the argument types the per-cell stage passes,
    those of the n-D SCP (:mod:`pipelines.abstraction.scp`) included."""
    from pipelines.abstraction import scp

    scp.warm_up()
    V = np.zeros((2, 2, 2))
    vmax, vmin, _, _ = scalar_sample_pass(V)
    E = pair_maxima_batch_last(vmax, vmin)
    hull_and_bound(vmax, vmin, 1)
    one = np.ones(2)
    scp_parameters_batch_last(E, one, one, 1.0, one, 0.0)
    scp_parameters_batch_last(E[:, [0]], one[[0]], one[[0]], 1.0, one[[0]], 0.0)  # a column subset
    ints = np.zeros(1, dtype=np.int64)
    grid = (one[:1], one[:1], ints, ints, one[:1], one[:1])
    box_block(np.zeros((2, 2, 1)), np.zeros((2, 1)), np.zeros((2, 1)), np.zeros((2, 1)), np.full(1, 2, dtype=np.int64),
              np.ones((2, 1)), 1, 0, grid, 0.0, 0.0)
    for w in (one, np.zeros(0)):
        scalar_block(V, one, one, one, w, w, 2.0, 2.0, 1.0, 1.0, 0, grid, 0.0, 0.0, 0.0, 0.0)
