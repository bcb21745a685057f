"""Learning ``M̄`` (Section 4.2, Eq. (lasso)): lasso rows, supports, least-squares refit, support validation.

Departures from the paper (METHOD §4), and why
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
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from pipelines.errors import CertificationError
from pipelines.interconnection.sampling import Sampler

__all__ = ["lasso_row", "support_of", "refit", "dependence", "validate_support", "DEPENDENCE_RTOL"]

#: Relative change of ``M_j`` that counts as "depends on this coordinate".
DEPENDENCE_RTOL = 1e-9


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
    for i in range(n):
        moved = base.copy()
        moved[:, i] = fresh[:, i]
        dep[i] = _rel_change(y0, sample(moved)).any(axis=0)
    return dep


def validate_support(
    sample: Sampler, j: int, support: Sequence[int], dep: np.ndarray, count: int, rng: np.random.Generator
) -> float:
    """Check ``M_j`` does not depend on the coordinates outside its support; return the largest change.

    Every coordinate outside the support is redrawn at once on ``count`` random states.

    Raises
    ------
    CertificationError
        Naming the coordinate ``M_j`` depends on.
    """
    n = sample.lb.size
    outside = np.setdiff1d(np.arange(n), np.asarray(support, dtype=int))
    if outside.size == 0:
        return 0.0
    base = sample.uniform(count, rng)
    moved = base.copy()
    moved[:, outside] = sample.uniform(count, rng)[:, outside]
    y0 = sample(base)[:, j]
    y1 = sample(moved)[:, j]
    changed = _rel_change(y0, y1)
    if changed.any():
        culprits = [int(i) for i in outside if dep[i, j]]
        r = int(np.argmax(changed))
        which = f"coordinate x{culprits[0]}" if culprits else f"the coordinates {outside.tolist()} jointly"
        raise CertificationError(
            f"interconnection output w{j} depends on {which}, which lasso left out of its support "
            f"{list(support)}: M_{j} changed from {float(y0[r])!r} to {float(y1[r])!r} when it was resampled; "
            "lower alpha (or use 'cv') or give more samples"
        )
    return float(np.abs(y1 - y0).max(initial=0.0))
