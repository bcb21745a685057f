"""Learning ``M̄`` (Section 4.2, Eq. (lasso)): lasso rows, supports, least-squares refit, support validation.

Departures from the paper (docs/method.md §4), and why
-----------------------------------------------
* Lasso alone over-selects: with ``alpha = 'cv'`` on the tank map and ``N_I = 80`` it typically keeps several
  spurious coordinates (e.g. 7 for ``w6 = sqrt(x4)``), because cross-validation tunes prediction, not
  support recovery. Lasso's support is therefore only a candidate set: :func:`dependence` resamples each
  coordinate ``x_i`` alone on ``holdout`` random states and keeps it for ``M_j`` only if ``M_j`` changes
  (relative ``1e-9``). The surviving support is then validated jointly (:func:`validate_support`: all other
  coordinates resampled together); a dependence still missed is an error ("lower alpha"). The largest change
  seen in that joint test (normally exactly 0) is added to ``eps_j`` in ``certify`` and ``direct`` modes, so a
  dependence below the tolerance is still covered.
* After lasso, ``M̄_j`` and ``b_j`` are refitted by ordinary least squares on the support (:func:`refit`), so
  that a linear map is identified exactly (lasso shrinks its coefficients). ``alpha`` is scikit-learn's (its
  objective divides the squared error by ``2 N``, unlike Eq. (lasso)).
* A map that reads many coordinates, each of which matters only on a small part of the box (``max(x)`` of
  512 coordinates: ``x_i`` changes the maximum on about ``2 / n`` of the draws), can keep a few coordinates
  out of the one-at-a-time test. The joint check then sees a change; instead of failing at once,
  :func:`complete_support` walks from the base state to the moved one, switching half of the differing
  coordinates at a time (bisection, one evaluation per step), down to one coordinate whose switch changed
  ``M_j``, adds it and checks again on fresh states. A larger support is never unsound (only coarser);
  the support is what the final joint check accepts.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from pipelines.errors import CertificationError
from pipelines.interconnection.sampling import Sampler

__all__ = [
    "lasso_row",
    "support_of",
    "refit",
    "dependence",
    "validate_support",
    "complete_support",
    "DEPENDENCE_RTOL",
    "SUPPORT_ROUNDS",
    "BISECT_ROWS",
]

#: Relative change of ``M_j`` that counts as "depends on this coordinate".
DEPENDENCE_RTOL = 1e-9
#: Rounds of :func:`complete_support` (each adds at least one coordinate) before the support is refused.
SUPPORT_ROUNDS = 32
#: Changed states bisected per round of :func:`complete_support`.
BISECT_ROWS = 64


def _rel_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether ``a`` and ``b`` differ by more than ``DEPENDENCE_RTOL`` relative to their magnitude."""
    return np.abs(a - b) > DEPENDENCE_RTOL * np.maximum(np.abs(a), np.abs(b))


def lasso_row(X: np.ndarray, y: np.ndarray, alpha: float | str) -> tuple[np.ndarray, float | None]:
    """Lasso (Eq. (lasso)) for one output row: coefficients (n,) and the alpha used (None for a constant row)."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.linear_model import Lasso, LassoCV

    if np.ptp(y) <= 1e-12 * np.abs(y).max(initial=0.0):
        # A constant output (the tanks' w_1 = 0): no coordinate explains it, and LassoCV's alpha grid
        # degenerates to zero on it.
        return np.zeros(X.shape[1]), None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        if alpha == "cv":
            model = LassoCV(cv=min(5, X.shape[0]), max_iter=100_000, n_jobs=1).fit(X, y)
            used = float(model.alpha_)
        else:
            model = Lasso(alpha=float(alpha), max_iter=100_000).fit(X, y)
            used = float(alpha)
    return np.asarray(model.coef_, dtype=float), used


def support_of(coef: np.ndarray) -> tuple[int, ...]:
    """Indices of the nonzero coefficients (``|coef| > 1e-12 max|coef|``)."""
    big = np.abs(coef).max(initial=0.0)
    if big == 0:
        return ()
    return tuple(int(i) for i in np.flatnonzero(np.abs(coef) > 1e-12 * big))


def refit(X: np.ndarray, y: np.ndarray, support: Sequence[int]) -> tuple[np.ndarray, float]:
    """Least squares with intercept on the support columns: row of ``M̄`` (n,) and ``b``."""
    row = np.zeros(X.shape[1])
    if not support:
        return row, float(np.mean(y))
    A = np.column_stack([X[:, list(support)], np.ones(X.shape[0])])
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    row[list(support)] = sol[:-1]
    return row, float(sol[-1])


def dependence(sample: Sampler, count: int, rng: np.random.Generator) -> np.ndarray:
    """``D[i, j]``: whether ``M_j`` changed when coordinate ``i`` alone was resampled, shape (n, p).

    ``count`` random base states; for each coordinate a copy with that coordinate redrawn. Each evaluation
    serves every output; one coordinate at a time keeps memory at ``count * n`` floats.
    """
    n = sample.lb.size
    base = sample.uniform(count, rng)
    fresh = sample.uniform(count, rng)
    y0 = sample(base)
    dep = np.zeros((n, y0.shape[1]), dtype=bool)
    moved = base.copy()  # one buffer: coordinate i is switched in and back (no copy of count * n per i)
    for i in range(n):
        moved[:, i] = fresh[:, i]
        dep[i] = _rel_change(y0, sample(moved)).any(axis=0)
        moved[:, i] = base[:, i]
    return dep


def validate_support(
    sample: Sampler, j: int, support: Sequence[int], dep: np.ndarray, count: int, rng: np.random.Generator
) -> float:
    """Check ``M_j`` does not depend on the coordinates outside its support; return the largest change.

    Every coordinate outside the support is redrawn at once on ``count`` random states
    (:func:`complete_support` without rounds).

    Raises
    ------
    CertificationError
        Naming the coordinate ``M_j`` depends on.
    """
    return complete_support(sample, j, support, dep, count, rng, rounds=0)[1]


def _bisect(sample: Sampler, j: int, a: np.ndarray, b: np.ndarray, coords: np.ndarray) -> int:
    """A coordinate whose switch from ``a`` to ``b`` changes ``M_j``, given ``M_j(a) != M_j(b)``.

    ``a`` and ``b`` (n,) differ on ``coords``. Each step switches the first half of the differing coordinates
    of ``a`` to their values in ``b``: where ``M_j`` changed, that half holds a culprit (``b`` becomes the
    switched state), else the change lies between the switched state and ``b`` (it becomes ``a``).
    """
    a, b = a.copy(), b.copy()
    ya = sample(a[None])[0, j]
    while coords.size > 1:
        half, rest = coords[: coords.size // 2], coords[coords.size // 2 :]
        c = a.copy()
        c[half] = b[half]
        yc = sample(c[None])[0, j]
        if _rel_change(np.asarray(ya), np.asarray(yc)):
            b, coords = c, half
        else:
            a, ya, coords = c, yc, rest
    return int(coords[0])


def complete_support(
    sample: Sampler,
    j: int,
    support: Sequence[int],
    dep: np.ndarray,
    count: int,
    rng: np.random.Generator,
    rounds: int = SUPPORT_ROUNDS,
) -> tuple[tuple[int, ...], float, list[int]]:
    """The joint support check, adding the coordinates it finds ``M_j`` depends on (module docstring).

    Each round redraws every coordinate outside the support at once on ``count`` random states (the first
    round draws exactly what the plain check draws). No change: done. A change: up to ``BISECT_ROWS`` changed
    states are bisected to one coordinate each (:func:`_bisect`), those coordinates join the support and the
    next round draws fresh states.

    Returns
    -------
    (support, largest change, added)
        The support (increasing), the largest ``|ΔM_j|`` of the round that passed (normally 0; added to
        ``eps_j``), and the coordinates the rounds added.

    Raises
    ------
    CertificationError
        A change after ``rounds`` rounds, naming the coordinate ``M_j`` depends on.
    """
    n = sample.lb.size
    current = sorted(int(i) for i in support)
    added: list[int] = []
    for k in range(rounds + 1):
        outside = np.setdiff1d(np.arange(n), np.asarray(current, dtype=int))
        if outside.size == 0:
            return tuple(current), 0.0, added
        base = sample.uniform(count, rng)
        moved = base.copy()
        moved[:, outside] = sample.uniform(count, rng)[:, outside]
        y0 = sample(base)[:, j]
        y1 = sample(moved)[:, j]
        changed = _rel_change(y0, y1)
        if not changed.any():
            return tuple(current), float(np.abs(y1 - y0).max(initial=0.0)), added
        if k == rounds:
            culprits = [int(i) for i in outside if dep[i, j]]
            r = int(np.argmax(changed))
            which = f"coordinate x{culprits[0]}" if culprits else f"the coordinates {outside.tolist()} jointly"
            raise CertificationError(
                f"interconnection output w{j} depends on {which}, which lasso left out of its support "
                f"{list(current)}: M_{j} changed from {float(y0[r])!r} to {float(y1[r])!r} when it was resampled; "
                "lower alpha (or use 'cv') or give more samples"
            )
        found = {_bisect(sample, j, base[r], moved[r], outside) for r in np.flatnonzero(changed)[:BISECT_ROWS]}
        added.extend(sorted(found))
        current = sorted(set(current) | found)
    raise AssertionError("unreachable")  # pragma: no cover - the last round returns or raises
