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
from typing import Literal

import numpy as np

from pipelines.abstraction.relation import SLOPE_RTOL, SlopeRecord
from pipelines.errors import LipschitzError
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


# ====================================================================================== constants of a job
@dataclass
class ConstantRecord:
    """A Lipschitz constant and where it came from (for the report)."""

    value: float
    source: str  # given | raised | estimated | estimated (raised by cell data) | unused
    given: float | None = None
    observed_max_slope: float = 0.0
    where: str = ""
    estimate: dict | None = None

    def as_dict(self) -> dict:
        d: dict = {"value": self.value, "source": self.source, "observed_max_slope": self.observed_max_slope}
        if self.given is not None:
            d["given"] = self.given
            if self.source == "raised":  # how much the data made it grow (docs/method.md §3: say so in the report)
                d["raised_by"] = self.value - self.given
                d["raised_factor"] = self.value / self.given if self.given > 0 else None
        if self.where:
            d["where"] = self.where
        if self.estimate:
            d["estimate"] = self.estimate
        return d


def resolve_constant(sub: Subsystem, arg: Literal["x", "w"], rng: np.random.Generator) -> ConstantRecord:
    """The constant ``L_arg`` a subsystem's abstraction starts with: given by the spec, or estimated
    (Algorithm 4) when the spec says ``estimate``."""
    lip = sub.spec.lipschitz
    given = getattr(lip, arg)
    if arg == "w" and sub.internal_grid is None:
        return ConstantRecord(0.0, "unused")
    if given == "estimate":
        est = estimate_lipschitz(sub, arg, rng, lip.batches, lip.pairs, lip.delta, lip.safety_factor)
        return ConstantRecord(
            est.value,
            "estimated",
            observed_max_slope=est.max_slope,
            estimate={"location": est.location, "max_slope": est.max_slope, "safety_factor": lip.safety_factor,
                      "batches": est.batches, "pairs": est.pairs},
        )
    return ConstantRecord(float(given), "given", given=float(given))


def _box(lo: np.ndarray, hi: np.ndarray) -> str:
    return " x ".join(f"[{a:g}, {b:g}]" for a, b in zip(lo, hi))


def describe_cell(sub: Subsystem, rec: SlopeRecord) -> str:
    """Where a slope was observed, in the user's coordinates."""
    x_lo, x_hi = sub.state_grid.clipped_cells(sub.state_grid.unravel(np.array([rec.x_cell])))
    u = sub.input_grid.points(sub.input_grid.unravel(np.array([rec.u_index])))[0]
    where = f"state cell {rec.x_cell} (x in {_box(x_lo[0], x_hi[0])}), input u={u.tolist()}"
    if sub.internal_grid is not None:
        w_lo, w_hi = sub.internal_grid.clipped_cells(sub.internal_grid.unravel(np.array([rec.w_cell])))
        where += f", internal cell {rec.w_cell} (w in {_box(w_lo[0], w_hi[0])})"
    return where


def check_constants(
    sub: Subsystem, names: str, constants: dict[str, ConstantRecord], slopes: dict[str, SlopeRecord]
) -> bool:
    """Check the constants against the largest slopes the per-cell stage observed (docs/method.md §3).

    Records each observed slope. A slope above a constant either fails the job with a
    :class:`~pipelines.errors.LipschitzError` naming the cell and the slope (a given constant with
    ``lipschitz.on_violation: fail``), or raises the constant to the slope times the safety factor and says so
    in the record.

    Returns
    -------
    bool
        ``True`` if every constant held; ``False`` if some were raised, so the abstraction must be computed
        again with the new constants.
    """
    spec = sub.spec
    violated = []
    for arg, rec in slopes.items():
        c = constants[arg]
        c.observed_max_slope = max(c.observed_max_slope, rec.slope)
        if c.source != "unused" and rec.slope > c.value * (1 + SLOPE_RTOL):
            violated.append((arg, rec))
    for arg, rec in violated:
        c = constants[arg]
        where = describe_cell(sub, rec)
        if c.source == "given" and spec.lipschitz.on_violation == "fail":
            excess = f", {rec.slope - c.value:.6g} ({rec.slope / c.value - 1:.2%}) above it" if c.value > 0 else ""
            raise LipschitzError(
                f"subsystem {names}: the given L_{arg} = {c.value:g} is contradicted by the data: slope "
                f"{rec.slope:.6g} observed at {where}{excess}. An abstraction built with it would be unsound. Give "
                f"L_{arg} >= {rec.slope:.6g}, set lipschitz.{arg}: estimate, or lipschitz.on_violation: raise."
            )
        c.value = rec.slope * spec.lipschitz.safety_factor
        c.source = "raised" if c.source in ("given", "raised") else "estimated (raised by cell data)"
        c.where = where
    return not violated
