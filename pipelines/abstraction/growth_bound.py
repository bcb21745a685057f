"""Growth bounds (Definition 4.1): boxes that contain ``{f(x, u, w) : x in cell(x̂), w in cell(ŵ)}``.

The per-cell stage receives a :class:`GrowthBound`, an object holding the bound and its Lipschitz constants, as
SCOTS's ``Abstraction`` receives its growth bound; :func:`growth_bound` makes one from a spec's name. Three bounds,
each per component, all sound given Lipschitz constants ``L_x``, ``L_w``
(:class:`~pipelines.abstraction.constants.LipschitzMatrix`: per entry and in the infinity norm, docs/method.md §2-3).
With ``dev_i(r) = min(L ||r||_inf, sum_j L_ij r_j)`` the largest move of component ``i`` over half-widths ``r``:

``lipschitz`` (:class:`LipschitzBound`)
    Lemma 4.3, the paper's conservative baseline: radius ``dev_i^x(r_x) + dev_i^w(r_w)`` around
    ``c = f(x̂, û, ŵ)``, where ``r`` are the half-widths of the (clipped) cells.
``scp`` (:class:`ScpBound`)
    Theorem 4.4, the paper's method, corrected so that it is feasible (see :func:`scp_parameters_scalar`), one LP
    per output row.
``hull`` (:class:`HullBound`)
    Beyond the paper: ``[min_l x'_l - rho_h, max_l x'_l + rho_h]`` per component, ``rho_h = dev^x(h_x/2) +
    dev^w(h_w/2)``, where ``h`` are the sub-cell spacings of the samples.

With one constant per argument (a number in the spec) ``dev_i(r) = L ||r||``, the same for every component, and
every bound gives the bits it gave before per-component constants existed.

The functions below the interface work on batches of cells: arrays carry the batch along axis 0, except the
``*_batch_last`` variants the per-cell stage uses, which carry it on the last (contiguous) axis so that numpy
reduces over the short sample axes with whole-row operations.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from pipelines.abstraction.constants import LipschitzMatrix
from pipelines.abstraction.scp_closed_form import (  # noqa: F401 - the growth bounds' module re-exports them
    SCP_TIE_RTOL,
    SMALL_TABLE,
    pair_maxima_batch_last,
    pair_maxima_scalar,
    scp_parameters_batch_last,
    scp_parameters_scalar,
    scp_reference,
)

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
    (Theorem 4.4 uses ``eta_x / N_C^(1/dim)`` spacings; we sample ``x`` and ``w`` jointly, docs/method.md §2).
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


def _max_norm(a: np.ndarray) -> np.ndarray:
    """``max(a, axis=1)`` of a ``(B, d)`` array: the infinity norm of non-negative rows (a view for ``d = 1``:
    the per-cell stage calls this on small arrays, where a reduction's fixed cost dominates)."""
    return a[:, 0] if a.shape[1] == 1 else np.max(a, axis=1)


def lipschitz_radius(r_x: np.ndarray, r_w: np.ndarray, L_x: float, L_w: float) -> np.ndarray:
    """Radius of Lemma 4.3, shape (B,): ``L_x ||r_x||_inf + L_w ||r_w||_inf`` (the same in every component).

    Parameters
    ----------
    r_x : ndarray, shape (B, n)
        Half-widths of the clipped state cells.
    r_w : ndarray, shape (B, p)
        Half-widths of the clipped internal-input cells (``p`` may be 0).
    """
    rad = L_x * _max_norm(r_x)
    if r_w.shape[1]:
        rad = rad + L_w * _max_norm(r_w)
    return rad


def hull_margin(h_x: np.ndarray, h_w: np.ndarray, L_x: float, L_w: float) -> np.ndarray:
    """The margin ``rho_h = L_x ||h_x|| / 2 + L_w ||h_w|| / 2`` of the ``hull`` growth bound, shape (B,): every
    point of the cell is within half a sub-cell spacing of a sample, per component."""
    rho = L_x * _max_norm(h_x) / 2
    if h_w.shape[1]:
        rho = rho + L_w * _max_norm(h_w) / 2
    return rho


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
    rho = 2.0 * L_x * _max_norm(h_x)
    if h_w.shape[1]:
        rho = rho + L_w * _max_norm(h_w)
    return rho


# ====================================================================================== the interface
#: Relative margin by which the SCP's lower bound ``max_{k <= S_x/2} E_k + rho`` must exceed the Lipschitz
#: radius before a row's LP is skipped (the radius is then the Lipschitz radius to the bit): far above the
#: rounding of terms of size <= 2 lip (see :meth:`ScpBound.boxes`).
SCP_SKIP_RTOL = 1e-9


class SampleBlock:
    """What a growth bound reads about a block of ``B`` triples ``(x̂, û, ŵ)``: the successors of the samples of
    each joint cell and of its centre, and the cells' geometry. Quantities several bounds need (the extremes over
    the samples, the SCP's pair maxima) are computed once per block and shared.

    Parameters
    ----------
    V : ndarray, shape (S_x, S_w, B, n)
        Successors of the samples: the state sub-grid (row-major in ``counts_x``), the internal-input sub-grid,
        the triples.
    C : ndarray, shape (B, n)
        Successor of the centre of each clipped joint cell.
    r_x, h_x : ndarray, shape (B, n)
        Half-widths of the clipped state cells and the sample spacings in them.
    r_w, h_w : ndarray, shape (B, p)
        The same for the internal-input cells (``p`` may be 0).
    counts_x : tuple of int
        State sub-grid points per axis.
    extremes : tuple of ndarray, optional
        For ``n = 1``: the largest and smallest successor over the internal-input samples at each state sample,
        shape (S_x, B) each, if the caller has them.
    """

    def __init__(self, V: np.ndarray, C: np.ndarray, r_x: np.ndarray, r_w: np.ndarray, h_x: np.ndarray,
                 h_w: np.ndarray, counts_x: tuple[int, ...],
                 extremes: tuple[np.ndarray, np.ndarray] | None = None):
        self.V, self.C = V, C
        self.r_x, self.r_w, self.h_x, self.h_w = r_x, r_w, h_x, h_w
        self.counts_x = tuple(int(c) for c in counts_x)
        self._extremes = extremes
        self._hull: tuple[np.ndarray, np.ndarray] | None = None
        self._pairs: dict[bytes | None, np.ndarray] = {}
        self._pairs_nd: dict[bytes | None, np.ndarray] = {}

    @property
    def size(self) -> int:
        """``B``, the triples of the block."""
        return self.C.shape[0]

    @property
    def n(self) -> int:
        return self.C.shape[1]

    def hull(self) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest successor sample of each triple, per component, shape (B, n) each (exact)."""
        if self._hull is None:
            if self.n == 1 and self._extremes is not None:
                vmax, vmin = self._extremes
                self._hull = vmin.min(axis=0)[:, None], vmax.max(axis=0)[:, None]
            else:
                self._hull = self.V.min(axis=(0, 1)), self.V.max(axis=(0, 1))
        return self._hull

    def extremes(self) -> tuple[np.ndarray, np.ndarray]:
        """For ``n = 1``: the largest and smallest successor over the internal-input samples at each state sample,
        shape (S_x, B) each."""
        if self._extremes is None:
            V = self.V[..., 0]
            self._extremes = V.max(axis=1), V.min(axis=1)
        return self._extremes

    def pair_maxima(self, rows: np.ndarray | None) -> np.ndarray:
        """For ``n > 1``: the SCP's pair maxima (:func:`pipelines.abstraction.scp.pair_maxima_nd`) of the triples
        ``rows`` (``None``: all), shape (S_x, n, len(rows)); those of all triples are sliced when computed."""
        from pipelines.abstraction.scp import pair_maxima_of

        key = None if rows is None else rows.tobytes()
        if key not in self._pairs_nd:
            if None in self._pairs_nd:
                self._pairs_nd[key] = np.ascontiguousarray(self._pairs_nd[None][:, :, rows])
            else:
                self._pairs_nd[key] = pair_maxima_of(self.V if rows is None else self.V[:, :, rows], self.counts_x)
        return self._pairs_nd[key]

    def pair_maxima_scalar(self) -> np.ndarray:
        """For ``n = 1``: :func:`pair_maxima_batch_last` of every triple, shape (S_x, B)."""
        if None not in self._pairs:
            self._pairs[None] = pair_maxima_batch_last(*self.extremes())
        return self._pairs[None]


class GrowthBound(ABC):
    """A growth bound (Definition 4.1) with the Lipschitz constants it assumes: for a block of triples, boxes that
    contain the image of each joint cell under the black box.

    The per-cell stage (:func:`pipelines.abstraction.cells.abstract_chunk`) receives one and asks it for boxes;
    it never chooses a bound itself. An implementation must be sound: for every triple, every ``f(x, u, w)`` with
    ``x`` in the clipped state cell and ``w`` in the clipped internal cell lies in its box, given that the
    constants hold (the stage checks them against the same samples, docs/method.md §3).

    Parameters
    ----------
    L_x : LipschitzMatrix, shape (n, n)
    L_w : LipschitzMatrix, shape (n, p)
    """

    #: How the report names the bound's successors (``mean_successors``).
    name: str = ""

    def __init__(self, L_x: LipschitzMatrix, L_w: LipschitzMatrix):
        self.L_x, self.L_w = L_x, L_w

    @abstractmethod
    def boxes(self, block: SampleBlock, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners of the boxes of the block's triples ``rows`` (positions, increasing; ``None``:
        every triple), shape (len(rows), n) each."""

    def lipschitz_radius(self, block: SampleBlock) -> np.ndarray:
        """Lemma 4.3 per component, shape (B, n): ``dev^x(r_x) + dev^w(r_w)``."""
        rad = self.L_x.deviation(block.r_x)
        if block.r_w.shape[1]:
            rad = rad + self.L_w.deviation(block.r_w)
        return rad

    def margin(self, block: SampleBlock, scale: float) -> np.ndarray:
        """``dev^x(h_x) / scale + dev^w(h_w) / scale``, shape (B, n): how far a component moves between a point of
        the joint cell and its nearest sample (``scale = 2``)."""
        rho = self.L_x.deviation(block.h_x) / scale
        if block.h_w.shape[1]:
            rho = rho + self.L_w.deviation(block.h_w) / scale
        return rho

    def with_constants(self, L_x: LipschitzMatrix, L_w: LipschitzMatrix) -> GrowthBound:
        """The same bound under other constants."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        out.L_x, out.L_w = L_x, L_w
        return out

    def _key(self) -> tuple:
        return (type(self), self.name, self.L_x, self.L_w)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, GrowthBound) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.L_x!r}, {self.L_w!r})"


def _rows(a: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    return a if rows is None else a[rows]


class LipschitzBound(GrowthBound):
    """Lemma 4.3: ``c ± (dev^x(r_x) + dev^w(r_w))`` per component, ``c`` the successor of the cell's centre."""

    name = "lipschitz"

    def boxes(self, block: SampleBlock, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        lip = _rows(self.lipschitz_radius(block), rows)
        C = _rows(block.C, rows)
        return C - lip, C + lip


class HullBound(GrowthBound):
    """The sample hull, widened per component by how far the map moves between a point and its nearest sample:
    ``[min_l x'_l - rho_h, max_l x'_l + rho_h]``, ``rho_h = dev^x(h_x/2) + dev^w(h_w/2)``.

    Every point of the joint cell is within ``h/2`` of a sample per coordinate. For an affine map with exact
    per-entry constants (``|A_ij|``) the box is the image box of the cell, the tightest interval abstraction.
    """

    name = "hull"

    def boxes(self, block: SampleBlock, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = block.hull()
        rho = self.margin(block, 2)
        return _rows(lo - rho, rows), _rows(hi + rho, rows)


class ScpBound(GrowthBound):
    """The corrected scenario program of Theorem 4.4 (Eq. 4.5), one LP per output row (docs/method.md §2).

    Row ``i``: ``theta1_i . |x_l - x_m| + theta2_i >= |x'_{l,i} - x'_{m,i}| + rho_i`` for every sample pair,
    ``theta >= 0`` and a budget on ``theta1_i`` that the margin pays for:
    ``rho_i = 2 dev_i^x(h_x) + dev_i^w(h_w)`` where ``dev_i^x(h_x)`` is both the two Lipschitz steps from points to
    their samples and the bound on ``theta1_i . h_x``: ``sum(theta1_i) <= L_x`` when the infinity-norm constant
    gives the smaller ``dev_i^x`` (the paper's ``||theta1|| <= L_x``), ``theta1_i . h_x <= sum_j L_ij h_j`` when
    the entries do. The radius is ``theta1_i . r_x + theta2_i``, at most the Lipschitz radius (both are sound).

    Parameters
    ----------
    objective : {'paper', 'radius'}
        ``paper`` minimises ``1'theta`` as printed; ``radius`` the radius actually used.
    """

    def __init__(self, L_x: LipschitzMatrix, L_w: LipschitzMatrix, objective: str = "paper"):
        super().__init__(L_x, L_w)
        if objective not in ("paper", "radius"):
            raise ValueError(f"unknown SCP objective {objective!r}: expected 'paper' or 'radius'")
        self.objective = objective

    @property
    def name(self) -> str:  # type: ignore[override]
        return "scp" if self.objective == "paper" else "scp_radius"

    def margin_and_budget(self, block: SampleBlock) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``rho`` (B, n), the budget of ``theta1`` per row (B, n) and whether it weighs ``theta1`` by the spacings
        (B, n)."""
        h = block.h_x
        dev = self.L_x.deviation(h)
        if self.L_x.is_scalar:  # the entries never beat the norm
            by_spacing = np.zeros(dev.shape, dtype=bool)
            budget = np.full(dev.shape, self.L_x.norm)
        else:
            sums = self.L_x.row_sums(h)
            by_spacing = sums < self.L_x.by_norm(h)[:, None]  # where the entries gave dev (ties: the norm)
            budget = np.where(by_spacing, sums, self.L_x.norm)
        rho = 2.0 * dev
        if block.h_w.shape[1]:
            rho = rho + self.L_w.deviation(block.h_w)
        return rho, budget, by_spacing

    def boxes(self, block: SampleBlock, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if block.n == 1:
            rad = self._scalar_radius(block, rows)
        else:
            rad = self._radius(block, rows)
        C = _rows(block.C, rows)
        return C - rad, C + rad

    def _scalar_radius(self, block: SampleBlock, rows: np.ndarray | None) -> np.ndarray:
        """``dim(x) = 1``: the LP in closed form (:func:`scp_parameters_batch_last`), shape (len(rows), 1).

        A triple whose SCP radius cannot beat the Lipschitz radius needs no LP. Every feasible theta has
        ``theta1 r_x + theta2 >= theta1 d_k + theta2 >= E_k + rho`` for ``d_k = k h_x <= r_x`` (``k <= S_x / 2``,
        ``theta1 >= 0``), so the minimum below is the Lipschitz radius, to the bit, where
        ``max_{k <= S_x/2} E_k + rho`` exceeds it by :data:`SCP_SKIP_RTOL` (far above the rounding of the radius,
        terms of size <= 2 lip). First with ``E_0`` and ``E_{S_x/2}`` only (two of the pair maxima, computed as
        :func:`pair_maxima_batch_last` does): where that settles every triple (the tanks), the pair maxima are not
        needed at all.
        """
        L = self.L_x.effective()
        lip = self.lipschitz_radius(block)[:, 0]
        rho = self.margin_and_budget(block)[0][:, 0]
        RX, HX = block.r_x[:, 0], block.h_x[:, 0]
        vmax_w, vmin_w = block.extremes()
        B = block.size
        Sx = vmax_w.shape[0]
        half = Sx // 2
        threshold = lip * (1 + SCP_SKIP_RTOL)
        bound = np.max(vmax_w - vmin_w, axis=0)
        if half:
            up = (vmax_w[half:] - vmin_w[:-half]).max(axis=0)
            down = (vmax_w[:-half] - vmin_w[half:]).max(axis=0)
            bound = np.maximum(bound, np.maximum(up, down))
        cannot = bound + rho >= threshold
        sel = slice(None) if rows is None else rows
        E = None
        if not cannot[sel].all():
            E = block.pair_maxima_scalar()  # (Sx, B)
            cannot = E[: half + 1].max(axis=0) + rho >= threshold
        rad = lip[sel][:, None].copy()
        todo = ~cannot[sel]
        if todo.any():
            assert E is not None
            t_ix = slice(None) if rows is None and todo.all() else np.arange(B)[sel][todo]
            w1 = np.ones(B)[t_ix] if self.objective == "paper" else RX[t_ix]
            t1_, t2_ = scp_parameters_batch_last(E[:, t_ix], HX[t_ix], rho[t_ix], L, w1)
            rad[todo, 0] = np.minimum(t1_ * RX[t_ix] + t2_, lip[t_ix])  # both bounds are sound: so is the min
        return rad

    def _radius(self, block: SampleBlock, rows: np.ndarray | None) -> np.ndarray:
        """``dim(x) > 1``: one LP per output row by the compiled dual simplex (:mod:`pipelines.abstraction.scp`),
        shape (len(rows), n)."""
        from pipelines.abstraction.scp import displacement_classes, scp_radii_rows

        lip = self.lipschitz_radius(block)
        rho, budget, by_spacing = self.margin_and_budget(block)
        E = block.pair_maxima(rows)
        k = displacement_classes(block.counts_x)[3]

        def at(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(_rows(a, rows))

        rx = at(block.r_x)
        W = np.ones_like(rx) if self.objective == "paper" else rx
        return scp_radii_rows(E, k, at(block.h_x), at(rho), at(budget), at(by_spacing), W, rx, at(lip),
                              SCP_SKIP_RTOL)


def growth_bound(name: str, L_x: LipschitzMatrix, L_w: LipschitzMatrix, objective: str = "paper") -> GrowthBound:
    """The growth bound a spec names (``growth_bound``, ``scp_objective``) under these constants."""
    if name == "lipschitz":
        return LipschitzBound(L_x, L_w)
    if name == "hull":
        return HullBound(L_x, L_w)
    if name == "scp":
        return ScpBound(L_x, L_w, objective)
    raise ValueError(f"unknown growth bound {name!r}: expected 'lipschitz', 'scp' or 'hull'")


def standard_bounds(chosen: GrowthBound) -> list[GrowthBound]:
    """The bounds whose successors every job reports (``mean_successors``), under ``chosen``'s constants:
    ``chosen`` first, then the others of ``lipschitz``, ``hull``, ``scp`` (both objectives) it is not."""
    others: list[GrowthBound] = [LipschitzBound(chosen.L_x, chosen.L_w), HullBound(chosen.L_x, chosen.L_w),
                                 ScpBound(chosen.L_x, chosen.L_w, "paper"), ScpBound(chosen.L_x, chosen.L_w, "radius")]
    return [chosen] + [b for b in others if b.name != chosen.name]
