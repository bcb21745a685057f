"""Why a winning domain is empty: which part of the safe set (or target) is lost first, and why.

Worked out from what a job already holds, the subsystem relations as interval arrays (``lo``, ``hi``,
``blocking``: :class:`~pipelines.abstraction.relation.SubsystemRelation`), the interconnection abstraction and the
specification's regions, never from the BDDs, so it costs one pass over the relations per round.

An empty domain of a ``safe`` or ``reach_and_stay`` specification means the safety game on the region
``R`` (``S``, or ``φ ∧ S``) is lost (a co-Büchi or Reach(Safe) domain contains ``Safe(φ ∧ S)``, and is empty only
with it). Each subsystem ``i`` then plays two local safety games on ``R_i``, the projection of ``R`` on its
state:

* *favourable*: an input and an internal cell ``ŵ`` are chosen together (``∃û ∃ŵ``). The projection of any
  composed winning set lies in its winning set (a composed state has some admitted ``ŵ``, and its successors
  stay in the projection), so when it is empty **the domain is empty because of this subsystem alone**, and
  the cells it loses at the first step say why: every input blocking (the successors leave the state box),
  every image wider than the region there (the growth bound), or images narrow enough that none lands inside
  (the inputs cannot counter the drift);
* *adverse*: ``∃û ∀ŵ`` over the internal cells the interconnection admits from states of ``R`` (sampled). When
  only this one is empty, the uncertainty of the internal variables (the interconnection's error bound and the
  spread of ``M̂``) loses the region.

When every subsystem keeps part of its projection in both games, the region is lost through the coupling of the
subsystems' states (a region that is not a product, such as consensus). An empty ``reach`` or ``reach_avoid``
domain means the target holds no cell of the safe set outside the avoid set (the target's own cells win at once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.interconnection import InterconnectionAbstraction
from pipelines.network import Network, Subsystem
from pipelines.spec.model import JobSpec
from pipelines.spec.regions import AbstractRegion, IndexBox, spec_regions, union_count

__all__ = ["LocalGame", "explain_empty_domain", "local_game"]

#: Most rounds of a local game (each round is one pass over the relation), and most triples passed over in all.
MAX_ROUNDS = 200
MAX_WORK = 2 * 10**8
#: Triples looked at at once.
CHUNK = 1 << 20
#: States of the region sampled to find the internal cells the interconnection admits there.
W_SAMPLES = 256
#: Causes of a cell lost at the first step, in the order they are told, and how they are told.
CAUSES = ("blocking", "wide", "drift")
CAUSE_WORDS = {"blocking": "blocking", "wide": "wider than the region", "drift": "drifting out"}
CAUSE_TEXT = {
    "blocking": "every input is blocking near the boundary, its successors leaving the state box",
    "wide": "every image of some cells is wider than a cell and spills out of the region, through the growth bound",
    "drift": "the inputs cannot counter the drift",
}


def _cells(count: int) -> str:
    return f"{count:,} cell{'' if count == 1 else 's'}"


@dataclass
class LocalGame:
    """One subsystem's local safety games on its projection of the region (module docstring)."""

    subsystem: Subsystem
    region: np.ndarray  # bool, the subsystem's state grid shape: R_i
    favourable: np.ndarray  # bool: the winning cells with ∃û ∃ŵ
    adverse: np.ndarray | None  # bool: with ∃û ∀ŵ admitted (None: no internal variables)
    rounds: int  # steps of the favourable game that lost cells
    first_lost: dict[str, list[int]] = field(default_factory=dict)  # cause -> flat cells lost at the first step
    example: str = ""  # the first lost cell of the most frequent cause, in words


def _projection(region: AbstractRegion, sub: Subsystem) -> np.ndarray:
    mask = np.zeros(sub.state_grid.shape, dtype=bool)
    a, b = sub.state_offset, sub.state_offset + sub.n
    for lo, hi in region.boxes:
        mask[tuple(slice(int(f), int(t) + 1) for f, t in zip(lo[a:b], hi[a:b]))] = True
    return mask


def _inside(rel: SubsystemRelation, mask: np.ndarray) -> np.ndarray:
    """Whether each triple is admissible with every successor in ``mask``; bool (n_x, n_u, n_w). A summed-area
    table of ``mask`` counts the cells of each successor box in ``2^n`` look-ups, :data:`CHUNK` triples at a time."""
    n = mask.ndim
    table = np.zeros(tuple(s + 1 for s in mask.shape), dtype=np.int64)  # a zero border before each axis
    table[(slice(1, None),) * n] = mask
    for d in range(n):
        np.cumsum(table, axis=d, out=table)
    n_x, n_u, n_w = rel.blocking.shape
    out = np.zeros((n_x, n_u, n_w), dtype=bool)
    step = max(1, CHUNK // max(1, n_u * n_w))
    for start in range(0, n_x, step):
        part = slice(start, start + step)
        lo, hi = rel.lo[part].astype(np.int64), rel.hi[part].astype(np.int64) + 1
        count = np.zeros(lo.shape[:-1], dtype=np.int64)
        for corner in range(2 ** n):
            picks = [(corner >> d) & 1 for d in range(n)]
            count += (-1) ** (n - sum(picks)) * table[tuple(hi[..., d] if p else lo[..., d] for d, p in enumerate(picks))]
        out[part] = ~rel.blocking[part] & (count == np.prod(np.maximum(hi - lo, 0), axis=-1))
    return out


def _run_lengths(mask: np.ndarray, axis: int) -> np.ndarray:
    """For each cell of ``mask``, the length of the run of ``mask`` cells through it along ``axis`` (0 off it)."""
    m = np.moveaxis(mask, axis, 0)
    fwd, bwd = np.zeros(m.shape, dtype=np.int64), np.zeros(m.shape, dtype=np.int64)
    for k in range(m.shape[0]):
        fwd[k] = np.where(m[k], (fwd[k - 1] if k else 0) + 1, 0)
    for k in range(m.shape[0] - 1, -1, -1):
        bwd[k] = np.where(m[k], (bwd[k + 1] if k + 1 < m.shape[0] else 0) + 1, 0)
    return np.moveaxis(np.where(m, fwd + bwd - 1, 0), 0, axis)


def _cells_text(sub: Subsystem, first: np.ndarray, last: np.ndarray) -> str:
    """The concrete box of cells ``first .. last`` (per-dimension indices), ``[9.5, 10.5]`` or ``[a, b] × …``."""
    g = sub.state_grid
    half = g.eta_array / 2
    lo, hi = g.points(first[None])[0] - half, g.points(last[None])[0] + half
    return " × ".join(f"[{a:.4g}, {b:.4g}]" for a, b in zip(lo, hi))


def _point_text(values: np.ndarray) -> str:
    return f"{values[0]:.4g}" if values.size == 1 else "(" + ", ".join(f"{v:.4g}" for v in values) + ")"


def _outside(region: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Cells of each successor box ``lo[k] .. hi[k]`` outside ``region``, shape (k,)."""
    return np.array([np.prod(high - low + 1) - np.count_nonzero(region[tuple(slice(a, b + 1) for a, b in zip(low, high))])
                     for low, high in zip(lo, hi)])


def _classify(sub: Subsystem, rel: SubsystemRelation, region: np.ndarray, lost: np.ndarray
              ) -> tuple[dict[str, list[int]], str]:
    """Why each cell lost at the first step is lost (:data:`CAUSES`), and the first of the most frequent cause.

    ``blocking``: no input is admissible. ``wide``: every image is wider than the region there, or the closest
    image still covers the cell itself (an input holds the state, the growth bound spills it out of the region).
    ``drift``: the closest image has left the cell (every input moves the state out)."""
    n = sub.n
    runs = np.stack([_run_lengths(region, d).reshape(-1) for d in range(n)], axis=-1)  # (n_x, n)
    causes: dict[str, list[int]] = {c: [] for c in CAUSES}
    seen: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, int, bool]] = {}  # per cell: u, lo, hi, closest, wider
    for x in np.flatnonzero(lost.reshape(-1)).tolist():
        u, w = np.nonzero(~rel.blocking[x])
        if u.size == 0:
            causes["blocking"].append(x)
            continue
        lo, hi = rel.lo[x][u, w].astype(np.int64), rel.hi[x][u, w].astype(np.int64)
        outside = _outside(region, lo, hi)
        k = int(np.argmin(outside))
        idx = sub.state_grid.unravel(np.array([x]))[0]
        wider = bool(np.all(np.any(hi - lo + 1 > runs[x], axis=-1)) and np.any(outside < np.prod(hi - lo + 1, axis=-1)))
        holds = bool(np.all((lo[k] <= idx) & (idx <= hi[k])))
        causes["wide" if wider or holds else "drift"].append(x)
        seen[x] = (u, lo, hi, k, wider)
    cause = max(CAUSES, key=lambda c: len(causes[c]))
    if not causes[cause]:
        return causes, ""
    x = causes[cause][0]
    idx = sub.state_grid.unravel(np.array([x]))[0]
    where = f"at x ≈ {_point_text(sub.state_grid.points(idx[None])[0])} (cell {_cells_text(sub, idx, idx)})"
    if cause == "blocking":
        span = _cells_text(sub, np.zeros(n, dtype=np.int64), np.asarray(sub.state_grid.shape) - 1)
        return causes, (f"{where} the successors of every input leave the state box {span}: a larger state box, "
                        "or dynamics that stay inside it")
    u, lo, hi, k, wider = seen[x]
    inputs = sub.input_grid.all_points() if sub.input_grid.size <= 10_000 else None

    def with_u(j: int) -> str:
        return "" if inputs is None else f" (u = {_point_text(inputs[u[j]])})"

    narrow = " or the 'hull' growth bound" if rel.method != "hull" else ""
    fix = f": a finer grid (eta), more samples{narrow} narrow the images (L_x = {float(rel.L_x):g}, {rel.method})"
    if cause == "wide" and wider:
        width = hi - lo + 1
        over = width - runs[x]  # how much wider than the region there, per dimension
        j = int(np.argmin(over.max(axis=-1)))
        d = int(np.argmax(over[j]))
        return causes, (f"{where} the narrowest successors of any input{with_u(j)} are {_cells_text(sub, lo[j], hi[j])}, "
                        f"{width[j, d]} cells of x[{d}] where the region has {runs[x, d]}{fix}")
    if cause == "wide":
        return causes, (f"{where} the closest successors of any input{with_u(k)} are {_cells_text(sub, lo[k], hi[k])}: "
                        f"they cover the cell itself and spill out of the region, the image being wider than a cell{fix}")
    wholly = _outside(region, lo[k:k + 1], hi[k:k + 1])[0] == np.prod(hi[k] - lo[k] + 1)
    span = "" if inputs is None else (f" (u from {_point_text(inputs.min(axis=0))} to "
                                      f"{_point_text(inputs.max(axis=0))})")
    return causes, (f"{where} the closest successors of any input{with_u(k)} are {_cells_text(sub, lo[k], hi[k])}, "
                    f"{'' if wholly else 'partly '}outside the region: the inputs{span} cannot counter the drift")


def _admitted_cells(region: AbstractRegion, ia: InterconnectionAbstraction) -> list[np.ndarray]:
    """Per internal variable, the cells the interconnection admits from states of the region (its boxes' corners
    and :data:`W_SAMPLES` random states); bool (size_j,) each."""
    if ia.p == 0:
        return []
    rng = np.random.default_rng(0)
    boxes = list(region.boxes)
    volumes = np.array([float(math.prod(int(h - lo_ + 1) for lo_, h in zip(lo, hi))) for lo, hi in boxes])
    picks = rng.choice(len(boxes), W_SAMPLES, p=volumes / volumes.sum())
    states = [np.array([lo for lo, _ in boxes]), np.array([hi for _, hi in boxes])]
    states.append(np.array([rng.integers(boxes[b][0], boxes[b][1] + 1) for b in picks]))
    return [np.asarray(np.any(mask, axis=0), dtype=bool) for mask in ia.allowed_cells(np.concatenate(states))]


def _admitted_w(sub: Subsystem, admitted: list[np.ndarray]) -> np.ndarray:
    """The internal cells of ``sub`` (the product over the variables it reads) of :func:`_admitted_cells`."""
    if sub.internal_grid is None or not sub.reads:
        return np.ones(sub.n_w_cells, dtype=bool)
    per_read = [admitted[j] for j in sub.reads]
    if len(per_read) == 1:
        return np.asarray(per_read[0], dtype=bool)
    return np.asarray(np.logical_and.reduce(np.ix_(*per_read)), dtype=bool).reshape(-1)


def local_game(sub: Subsystem, rel: SubsystemRelation, region_mask: np.ndarray, admitted_w: np.ndarray | None = None
               ) -> LocalGame:
    """The local safety games of ``sub`` on ``region_mask`` (module docstring), and why cells are lost first."""
    admitted = np.ones(sub.n_w_cells, dtype=bool) if admitted_w is None else admitted_w
    most = max(1, min(MAX_ROUNDS, MAX_WORK // max(1, rel.blocking.size)))  # unfinished: not shown to be lost
    z, rounds, first = region_mask.copy(), 0, None
    for _ in range(most):
        keep = z & _inside(rel, z).any(axis=(1, 2)).reshape(z.shape)
        if first is None:
            first = z & ~keep
        if np.array_equal(keep, z):
            break
        z, rounds = keep, rounds + 1
    adverse = None
    if sub.n_w_cells > 1 and bool(np.any(admitted)):
        a = region_mask.copy()
        for _ in range(most):
            ok = np.any(np.all(_inside(rel, a)[:, :, admitted], axis=2), axis=1).reshape(a.shape)
            if np.array_equal(a & ok, a):
                break
            a = a & ok
        adverse = a
    game = LocalGame(sub, region_mask, z, adverse, rounds)
    if not z.any():
        assert first is not None
        game.first_lost, game.example = _classify(sub, rel, region_mask, first)
    return game


def _intersect(a: AbstractRegion, b: AbstractRegion) -> list[IndexBox]:
    out = []
    for la, ha in a.boxes:
        for lb, hb in b.boxes:
            lo, hi = np.maximum(la, lb), np.minimum(ha, hb)
            if np.all(hi >= lo):
                out.append((lo, hi))
    return out


def _reach_reasons(regions: dict[str, AbstractRegion]) -> list[str]:
    target = regions["target"]
    boxes = _intersect(target, regions["safe"]) if "safe" in regions else list(target.boxes)
    if not boxes:
        return ["why the winning domain is empty: the target and the safe set share no whole cell; a run cannot "
                "reach the target while staying in the safe set"]
    if "avoid" in regions:
        kept = union_count(boxes)
        hit = union_count(_intersect(AbstractRegion(tuple(boxes)), regions["avoid"]))
        if hit >= kept:
            return ["why the winning domain is empty: every cell of the target" + (" inside the safe set" if "safe" in
                    regions else "") + " meets the avoid set (approximated from outside: a cell that touches an "
                    "obstacle counts as one); shrink the obstacles or move the target"]
    return []


def explain_empty_domain(network: Network, relations: dict[str, SubsystemRelation], ia: InterconnectionAbstraction,
                         spec: JobSpec, max_lines: int = 3) -> list[str]:
    """Lines (warnings) saying why the winning domain of ``spec`` is empty (module docstring); ``[]`` when the data
    show no reason (a domain that is not empty, or lost in a way these local games do not see).

    Parameters
    ----------
    relations : dict of str to SubsystemRelation
        By subsystem key, as the abstraction stages return them.
    max_lines : int
        At most this many subsystems are named.
    """
    regions = spec_regions(spec, network)
    kind = spec.specification.kind
    if kind in ("reach", "reach_avoid"):
        return _reach_reasons(regions)
    if kind == "safe":
        region, name = regions["safe"], "safe set"
    elif "safe" in regions:
        region, name = AbstractRegion(tuple(_intersect(regions["target"], regions["safe"]))), "target within the safe set"
        if not region.boxes:
            return ["why the winning domain is empty: the target and the safe set share no whole cell"]
    else:
        region, name = regions["target"], "target"
    games: dict[tuple[str, bytes, bytes], LocalGame] = {}
    named: dict[int, list[str]] = {}  # identical games (replicas): told once, naming every subsystem
    cells = _admitted_cells(region, ia)
    for sub in network.subsystems:
        mask = _projection(region, sub)
        admitted = _admitted_w(sub, cells)
        key = (sub.key, np.packbits(mask).tobytes(), np.packbits(admitted).tobytes())
        if key not in games:
            games[key] = local_game(sub, relations[sub.key], mask, admitted)
        named.setdefault(id(games[key]), []).append(sub.name)
    unique = list(games.values())
    lost = [g for g in unique if not g.favourable.any()]
    adverse = [g for g in unique if g.favourable.any() and g.adverse is not None and not g.adverse.any()]
    kept = [g for g in unique if g not in lost and g not in adverse]

    def who(game: LocalGame) -> str:
        names = named[id(game)]
        return f"subsystem '{names[0]}'" + (f" (and {len(names) - 1} identical)" if len(names) > 1 else "")

    def part(game: LocalGame) -> str:
        idx = np.argwhere(game.region)
        return f"its part of the {name} ({_cells_text(game.subsystem, idx.min(axis=0), idx.max(axis=0))}, " \
               f"{_cells(int(game.region.sum()))})"

    lines = []
    for game in lost[:max_lines]:
        lost_first = sum(len(v) for v in game.first_lost.values())
        main = max(CAUSES, key=lambda c: len(game.first_lost[c]))
        others = ", ".join(f"{len(game.first_lost[c])} {CAUSE_WORDS[c]}" for c in CAUSES
                           if c != main and game.first_lost[c])
        lines.append(
            f"why the winning domain is empty: {who(game)} cannot keep its state in {part(game)} even with the most "
            f"favourable internal variables: {CAUSE_TEXT[main]}; {len(game.first_lost[main]):,} of the "
            f"{_cells(lost_first)} lost at the first step{' (' + others + ')' if others else ''}"
            f"{f', all within {game.rounds} steps' if game.rounds > 1 else ''}; e.g. {game.example}")
    if not lines:
        for game in adverse[:max_lines]:
            sub = game.subsystem
            reads = ", ".join(f"w{j}: error bound {float(ia.error_bounds[j]):.3g} = "
                              f"{float(ia.error_bounds[j]) / network.internal_grids[j].eta[0]:.2g} cells" for j in sub.reads)
            lines.append(
                f"why the winning domain is empty: {who(game)} keeps {int(game.favourable.sum()):,} cells of "
                f"{part(game)} when the internal variables are favourable, but none against every internal cell the "
                f"interconnection admits across the {name} ({reads}): the uncertainty of the internal variables, the "
                "interconnection's error bound, loses it; a tighter interconnection (error: linear or max where the "
                "map is, a finer internal grid, more samples) narrows it")
    if not lines and kept:
        shares = ", ".join(f"{who(g)} {int((g.adverse if g.adverse is not None else g.favourable).sum()):,} of "
                           f"{int(g.region.sum()):,}" for g in kept[:max_lines])
        lines.append(f"why the winning domain is empty: each subsystem alone keeps part of its projection of the {name} "
                     f"({shares} cells), so the {name} is lost through the coupling of the subsystems' states (a "
                     f"{name} that is not a product of per-subsystem sets, such as a consensus region, needs them "
                     "held together)")
    return lines
