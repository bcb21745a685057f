"""The audit: concrete transitions drawn at random, each checked against the abstraction.

Soundness (docs/method.md, "the one rule"): for a concrete state ``x`` in ``cell(x̂)``, an input ``û`` and an
internal input ``w`` in ``cell(ŵ)``, either ``û`` is blocking at ``(x̂, ŵ)`` or the cell of ``f(x, û, w)`` is
among the abstract successors (Theorem 4.2 / Definition 4.2). For the interconnection, the cell of ``M(x)``
is in ``M̂(x̂)`` (Theorem 4.7). A violation is a bug that makes every controller built on the abstraction
wrong, so the audit draws a share of its points exactly on cell boundaries and box edges, where off-by-one
errors live.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.grid import UniformGrid, cell_index
from pipelines.network import Network, Subsystem

#: Points per batch of black-box evaluations.
BATCH = 250_000


@dataclass(frozen=True)
class AuditResult:
    transitions_checked: int
    violations: int
    skipped_blocking: int
    first_violation: str | None

    def as_dict(self) -> dict:
        return {
            "transitions_checked": self.transitions_checked,
            "violations": self.violations,
            "skipped_blocking": self.skipped_blocking,
            "first_violation": self.first_violation,
        }


def draw_in_box(grid: UniformGrid, count: int, rng: np.random.Generator, boundary_share: float = 0.2) -> np.ndarray:
    """Random concrete points of the grid's box, shape (count, d); some exactly on cell boundaries/box edges."""
    lb, ub = np.asarray(grid.lb), np.asarray(grid.ub)
    pts = rng.uniform(lb, ub, (count, grid.dim))
    k = int(count * boundary_share)
    if k:
        # Snap some coordinates to a cell boundary (point ± eta/2) or a box edge.
        rows = rng.integers(0, count, k)
        cols = rng.integers(0, grid.dim, k)
        idx = np.asarray(grid.cell_of(pts[rows])[0])[np.arange(k), cols]
        centre = np.asarray(grid.origin)[cols] + (idx + np.asarray(grid.k_lo)[cols]) * np.asarray(grid.eta)[cols]
        edge = centre + rng.choice([-0.5, 0.5], k) * np.asarray(grid.eta)[cols]
        edge = np.where(rng.random(k) < 0.1, np.where(rng.random(k) < 0.5, lb[cols], ub[cols]), edge)
        pts[rows, cols] = np.clip(edge, lb[cols], ub[cols])
    return pts


def _either_cell(grid: UniformGrid, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Cell indices of points, shape (B, d), taking at random the upper or lower cell on a boundary.

    A point on a boundary is related to both cells, so over many draws both assignments get checked. The choice
    is per coordinate (a point may lie on a boundary in one coordinate only), and so is the fallback: on the box
    edge the outer cell of that coordinate may be off the grid, and the other one, which holds the point, is
    taken for that coordinate alone.
    """
    x = np.ascontiguousarray(x, dtype=float)
    U = rng.random(x.shape)
    idx = np.empty(x.shape, dtype=np.int64)
    _either(x, U, np.asarray(grid.origin, dtype=float), grid.eta_array.astype(float),
            np.asarray(grid.k_lo, dtype=np.int64), np.asarray(grid.shape, dtype=np.int64), idx)
    return idx


@njit(cache=True, nogil=True)
def _either(x: np.ndarray, U: np.ndarray, origin: np.ndarray, eta: np.ndarray, k_lo: np.ndarray, top: np.ndarray,
            idx: np.ndarray) -> None:
    """:func:`_either_cell`'s loop: per coordinate the upper cell where ``U < 1/2``, else the lower, and the other
    where the pick is off the grid."""
    B, d = x.shape
    for b in range(B):
        for j in range(d):
            up = cell_index(x[b, j], origin[j], eta[j], k_lo[j], True)
            low = cell_index(x[b, j], origin[j], eta[j], k_lo[j], False)
            first, other = (up, low) if U[b, j] < 0.5 else (low, up)
            idx[b, j] = other if first < 0 or first >= top[j] else first


def _batches(count: int) -> Iterator[int]:
    """The sizes of the batches of ``count`` draws: :data:`BATCH` each, the last one the rest."""
    return (min(BATCH, count - start) for start in range(0, count, BATCH))


def _composed_draws(network: Network, grid: UniformGrid, b: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """``b`` composed states ``x`` (:func:`draw_in_box`), their cells, ``w = M(x)``, its cells and whether it lies in
    the internal boxes (:func:`_internal_cells`), drawn from ``rng`` in that order."""
    x = draw_in_box(grid, b, rng)
    x_idx = _either_cell(grid, x, rng)
    w = network.interconnection_map(x)
    return (x, x_idx, w, *_internal_cells(network, w, rng))


def audit_subsystem(sub: Subsystem, rel: SubsystemRelation, count: int, rng: np.random.Generator) -> AuditResult:
    """Check ``count`` random concrete transitions of one subsystem against its relation."""
    xg, ug, wg = sub.state_grid, sub.input_grid, sub.internal_grid
    checked = violations = skipped = 0
    first: str | None = None
    for b in _batches(count):
        x = draw_in_box(xg, b, rng)
        ui = rng.integers(0, ug.size, b)
        u = ug.points(ug.unravel(ui))
        if wg is None:
            w = np.zeros((b, 0))
            wi = np.zeros(b, dtype=np.int64)
        else:
            w = draw_in_box(wg, b, rng)
            wi = wg.ravel(_either_cell(wg, w, rng))
        xi = xg.ravel(_either_cell(xg, x, rng))
        xn = sub.dynamics(x, u, w)
        lo, hi, block = rel.successor_ranges(xi, ui, wi)
        skipped += int(block.sum())
        live = ~block
        ok, n_idx = _successor_ok(xg, xn, lo, hi)
        bad = live & ~ok
        checked += int(live.sum())
        violations += int(bad.sum())
        if bad.any() and first is None:
            k = int(np.argmax(bad))
            first = (
                f"{sub.name}: state cell {int(xi[k])}, input {int(ui[k])}, internal cell {int(wi[k])}: "
                f"x={x[k].tolist()} u={u[k].tolist()} w={w[k].tolist()} -> x'={xn[k].tolist()} "
                f"in cell {n_idx[k].tolist()}, abstraction allows {lo[k].tolist()}..{hi[k].tolist()}"
            )
    return AuditResult(checked, violations, skipped, first)


def _internal_cells(network: Network, w: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Cells of concrete internal inputs ``w``, shape (B, p) (either cell on a boundary; 0 outside the box),
    and whether every component lies in its internal box, shape (B,)."""
    w_idx = np.zeros(w.shape, dtype=np.int64)
    inside_all = np.ones(w.shape[0], dtype=bool)
    for j, g in enumerate(network.internal_grids):
        inside = (w[:, j] >= g.lb[0]) & (w[:, j] <= g.ub[0])
        w_idx[:, j] = np.where(inside, _either_cell(g, np.clip(w[:, j : j + 1], g.lb[0], g.ub[0]), rng)[:, 0], 0)
        inside_all &= inside
    return w_idx, inside_all


def audit_interconnection(network: Network, ia, count: int, rng: np.random.Generator) -> AuditResult:
    """Check ``count`` random concrete states: the cell of ``M(x)`` must be in ``M̂(cell(x))`` (Thm 4.7)."""
    grid = network.composed_state_grid()
    checked = violations = 0
    first: str | None = None
    for b in _batches(count):
        x, x_idx, w, w_idx, ok = _composed_draws(network, grid, b, rng)
        safe_idx = np.where(ok[:, None], w_idx, 0)
        ok &= ia.contains(x_idx, safe_idx)
        checked += b
        violations += int((~ok).sum())
        if (~ok).any() and first is None:
            k = int(np.argmax(~ok))
            first = f"interconnection: x={x[k].tolist()} M(x)={w[k].tolist()} cells {w_idx[k].tolist()} not allowed"
    return AuditResult(checked, violations, 0, first)


def _successor_ok(grid: UniformGrid, xn: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether each successor's cell(s) lie in ``[lo, hi]`` and in the state box; also the (upper) cell index.

    A successor on a cell boundary lies in both cells, so both must be in the range.
    """
    n_up, in_up = grid.cell_of(xn, "upper")
    n_low, in_low = grid.cell_of(xn, "lower")
    inside_box = np.all((xn >= np.asarray(grid.lb)) & (xn <= np.asarray(grid.ub)), axis=1)
    ok = in_up & in_low & inside_box
    ok &= np.all((n_up >= lo) & (n_up <= hi) & (n_low >= lo) & (n_low <= hi), axis=1)
    return ok, n_up


def audit_composition(
    network: Network,
    relations: dict[str, SubsystemRelation],
    ia,
    count: int,
    rng: np.random.Generator,
) -> AuditResult:
    """Check ``count`` random concrete transitions of the composed system against the composed abstraction.

    Each transition draws a composed concrete state ``x`` (a share on cell boundaries) and one input grid point
    per subsystem, computes ``w = M(x)`` with the concrete map and steps every subsystem's black box with its
    share of ``w``. With ``x̂`` the cell of ``x`` and ``ŵ`` the cell of ``w``, the abstraction must allow it:
    ``ŵ ∈ M̂(x̂)`` (Theorem 4.7) and, unless some subsystem blocks at ``(x̂_i, û_i, ŵ_i)`` (then the composed input
    is not admissible at ``x̂`` and no controller uses it), every ``x'_i``'s cell is a successor of
    ``(x̂_i, û_i, ŵ_i)`` in subsystem ``i``'s relation. The per-part audits check the same inclusions one part at a
    time; this one checks the wiring between them too: state offsets, which ``w_j`` each subsystem reads and in
    which order, which stored relation serves which replica.

    Parameters
    ----------
    network : Network
    relations : dict of str to SubsystemRelation
        By subsystem key (``Subsystem.key``), as :class:`workers.job.AbstractionResult` holds them.
    ia : InterconnectionAbstraction
    count : int
        Composed transitions to draw.
    rng : numpy.random.Generator

    Returns
    -------
    AuditResult
        ``transitions_checked`` counts the composed transitions with every subsystem non-blocking (plus those
        whose ``ŵ`` is not in ``M̂(x̂)``, which are violations whatever the subsystems do); ``skipped_blocking``
        the others.
    """
    grid = network.composed_state_grid()
    subs = network.subsystems
    checked = violations = skipped = 0
    first: str | None = None
    for b in _batches(count):
        x, x_idx, w, w_idx, w_in = _composed_draws(network, grid, b, rng)
        bad_w = ~(w_in & ia.contains(x_idx, w_idx))
        blocked = np.zeros(b, dtype=bool)
        bad_sub = np.zeros(b, dtype=bool)
        culprit = np.full(b, -1, dtype=np.int64)
        records = []
        for i, s in enumerate(subs):
            sl = slice(s.state_offset, s.state_offset + s.n)
            xi = s.state_grid.ravel(x_idx[:, sl])
            ui = rng.integers(0, s.input_grid.size, b)
            u = s.input_grid.points(s.input_grid.unravel(ui))
            if s.reads:
                assert s.internal_grid is not None  # build_network gives a subsystem that reads w its grid
                ws = w[:, list(s.reads)]
                wi = s.internal_grid.ravel(w_idx[:, list(s.reads)])
            else:
                ws = np.zeros((b, 0))
                wi = np.zeros(b, dtype=np.int64)
            xn = s.dynamics(x[:, sl], u, ws)
            lo, hi, block = relations[s.key].successor_ranges(xi, ui, wi)
            ok, n_idx = _successor_ok(s.state_grid, xn, lo, hi)
            blocked |= block
            new_bad = ~block & ~ok & ~bad_sub
            culprit[new_bad] = i
            bad_sub |= ~block & ~ok
            records.append((xi, ui, wi, u, xn, n_idx, lo, hi))
        bad = bad_w | (bad_sub & ~blocked)
        live = bad_w | ~blocked
        checked += int(live.sum())
        skipped += int((~live).sum())
        violations += int(bad.sum())
        if bad.any() and first is None:
            k = int(np.argmax(bad))
            if bad_w[k]:
                first = (
                    f"composition: x={x[k].tolist()} (cells {x_idx[k].tolist()}) M(x)={w[k].tolist()} in internal "
                    f"cells {w_idx[k].tolist()}, which M̂ does not allow"
                )
            else:
                i = int(culprit[k])
                xi, ui, wi, u, xn, n_idx, lo, hi = (r[k] for r in records[i])
                first = (
                    f"composition: subsystem {subs[i].name}, state cell {int(xi)}, input {int(ui)}, internal cell "
                    f"{int(wi)}: x={x[k].tolist()} M(x)={w[k].tolist()} u={u.tolist()} -> x'={xn.tolist()} in cell "
                    f"{n_idx.tolist()}, abstraction allows {lo.tolist()}..{hi.tolist()}"
                )
    return AuditResult(checked, violations, skipped, first)


#: Composed transitions of an audit of ``count`` transitions per part: at least ``min(count, COMPOSITION_MIN)``.
COMPOSITION_MIN = 10_000


def composition_transitions(count: int) -> int:
    """Transitions of the composed system that :func:`audit_abstraction` draws by default: a tenth of ``count``
    (the composition checks the same inclusions again, plus the wiring between the parts), at least
    ``min(count, COMPOSITION_MIN)``."""
    return max(min(count, COMPOSITION_MIN), count // 10)


def audit_abstraction(
    network: Network, relations: dict[str, SubsystemRelation], ia: Any, count: int, rng: np.random.Generator,
    progress: Callable[[int, int, str], None] | None = None, composition: int | None = None,
    seconds: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Theorems 4.2 and 4.7 and the composition, each checked on ``count`` random concrete transitions.

    Returns the report's ``audit`` entry (``transitions_checked``, ``violations``, ``parts``). Draws from ``rng``
    in a fixed order, so the same generator state gives the same report in any process.
    ``progress(done, total, part)`` is called after each part. ``composition``: transitions of the composed
    system (default: :func:`composition_transitions`). ``seconds``, if given, receives each
    part's wall time (kept out of the report, so the same draws give the same report).
    """
    report = progress or (lambda done, total, part: None)
    groups = network.unique_subsystems()
    parts: dict[str, AuditResult] = {}
    seconds = {} if seconds is None else seconds
    total = len(groups) + 2

    def timed(name: str, check: Callable[[], AuditResult]) -> None:
        t0 = time.perf_counter()
        parts[name] = check()
        seconds[name] = time.perf_counter() - t0
        report(len(parts), total, name)

    for key, members in groups.items():
        sub, rel = members[0], relations[key]
        timed(sub.name, lambda: audit_subsystem(sub, rel, count, rng))  # noqa: B023 - called at once
    timed("interconnection", lambda: audit_interconnection(network, ia, count, rng))
    # The composed system: the same inclusions again, plus the wiring between the parts (which w_j each
    # subsystem reads, offsets, which relation serves which replica); `compabs audit DIR --transitions N` draws
    # N of them against the stored abstraction.
    if composition is None:
        composition = composition_transitions(count)
    timed("composition", lambda: audit_composition(network, relations, ia, composition, rng))
    return {
        "transitions_checked": sum(p.transitions_checked for p in parts.values()),
        "violations": sum(p.violations for p in parts.values()),
        "parts": {k: p.as_dict() for k, p in parts.items()},
    }
