"""Lipschitz constants: checking given ones against the data, and estimating them (Algorithm 4, App. A).

A growth bound is only sound if the Lipschitz constants it uses are (Assumptions 1-2). Data can refute a
constant but never prove it: a slope observed between two samples above the given constant shows the
constant is wrong, and the job fails (or, if the spec asks, raises the constant and says so). Estimated
constants follow Wood & Zhang's reverse-Weibull fit of batch maxima, times a safety factor, and are never
below the largest slope observed.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from pipelines.network import Subsystem


@dataclass(frozen=True)
class LipschitzEstimate:
    """Result of Algorithm 4 for one argument (``x`` or ``w``) of one subsystem."""

    value: float  # the constant to use: max(location, largest slope) * safety factor
    location: float  # reverse-Weibull location parameter (the paper's estimate)
    max_slope: float  # largest slope seen in all batches
    batches: int
    pairs: int


def _reverse_weibull_location(maxima: np.ndarray) -> float:
    """Location of a reverse Weibull (``scipy.stats.weibull_max``) fitted to batch maxima.

    The location is the distribution's finite upper end point: the estimate of the true maximum slope.
    A failed or degenerate fit returns the largest maximum.
    """
    from scipy import stats

    top = float(np.max(maxima))
    if np.ptp(maxima) <= 1e-12 * max(1.0, top):
        return top
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            _, loc, _ = stats.weibull_max.fit(maxima, loc=top * 1.01)
        except Exception:  # scipy's optimiser may fail on odd samples: fall back to the data
            return top
    return float(loc) if np.isfinite(loc) else top


def estimate_lipschitz(
    sub: Subsystem,
    argument: str,
    rng: np.random.Generator,
    batches: int = 40,
    pairs: int = 200,
    delta: float | None = None,
    safety_factor: float = 1.1,
) -> LipschitzEstimate:
    """Algorithm 4: estimate ``L_x`` (``argument='x'``) or ``L_w`` (``'w'``) of a subsystem's dynamics.

    For every input ``û`` and each of ``batches`` batches, ``pairs`` random pairs at infinity-distance at
    most ``delta`` (default: a tenth of the grid spacing) in the state box (or the internal box), the other
    argument drawn at random and shared by the pair, give slopes ``||f(a) - f(b)|| / ||a - b||``; the batch
    maxima are fitted by a reverse Weibull distribution whose location estimates the constant.
    """
    grid = sub.state_grid if argument == "x" else sub.internal_grid
    if grid is None:
        return LipschitzEstimate(0.0, 0.0, 0.0, 0, 0)
    lb, ub = np.asarray(grid.lb), np.asarray(grid.ub)
    d = grid.dim
    if delta is None:
        delta = float(np.min(grid.eta_array)) / 10
    u_pts = sub.input_grid.all_points()
    n_u = u_pts.shape[0]
    total = n_u * batches * pairs
    a = rng.uniform(lb, ub, (total, d))
    step = rng.uniform(-delta, delta, (total, d))
    b = np.clip(a + step, lb, ub)
    same = np.all(a == b, axis=1)
    b[same] = np.clip(a[same] + delta / 2, lb, ub)
    other_grid = sub.internal_grid if argument == "x" else sub.state_grid
    if other_grid is None:
        other = np.zeros((total, 0))
    else:
        other = rng.uniform(np.asarray(other_grid.lb), np.asarray(other_grid.ub), (total, other_grid.dim))
    U = np.repeat(u_pts, batches * pairs, axis=0)
    if argument == "x":
        fa, fb = sub.dynamics(a, U, other), sub.dynamics(b, U, other)
    else:
        fa, fb = sub.dynamics(other, U, a), sub.dynamics(other, U, b)
    dist = np.max(np.abs(a - b), axis=1)
    ok = dist > 0
    slopes = np.zeros(total)
    slopes[ok] = np.max(np.abs(fa - fb), axis=1)[ok] / dist[ok]
    maxima = slopes.reshape(n_u * batches, pairs).max(axis=1).reshape(n_u, batches)
    locs = np.array([_reverse_weibull_location(maxima[i]) for i in range(n_u)])
    location = float(locs.max())
    max_slope = float(maxima.max())
    return LipschitzEstimate(max(location, max_slope) * safety_factor, location, max_slope, batches, pairs)
