"""Lipschitz constants: checking given ones against the data, and estimating them (Algorithm 4, App. A).

A growth bound is only sound if the Lipschitz constants it uses are (Assumptions 1-2). Data can refute a
constant but never prove it: a slope observed between two samples above the given constant shows the
constant is wrong, and the job fails (or, if the spec asks, raises the constant and says so). Constants are
per component (:class:`~pipelines.abstraction.constants.LipschitzMatrix`: an entry per component of the successor
and coordinate of the argument, and one in the infinity norm), each checked on its own. Estimated constants
follow Wood & Zhang's reverse-Weibull fit of batch maxima, times a safety factor, and are never below the
largest slope observed; an entry is estimated from pairs that differ in its coordinate only.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np

from pipelines.abstraction.constants import LipschitzMatrix
from pipelines.abstraction.relation import SLOPE_RTOL, SlopeRecord
from pipelines.errors import LipschitzError
from pipelines.network import Subsystem


@dataclass(frozen=True)
class LipschitzEstimate:
    """Result of Algorithm 4 for one argument (``x`` or ``w``) of one subsystem, in the infinity norm."""

    value: float  # the constant to use: max(location, largest slope) * safety factor
    location: float  # reverse-Weibull location parameter (the paper's estimate)
    max_slope: float  # largest slope seen in all batches
    batches: int
    pairs: int


@dataclass(frozen=True)
class EntryEstimate:
    """Algorithm 4 per entry: arrays of shape (n, d), component of the successor x coordinate of the argument."""

    value: np.ndarray
    location: np.ndarray
    max_slope: np.ndarray


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


@dataclass(frozen=True)
class _Pairs:
    """What Algorithm 4 draws its pairs in, for one argument of one subsystem (:func:`_pairs`)."""

    lb: np.ndarray  # the argument's box
    ub: np.ndarray
    delta: float  # largest distance of a pair
    n_u: int  # input grid points
    total: int  # pairs: n_u * batches * pairs
    U: np.ndarray  # the input of each pair, shape (total, m): every input batches * pairs times


def _pairs(sub: Subsystem, argument: str, batches: int, pairs: int, delta: float | None) -> _Pairs | None:
    """The box, distance and inputs of Algorithm 4's pairs of ``argument`` (``None``: the subsystem has no such
    argument); ``delta`` defaults to a tenth of the grid's smallest spacing."""
    grid = sub.state_grid if argument == "x" else sub.internal_grid
    if grid is None:
        return None
    u_pts = sub.input_grid.all_points()
    return _Pairs(np.asarray(grid.lb), np.asarray(grid.ub),
                  float(np.min(grid.eta_array)) / 10 if delta is None else delta, u_pts.shape[0],
                  u_pts.shape[0] * batches * pairs, np.repeat(u_pts, batches * pairs, axis=0))


def _images(sub: Subsystem, argument: str, a: np.ndarray, b: np.ndarray, U: np.ndarray,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``f`` at the pairs ``a``, ``b`` of ``argument`` with inputs ``U``, the other argument drawn at random in its
    box (after ``a`` and ``b``) and shared by each pair."""
    other_grid = sub.internal_grid if argument == "x" else sub.state_grid
    if other_grid is None:
        other = np.zeros((a.shape[0], 0))
    else:
        other = rng.uniform(np.asarray(other_grid.lb), np.asarray(other_grid.ub), (a.shape[0], other_grid.dim))
    if argument == "x":
        return sub.dynamics(a, U, other), sub.dynamics(b, U, other)
    return sub.dynamics(other, U, a), sub.dynamics(other, U, b)


def estimate_lipschitz(sub: Subsystem, argument: str, rng: np.random.Generator, batches: int = 40, pairs: int = 200,
                       delta: float | None = None, safety_factor: float = 1.1) -> LipschitzEstimate:
    """Algorithm 4: estimate ``L_x`` (``argument='x'``) or ``L_w`` (``'w'``) of a subsystem's dynamics.

    For every input ``û`` and each of ``batches`` batches, ``pairs`` random pairs at infinity-distance at
    most ``delta`` (default: a tenth of the grid spacing) in the state box (or the internal box), the other
    argument drawn at random and shared by the pair, give slopes ``||f(a) - f(b)|| / ||a - b||``; the batch
    maxima are fitted by a reverse Weibull distribution whose location estimates the constant.
    """
    box = _pairs(sub, argument, batches, pairs, delta)
    if box is None:
        return LipschitzEstimate(0.0, 0.0, 0.0, 0, 0)
    lb, ub, delta, n_u, total = box.lb, box.ub, box.delta, box.n_u, box.total
    a = rng.uniform(lb, ub, (total, lb.size))
    step = rng.uniform(-delta, delta, (total, lb.size))
    b = np.clip(a + step, lb, ub)
    same = np.all(a == b, axis=1)
    b[same] = np.clip(a[same] + delta / 2, lb, ub)
    fa, fb = _images(sub, argument, a, b, box.U, rng)
    dist = np.max(np.abs(a - b), axis=1)
    ok = dist > 0
    slopes = np.zeros(total)
    slopes[ok] = np.max(np.abs(fa - fb), axis=1)[ok] / dist[ok]
    maxima = slopes.reshape(n_u * batches, pairs).max(axis=1).reshape(n_u, batches)
    locs = np.array([_reverse_weibull_location(maxima[i]) for i in range(n_u)])
    location = float(locs.max())
    max_slope = float(maxima.max())
    return LipschitzEstimate(max(location, max_slope) * safety_factor, location, max_slope, batches, pairs)


def estimation_rounds(n: int, d: int) -> int:
    """Rounds of pairs that estimating ``L`` draws for ``n`` components over ``d`` coordinates, each of ``batches x
    pairs x input points`` pairs: one in the infinity norm (:func:`estimate_lipschitz`) and, with more than one
    entry, one more per coordinate (:func:`estimate_entries`). The cost model counts them (:mod:`pipelines.spec.costs`)."""
    return 1 if n * d == 1 else 1 + d


def estimate_entries(sub: Subsystem, argument: str, rng: np.random.Generator, batches: int = 40, pairs: int = 200,
                     delta: float | None = None, safety_factor: float = 1.1) -> EntryEstimate:
    """Algorithm 4 per entry: ``L_x[i, j]`` (``argument='x'``) or ``L_w[i, j]`` (``'w'``) for every component ``i``
    of the successor and coordinate ``j`` of the argument.

    As :func:`estimate_lipschitz`, with the pairs of coordinate ``j`` differing in that coordinate only (the rest of
    the argument and the other argument drawn at random and shared by the pair), and the slopes
    ``|f_i(a) - f_i(b)| / |a_j - b_j|`` fitted per component: ``n`` fits per input and coordinate.
    """
    n = sub.n
    box = _pairs(sub, argument, batches, pairs, delta)
    if box is None:
        empty = np.zeros((n, 0))
        return EntryEstimate(empty, empty, empty)
    lb, ub, delta, n_u, total = box.lb, box.ub, box.delta, box.n_u, box.total
    d = lb.size
    value, location, max_slope = np.zeros((n, d)), np.zeros((n, d)), np.zeros((n, d))
    for j in range(d):
        a = rng.uniform(lb, ub, (total, d))
        b = a.copy()
        b[:, j] = np.clip(a[:, j] + rng.uniform(-delta, delta, total), lb[j], ub[j])
        same = a[:, j] == b[:, j]
        b[same, j] = np.clip(a[same, j] + delta / 2, lb[j], ub[j])
        fa, fb = _images(sub, argument, a, b, box.U, rng)
        dist = np.abs(a[:, j] - b[:, j])
        ok = dist > 0  # a box of zero width along j: no pair, no slope
        slopes = np.zeros((total, n))
        slopes[ok] = np.abs(fa - fb)[ok] / dist[ok, None]
        maxima = slopes.reshape(n_u, batches, pairs, n).max(axis=2)  # (n_u, batches, n)
        for i in range(n):
            locs = [_reverse_weibull_location(maxima[k, :, i]) for k in range(n_u)]
            location[i, j] = float(max(locs))
            max_slope[i, j] = float(maxima[:, :, i].max())
    value = np.maximum(location, max_slope) * safety_factor
    return EntryEstimate(value, location, max_slope)


# ====================================================================================== constants of a job
@dataclass
class ConstantRecord:
    """The Lipschitz constants of one argument and where they came from (for the report).

    ``value`` is a :class:`~pipelines.abstraction.constants.LipschitzMatrix`; ``float(value)`` is the constant in
    the infinity norm, which the report's ``value`` gives (and ``matrix`` the entries, when they are not all that
    constant).
    """

    value: LipschitzMatrix
    source: str  # given | raised | estimated | estimated (raised by cell data) | unused
    given: LipschitzMatrix | None = None
    observed_max_slope: float = 0.0
    where: str = ""
    estimate: dict | None = None
    observed: np.ndarray | None = None  # largest slope per entry, shape of value

    def as_dict(self) -> dict:
        value = self.value
        d: dict = {"value": float(value), "source": self.source, "observed_max_slope": self.observed_max_slope}
        if not value.is_scalar:
            d["matrix"] = value.entries.tolist()
        if self.observed is not None and self.observed.size > 1:
            d["observed_slopes"] = self.observed.tolist()
        if self.given is not None:
            given = self.given
            d["given"] = given.as_json()
            if self.source == "raised":  # how much the data made it grow (docs/method.md §3: say so in the report)
                if given.is_scalar and value.is_scalar:
                    d["raised_by"] = float(value) - float(given)
                    d["raised_factor"] = float(value) / float(given) if float(given) > 0 else None
                else:
                    d["raised_by"] = (value.entries - given.entries).tolist()
        if self.where:
            d["where"] = self.where
        if self.estimate:
            d["estimate"] = self.estimate
        return d


def _dims(sub: Subsystem, arg: str) -> tuple[int, int]:
    return sub.n, (sub.n if arg == "x" else sub.p)


def check_given_constants(sub: Subsystem) -> None:
    """Refuse a given matrix of constants whose shape does not fit the subsystem, before anything runs (the
    same check and message as when the job resolves its constants, :func:`resolve_constant`)."""
    lip = sub.spec.lipschitz
    for arg in ("x", "w"):
        given = getattr(lip, arg)
        if isinstance(given, list) and not (arg == "w" and sub.internal_grid is None):
            n, d = _dims(sub, arg)
            LipschitzMatrix.given(given, n, d, f"subsystems[{sub.spec.name}].lipschitz.{arg}")


def resolve_constant(sub: Subsystem, arg: Literal["x", "w"], rng: np.random.Generator) -> ConstantRecord:
    """The constants ``L_arg`` a subsystem's abstraction starts with: given by the spec (a number, or a matrix of
    one row per state component and one column per coordinate of ``arg``), or estimated (Algorithm 4, in the
    infinity norm and, for more than one entry, per entry) when the spec says ``estimate``.

    Raises
    ------
    SpecError
        A matrix of the wrong shape, naming the field.
    """
    lip = sub.spec.lipschitz
    given = getattr(lip, arg)
    n, d = _dims(sub, arg)
    if arg == "w" and sub.internal_grid is None:
        return ConstantRecord(LipschitzMatrix.scalar(0.0, n, 0), "unused")
    if given == "estimate":
        est = estimate_lipschitz(sub, arg, rng, lip.batches, lip.pairs, lip.delta, lip.safety_factor)
        info: dict = {"location": est.location, "max_slope": est.max_slope, "safety_factor": lip.safety_factor,
                      "batches": est.batches, "pairs": est.pairs}
        if estimation_rounds(n, d) == 1:
            value = LipschitzMatrix.scalar(est.value, n, d)
        else:
            ent = estimate_entries(sub, arg, rng, lip.batches, lip.pairs, lip.delta, lip.safety_factor)
            value = LipschitzMatrix(ent.value, est.value)
            info["entries"] = {"location": ent.location.tolist(), "max_slope": ent.max_slope.tolist()}
        return ConstantRecord(value, "estimated", observed_max_slope=est.max_slope, estimate=info)
    field = f"subsystems[{sub.spec.name}].lipschitz.{arg}"
    value = LipschitzMatrix.given(given, n, d, field)
    return ConstantRecord(value, "given", given=value)


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


def steepest_pair(sub: Subsystem, arg: str, rec: SlopeRecord, component: int | None = None,
                  coordinate: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The pair of neighbouring samples of a triple that shows its largest slope, sampled again as the per-cell
    stage samples it (:func:`pipelines.abstraction.block.triple_samples`).

    Parameters
    ----------
    arg : {'x', 'w'}
        Along which argument the pair differs.
    rec : SlopeRecord
        The triple (``x_cell``, ``u_index``, ``w_cell``).
    component, coordinate : int, optional
        The entry: component of the successor and coordinate of ``arg``; ``None``: any (the infinity norm).

    Returns
    -------
    x_a, w_a, x_b, w_b : ndarray
        The two samples.
    slope : float
    """
    from pipelines.abstraction.block import triple_samples

    X, W, u, counts = triple_samples(sub, rec.x_cell, rec.u_index, rec.w_cell)  # (*counts, n), (*counts, p)
    N = X[..., 0].size
    V = sub.dynamics(X.reshape(N, sub.n), np.repeat(u[None], N, axis=0), W.reshape(N, sub.p)).reshape(counts + (sub.n,))
    first = 0 if arg == "x" else sub.n
    axes = range(first, first + (sub.n if arg == "x" else sub.p))
    best: tuple[float, tuple[int, ...] | None, tuple[int, ...] | None] = (-1.0, None, None)
    for j, ax in enumerate(axes):
        if coordinate is not None and j != coordinate or counts[ax] < 2:
            continue
        lo = [slice(None)] * len(counts)
        hi = [slice(None)] * len(counts)
        lo[ax], hi[ax] = slice(None, -1), slice(1, None)
        P = (X if arg == "x" else W)
        step = np.abs(P[tuple(hi)][..., j] - P[tuple(lo)][..., j])
        diff = np.abs(V[tuple(hi)] - V[tuple(lo)])
        diff = diff.max(axis=-1) if component is None else diff[..., component]
        slope = np.divide(diff, step, out=np.zeros_like(diff), where=step > 0)
        k = np.unravel_index(int(np.argmax(slope)), slope.shape)
        if slope[k] > best[0]:
            a = tuple(int(v) for v in k)
            b = tuple(v + 1 if q == ax else v for q, v in enumerate(a))
            best = (float(slope[k]), a, b)
    slope_, a_, b_ = best
    assert a_ is not None and b_ is not None  # a recorded positive slope has a pair
    return X[a_], W[a_], X[b_], W[b_], slope_


def _pair_text(sub: Subsystem, arg: str, rec: SlopeRecord, component: int | None, coordinate: int | None) -> str:
    try:
        xa, wa, xb, wb, _ = steepest_pair(sub, arg, rec, component, coordinate)
    except Exception:  # a description must never hide the error it describes
        return ""

    def point(x: np.ndarray, w: np.ndarray) -> str:
        text = f"x = {np.round(x, 12).tolist()}"
        return text + (f", w = {np.round(w, 12).tolist()}" if sub.p else "")

    return f"; the samples ({point(xa, wa)}) and ({point(xb, wb)})"


def _entry_name(arg: str, i: int, j: int) -> str:
    return f"L_{arg}[{i}][{j}]"


def check_constants(
    sub: Subsystem, names: str, constants: dict[str, ConstantRecord], slopes: dict[str, SlopeRecord]
) -> bool:
    """Check the constants against the largest slopes the per-cell stage observed (docs/method.md §3).

    Records each observed slope. A slope above a constant (the one in the infinity norm, or an entry ``L[i][j]``
    against the slope of component ``i`` along coordinate ``j``) either fails the job with a
    :class:`~pipelines.errors.LipschitzError` naming the constant, the cell, the pair of samples and the slope (a
    given constant with ``lipschitz.on_violation: fail``), or raises the constant to the slope times the safety
    factor and says so in the record.

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
        if c.source == "unused":
            continue
        L = c.value
        over = np.zeros(L.shape, dtype=bool)
        if rec.entries and rec.shape == L.shape:
            seen = rec.entry_slopes()
            c.observed = seen if c.observed is None else np.maximum(c.observed, seen)
            if not L.is_scalar:  # a scalar's entries are its norm: checked below
                over = c.observed > L.entries * (1 + SLOPE_RTOL)
        elif not L.is_scalar:
            raise LipschitzError(
                f"subsystem {names}: the stored data of some chunks carry no slope per entry, so the matrix L_{arg} "
                "cannot be checked against them: run the job again into a new directory (or with --overwrite)."
            )
        over_norm = rec.slope > L.norm * (1 + SLOPE_RTOL)
        if over_norm or over.any():
            violated.append((arg, rec, over_norm, over))
    for arg, rec, over_norm, over in violated:
        c = constants[arg]
        L = c.value
        if c.source == "given" and spec.lipschitz.on_violation == "fail":
            raise LipschitzError(_contradiction(sub, names, arg, L, rec, over_norm, over))
        # only what the data contradict beyond rounding (SLOPE_RTOL) is raised
        entry_slopes = np.where(over, c.observed, 0.0) if c.observed is not None else np.zeros(L.shape)
        c.value = L.raised(entry_slopes, rec.slope if over_norm else 0.0, spec.lipschitz.safety_factor)
        c.source = "raised" if c.source in ("given", "raised") else "estimated (raised by cell data)"
        c.where = describe_cell(sub, rec if over_norm else rec.entry(*np.argwhere(over)[0]))
    return not violated


def _contradiction(sub: Subsystem, names: str, arg: str, L: LipschitzMatrix, rec: SlopeRecord, over_norm: bool,
                   over: np.ndarray) -> str:
    """The message of a given constant the data contradict: which constant, where, by how much, what to do."""
    fix = f"set lipschitz.{arg}: estimate, or lipschitz.on_violation: raise"
    if not L.is_scalar and not over.any():  # a given matrix implies its norm: an entry is contradicted first
        over = rec.entry_slopes() >= rec.slope
    if L.is_scalar:
        value = float(L)
        excess = f", {rec.slope - value:.6g} ({rec.slope / value - 1:.2%}) above it" if value > 0 else ""
        return (
            f"subsystem {names}: the given L_{arg} = {value:g} is contradicted by the data: slope {rec.slope:.6g} observed "
            f"at {describe_cell(sub, rec)}{excess}{_pair_text(sub, arg, rec, None, None)}. An abstraction built with "
            f"it would be unsound. Give L_{arg} >= {rec.slope:.6g}, {fix}."
        )
    ratio = np.where(over, rec.entry_slopes() / np.maximum(L.entries, 1e-300), 0.0)
    i, j = (int(v) for v in np.unravel_index(int(np.argmax(ratio)), ratio.shape))
    e = rec.entry(i, j)
    value = float(L.entries[i, j])
    name = _entry_name(arg, i, j)
    excess = f", {e.slope - value:.6g} ({e.slope / value - 1:.2%}) above it" if value > 0 else ""
    others = [_entry_name(arg, int(a), int(b)) for a, b in np.argwhere(over) if (a, b) != (i, j)]
    more = f" (also contradicted: {', '.join(others)})" if others else ""
    return (
        f"subsystem {names}: the given {name} = {value:g} (component {i} of the successor along {arg}[{j}]) is "
        f"contradicted by the data: slope {e.slope:.6g} observed at {describe_cell(sub, e)}{excess}"
        f"{_pair_text(sub, arg, e, i, j)}{more}. An abstraction built with it would be unsound. Give {name} >= "
        f"{e.slope:.6g}, {fix}."
    )
