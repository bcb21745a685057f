"""Lipschitz constants of one argument of a subsystem's map, per component (Assumptions 1-2; docs/method.md §3).

For the argument ``a`` (the state ``x`` or the internal input ``w``) of ``f(x, u, w)``, a :class:`LipschitzMatrix`
holds two kinds of bound, both checked against the data:

``entries[i, j]``
    How fast component ``i`` of ``f`` moves along coordinate ``j`` of ``a``, everything else fixed:
    ``|f_i(a) - f_i(b)| <= entries[i, j] |a_j - b_j|`` when ``a`` and ``b`` differ in coordinate ``j`` only.
    Along a path that changes one coordinate at a time, ``|f_i(a) - f_i(b)| <= sum_j entries[i, j] |a_j - b_j|``
    for any ``a``, ``b`` of the box: the growth bound of each component, as SCOTS's and Dionysos.jl's are.
``norm``
    The constant of the paper, in the infinity norm: ``||f(a) - f(b)||_inf <= norm ||a - b||_inf``.

Over a box of half-widths ``r`` around a point, component ``i`` moves by at most
``min(norm ||r||_inf, sum_j entries[i, j] r_j)`` (:meth:`LipschitzMatrix.deviation`). A scalar constant, as specs
gave before per-component constants existed, means ``norm`` and every entry: the minimum is then ``norm ||r||``,
to the bit, so the relations of such specs do not change. A given matrix implies ``norm`` (its largest row sum),
which never beats the entries. A rotation is the case where a norm beats its entries (``[[c, -s], [s, c]]``:
entries 1, norm ``|c| + |s| <= sqrt(2)``), so an estimated constant keeps both.

``float(L)`` is ``norm``: what the report, the relation store and everything written for one constant per
argument read.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pipelines.errors import SpecError

__all__ = ["LipschitzMatrix"]

#: A raised matrix's ``norm`` grows at least by this factor, so that ``float(L)`` names every raise (the relation
#: store names a group by the float constants: a raised entry under an unchanged ``norm`` would reuse stale chunks).
RAISE_NORM_RTOL = 2.0**-40


class LipschitzMatrix:
    """Per-component Lipschitz constants of one argument (module docstring). Immutable.

    Parameters
    ----------
    entries : array_like, shape (n, d)
        Non-negative, finite; ``n`` outputs (the state dimension), ``d`` coordinates of the argument.
    norm : float
        The infinity-norm constant; by default the largest row sum of ``entries``.
    """

    __slots__ = ("_entries", "_norm", "_scalar", "_implied")

    def __init__(self, entries: np.ndarray | Sequence[Sequence[float]], norm: float | None = None):
        e = np.array(entries, dtype=float)
        if e.ndim != 2:
            raise ValueError(f"entries must be a matrix, got shape {e.shape}")
        if not (np.isfinite(e).all() and (e >= 0).all()):
            raise ValueError("Lipschitz entries must be finite and >= 0")
        e.setflags(write=False)
        self._entries = e
        implied = float(e.sum(axis=1).max()) if e.size else 0.0
        self._norm = implied if norm is None else float(norm)
        self._implied = norm is None  # the norm says nothing the entries do not
        if not (math.isfinite(self._norm) and self._norm >= 0):
            raise ValueError(f"a Lipschitz constant must be finite and >= 0, got {self._norm}")
        # A scalar constant (every entry the norm): deviation() is norm ||r|| to the bit, without the entries.
        self._scalar = bool(e.size == 0 or (e == self._norm).all())

    # ---------------------------------------------------------------------------------------------- making
    @classmethod
    def scalar(cls, value: float, n: int, d: int) -> LipschitzMatrix:
        """One constant for every entry and the norm (a spec's number)."""
        return cls(np.full((n, d), float(value)), float(value))

    @classmethod
    def given(cls, value: float | Sequence[Sequence[float]], n: int, d: int, field: str) -> LipschitzMatrix:
        """A spec's ``lipschitz.x`` or ``.w``: a number, or a matrix of ``n`` rows (state components) and ``d``
        columns (coordinates of the argument), checked against those dimensions.

        Raises
        ------
        SpecError
            A matrix of another shape, naming ``field`` and the shape expected.
        """
        if isinstance(value, (int, float)):
            return cls.scalar(float(value), n, d)
        rows = [list(r) for r in value]
        if len(rows) != n or any(len(r) != d for r in rows):
            got = f"{len(rows)} rows of lengths {[len(r) for r in rows]}" if rows else "an empty list"
            raise SpecError(
                f"{field}: a matrix of Lipschitz constants has one row per state component and one column per "
                f"coordinate of {field[-1]}: {n} x {d} here, got {got}"
            )
        return cls(rows)

    @classmethod
    def of(cls, value: float | LipschitzMatrix, n: int, d: int) -> LipschitzMatrix:
        """``value`` as an ``n x d`` constant: a number means every entry and the norm."""
        if isinstance(value, LipschitzMatrix):
            if value.shape != (n, d):
                raise ValueError(f"a {value.shape[0]} x {value.shape[1]} Lipschitz matrix where {n} x {d} is needed")
            return value
        return cls.scalar(float(value), n, d)

    # ---------------------------------------------------------------------------------------------- reading
    @property
    def entries(self) -> np.ndarray:
        """``(n, d)`` read-only."""
        return self._entries

    @property
    def norm(self) -> float:
        return self._norm

    @property
    def shape(self) -> tuple[int, int]:
        n, d = self._entries.shape
        return n, d

    @property
    def is_scalar(self) -> bool:
        """Whether every entry is the norm (a spec's number): the bounds are those of one constant."""
        return self._scalar

    def effective(self) -> float:
        """The constant of a scalar map of a scalar argument (``n = d = 1``): the smaller of the entry and the norm,
        which bound the same slope there."""
        if self.shape != (1, 1):
            raise ValueError(f"effective() is for a 1 x 1 constant, this one is {self.shape}")
        return min(self._norm, float(self._entries[0, 0]))

    def __float__(self) -> float:
        return self._norm

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LipschitzMatrix):
            return NotImplemented
        return self._norm == other._norm and np.array_equal(self._entries, other._entries)

    def __hash__(self) -> int:
        return hash((self._norm, self._entries.shape, self._entries.tobytes()))

    def __repr__(self) -> str:
        if self._scalar:
            return f"LipschitzMatrix.scalar({self._norm!r}, {self.shape[0]}, {self.shape[1]})"
        return f"LipschitzMatrix({self._entries.tolist()!r}, norm={self._norm!r})"

    def __reduce__(self):
        return (LipschitzMatrix, (self._entries.tolist(), None if self._implied else self._norm))

    def as_json(self) -> float | list[list[float]]:
        """The number of a scalar constant, the entries of a matrix (for reports)."""
        return self._norm if self._scalar else self._entries.tolist()

    # ---------------------------------------------------------------------------------------------- bounds
    def deviation(self, r: np.ndarray) -> np.ndarray:
        """How far each component can move over boxes of half-widths ``r``: ``min(norm ||r||_inf, r . entries[i])``.

        Parameters
        ----------
        r : ndarray, shape (B, d)
            Non-negative half-widths (or any non-negative distances per coordinate).

        Returns
        -------
        ndarray, shape (B, n)
            For a scalar constant every column is ``norm * max_j r_j``, computed as one product (the bits of the
            one-constant bound).
        """
        n, d = self.shape
        B = r.shape[0]
        if d == 0:
            return np.zeros((B, n))
        by_norm = self.by_norm(r)
        if self._scalar:
            return np.broadcast_to(by_norm[:, None], (B, n))
        return np.minimum(by_norm[:, None], self.row_sums(r))

    def by_norm(self, r: np.ndarray) -> np.ndarray:
        """``norm ||r||_inf``, shape (B,), for ``r`` of shape (B, d)."""
        if r.shape[1] == 0:
            return np.zeros(r.shape[0])
        largest = r[:, 0].copy()
        for j in range(1, r.shape[1]):  # column by column: a reduction over a short last axis is slow in numpy
            np.maximum(largest, r[:, j], out=largest)
        return self._norm * largest

    def row_sums(self, r: np.ndarray) -> np.ndarray:
        """``sum_j entries[i, j] r_j``, shape (B, n), for ``r`` of shape (B, d), summed in the order of ``j``.

        Not ``r @ entries.T``: BLAS would choose the order and the threads (its bits then depend on the library,
        and its threads, beside the per-cell stage's own, oversubscribe the cores).
        """
        out = np.zeros((r.shape[0], self._entries.shape[0]))
        for j in range(r.shape[1]):
            out += r[:, j, None] * self._entries[:, j]
        return out

    # ---------------------------------------------------------------------------------------------- raising
    def raised(self, slopes: np.ndarray, overall: float, factor: float) -> LipschitzMatrix:
        """This constant where the data contradict it, raised to the observed slopes times ``factor``.

        Parameters
        ----------
        slopes : ndarray, shape (n, d)
            Slope per entry to raise it to (0 to leave it); an entry below its slope becomes ``slope * factor``.
        overall : float
            Slope in the infinity norm to raise it to (0 to leave it); a norm below it becomes ``overall * factor``.

        Notes
        -----
        A scalar constant stays scalar (raised to the largest slope, as one constant always was). A norm implied by
        the entries follows them; any norm grows at least by :data:`RAISE_NORM_RTOL` when an entry is raised, so
        that ``float`` names every raise.
        """
        if self._scalar:
            return LipschitzMatrix.scalar(overall * factor, *self.shape)
        e = np.where(slopes > self._entries, slopes * factor, self._entries)
        if self._implied:
            return LipschitzMatrix(e) if np.array_equal(e, self._entries) else LipschitzMatrix(
                e, max(float(e.sum(axis=1).max()), self._norm * (1 + RAISE_NORM_RTOL)))
        norm = self._norm if overall <= self._norm else overall * factor
        if not np.array_equal(e, self._entries):
            norm = max(norm, self._norm * (1 + RAISE_NORM_RTOL))
        return LipschitzMatrix(e, norm)
