"""Explicit games: the fixed points of a game whose relation fits in memory, without BDDs (Algorithm 5).

A single system's relation is already one box of successor cells per (cell, input) (Definition 4.2,
:class:`~pipelines.abstraction.relation.SubsystemRelation`). Encoding it as BDDs costs far more than solving the
game on it (docs/method.md §5), so a game that fits in memory is solved on the boxes themselves: predecessor
lists in one CSR array, built in bulk, and SCOTS's worklist algorithms, linear in the transitions
(:mod:`.explicit_kernels`). The specifications, fixed points and controllers are those of :mod:`.fixed_points`,
set for set:

* :func:`safe`: ``νZ. S ∧ ∃u.CPre(Z)``, every input keeping the state in the invariant;
* :func:`reach` (and reach-avoid): ``μZ. (T ∨ ∃u.CPre(Z)) ∧ S ∧ ¬A``, the progress controller (an input counts
  at a cell only in the iteration where the cell entered; targets get every input);
* :func:`reach_and_stay`: the co-Büchi fixed point and Reach(Safe), as :func:`.fixed_points.reach_and_stay`.

``CPre(Z)(x̂, û)``: ``û`` is not blocking at ``x̂`` and every cell of its successor box lies in ``Z``. The
results are :class:`ExplicitResult` objects: a domain, a controller as a boolean (cell, input) array, and for
progress controllers the layer of each cell; ``tests/`` compare them with the BDD solver's, set for set.

Which games are explicit: a network of one subsystem that reads no internal variable (a single plant: SCOTS's
and Dionysos.jl's examples, a user's own black box). :func:`explicit_bytes` is the memory the solver needs, which
:func:`choose_backend` compares with what the machine has.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from pipelines.errors import SpecError
from pipelines.spec.regions import AbstractRegion, abstract_region
from pipelines.synthesis import explicit_kernels as kernels
from pipelines.synthesis import results

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.abstraction.relation import SubsystemRelation
    from pipelines.network import Network
    from pipelines.spec.model import SpecificationSpec

BACKENDS = ("auto", "explicit", "bdd")
#: Fraction of the machine's available memory an explicit game may take before ``auto`` chooses BDDs.
MEMORY_SHARE = 0.5
#: ``progress(iteration, message)``, as :data:`.fixed_points.IterationProgress`.
IterationProgress = Callable[[int, str], None]


def explicit_applicable(network: Network) -> str | None:
    """Why ``network``'s game cannot be solved explicitly, or ``None`` if it can (one subsystem, no internal
    inputs)."""
    if len(network.subsystems) != 1:
        return (f"the network has {len(network.subsystems)} subsystems: the explicit back end solves single systems "
                "(networks are composed as BDDs)")
    if network.subsystems[0].reads:
        return "the subsystem reads internal variables: the explicit back end solves systems without internal inputs"
    return None


def transitions(relation: SubsystemRelation) -> int:
    """The relation's transitions: the cells of the successor boxes of its non-blocking pairs (one bulk pass)."""
    widths = relation.hi.astype(np.int64)
    widths -= relation.lo
    widths += 1
    np.maximum(widths, 0, out=widths)
    per_pair = widths[..., 0].copy()
    for k in range(1, widths.shape[-1]):  # column by column: a product over a short last axis is slow in numpy
        per_pair *= widths[..., k]
    per_pair[relation.blocking] = 0
    return int(per_pair.sum())


def explicit_bytes(relation: SubsystemRelation) -> int:
    """Memory the explicit solver needs beyond the relation itself: the predecessor lists (4 bytes per
    transition, 8 per cell) and a few counters per pair and per cell."""
    n_x, n_u = relation.blocking.shape[:2]
    return 4 * transitions(relation) + 8 * n_x + 16 * n_x * n_u + 64 * n_x


def available_bytes() -> int:
    """Memory available to this process (``MemAvailable``; 4 GiB where it cannot be read)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 4 << 30


def choose_backend(requested: str, network: Network, relations: Mapping[str, SubsystemRelation]) -> str:
    """``explicit`` or ``bdd`` for ``options.synthesis_backend``: ``auto`` is explicit where the game qualifies
    (:func:`explicit_applicable`) and its lists fit in :data:`MEMORY_SHARE` of the available memory.

    Raises
    ------
    SpecError
        ``explicit`` asked for a game that cannot be solved explicitly.
    """
    if requested not in BACKENDS:
        raise SpecError(f"options.synthesis_backend must be one of {', '.join(BACKENDS)}, got {requested!r}")
    if requested == "bdd":
        return "bdd"
    why = explicit_applicable(network)
    if requested == "explicit":
        if why is not None:
            raise SpecError(f"options.synthesis_backend is 'explicit', but {why}; use 'auto' or 'bdd'")
        return "explicit"
    if why is not None:
        return "bdd"
    (relation,) = relations.values()
    fits = relation.blocking.size < 2**31 and explicit_bytes(relation) <= MEMORY_SHARE * available_bytes()
    return "explicit" if fits else "bdd"


@dataclass
class ExplicitGame:
    """A single system's game as boxes of successor cells, with its predecessor lists.

    Attributes
    ----------
    shape : tuple of int
        The state grid's shape (cells per coordinate); cells are flat row-major indices.
    n_u : int
        Inputs (flat indices of the input grid).
    lo, hi : ndarray of int32, shape (n_x * n_u, n)
        Per pair ``p = x̂ · n_u + û``, the successor box.
    blocking : ndarray of bool, shape (n_x * n_u,)
    indptr, preds : ndarray
        The CSR predecessor lists (:func:`.explicit_kernels.predecessor_lists`).
    counts : ndarray of int32, shape (n_x * n_u,)
        Successors per pair (:data:`.explicit_kernels.NEVER` where blocking).
    build_seconds : float
    """

    shape: tuple[int, ...]
    n_u: int
    lo: np.ndarray
    hi: np.ndarray
    blocking: np.ndarray
    indptr: np.ndarray
    preds: np.ndarray
    counts: np.ndarray
    build_seconds: float

    @classmethod
    def from_relation(cls, relation: SubsystemRelation, shape: Sequence[int]) -> ExplicitGame:
        """The game of a relation without internal inputs (its ``w`` axis of size 1)."""
        t0 = time.perf_counter()
        n_x, n_u, n_w = relation.blocking.shape
        if n_w != 1:
            raise ValueError(f"an explicit game has no internal inputs; the relation has {n_w} internal cells")
        shape = tuple(int(k) for k in shape)
        if math.prod(shape) != n_x:
            raise ValueError(f"a relation of {n_x} cells does not fit the grid {shape}")
        if n_x * n_u >= 2**31:
            raise ValueError(f"{n_x * n_u:,} (cell, input) pairs: an explicit game holds fewer than 2^31")
        n = len(shape)
        lo = np.ascontiguousarray(relation.lo.reshape(n_x * n_u, n), dtype=np.int32)
        hi = np.ascontiguousarray(relation.hi.reshape(n_x * n_u, n), dtype=np.int32)
        blocking = np.ascontiguousarray(relation.blocking.reshape(n_x * n_u))
        strides = np.array([math.prod(shape[d + 1:]) for d in range(n)], dtype=np.int64)
        indptr, preds = kernels.predecessor_lists(lo, hi, blocking, strides, n_x)
        counts = kernels.successor_counts(lo, hi, blocking)
        return cls(shape, int(n_u), lo, hi, blocking, indptr, preds, counts, time.perf_counter() - t0)

    @property
    def n_x(self) -> int:
        return math.prod(self.shape)

    @property
    def transitions(self) -> int:
        return int(self.preds.size)

    def states(self, region: AbstractRegion) -> np.ndarray:
        """A union of index boxes as a boolean array over the cells (clipped to the grid, as
        :func:`~pipelines.symbolic.relations.region`)."""
        mask = np.zeros(self.shape, dtype=bool)
        for first, last in region.boxes:
            lo = np.maximum(np.asarray(first, dtype=np.int64), 0)
            hi = np.minimum(np.asarray(last, dtype=np.int64), np.asarray(self.shape) - 1)
            if np.all(hi >= lo):
                mask[tuple(slice(int(a), int(b) + 1) for a, b in zip(lo, hi))] = True
        return mask.reshape(-1)

    def pairs(self, mask: np.ndarray) -> np.ndarray:
        """A boolean per-pair array as (cell, input), shape (n_x, n_u)."""
        return np.asarray(mask, dtype=bool).reshape(self.n_x, self.n_u)

    def describe(self) -> dict[str, Any]:
        return {"cells": self.n_x, "inputs": self.n_u, "transitions": self.transitions,
                "non_blocking_pairs": int((~self.blocking).sum()), "build_seconds": self.build_seconds,
                "predecessor_bytes": int(self.preds.nbytes + self.indptr.nbytes)}


@dataclass
class ExplicitResult:
    """A winning domain and a controller as arrays (the explicit :class:`~.fixed_points.SynthesisResult`).

    Attributes
    ----------
    kind : str
        As :attr:`.fixed_points.SynthesisResult.kind`.
    domain : ndarray of bool, shape (n_x,)
    admissible : ndarray of bool, shape (n_x, n_u)
        The controller: the inputs allowed at each cell (none outside the domain).
    layer : ndarray of int32, shape (n_x,), or None
        For a progress controller, the iteration at which each cell entered (``0``: the target, or the invariant
        of Reach(Safe); ``-1`` outside the domain).
    iterations, inner_iterations : int
        As the symbolic fixed point's.
    seconds : float
        Wall time of the fixed point(s), controller included.
    details : dict
        JSON-ready extras.
    """

    kind: str
    domain: np.ndarray
    admissible: np.ndarray
    layer: np.ndarray | None
    iterations: int
    inner_iterations: int
    seconds: float
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def domain_states(self) -> int:
        return int(self.domain.sum())

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers (:func:`.results.summary`)."""
        return results.summary(self, controller_form="array", controller_pairs=int(self.admissible.sum()))


def _tick(progress: IterationProgress | None, kind: str, iterations: int, domain: np.ndarray) -> None:
    if progress is not None:
        progress(iterations, f"{kind} iteration {iterations}: {int(domain.sum()):,} states")


def safe(game: ExplicitGame, S: np.ndarray, *, progress: IterationProgress | None = None,
         kind: str = "safe") -> ExplicitResult:
    """Safety ``□S``: ``νZ. S ∧ ∃u.CPre(Z)``; the controller allows every input that keeps the state in ``Z``
    (:func:`.fixed_points.safe`)."""
    t0 = time.perf_counter()
    Z, outside, iterations = kernels.safety(game.indptr, game.preds, game.blocking, game.n_u, S,
                                            np.zeros_like(S))
    admissible = game.pairs((outside == 0) & ~game.blocking) & Z[:, None]
    _tick(progress, kind, iterations, Z)
    return ExplicitResult(kind, Z, admissible, None, iterations, 0, time.perf_counter() - t0)


def reach(game: ExplicitGame, T: np.ndarray, avoid: np.ndarray | None = None, *, safe_set: np.ndarray | None = None,
          kind: str = "reach", progress: IterationProgress | None = None) -> ExplicitResult:
    """Reachability ``◇T`` in ``S ∖ A``: ``μZ. (T ∨ ∃u.CPre(Z)) ∧ S ∧ ¬A`` with the progress controller
    (:func:`.fixed_points.reach`): a cell of layer ``k > 0`` allows the inputs whose successors all lie in layers
    ``< k``; a target cell allows every input."""
    t0 = time.perf_counter()
    keep = np.ones(game.n_x, dtype=bool)
    if avoid is not None:
        keep &= ~avoid
    if safe_set is not None:
        keep &= safe_set
    layer, chosen = kernels.reach(game.indptr, game.preds, game.counts, game.n_u, T, keep)
    domain = layer >= 0
    admissible = game.pairs(chosen)
    admissible[layer == 0] = True
    iterations = int(layer.max()) + 1 if domain.any() else 1
    _tick(progress, kind, iterations, domain)
    return ExplicitResult(kind, domain, admissible, layer, iterations, 0, time.perf_counter() - t0)


def cobuchi(game: ExplicitGame, phi: np.ndarray, *, safe_set: np.ndarray | None = None,
            progress: IterationProgress | None = None) -> ExplicitResult:
    """``◇□φ`` (``□S ∧ ◇□φ`` with ``safe_set``) as ``μX. νY. (φ ∧ S ∧ ∃u.CPre(Y)) ∨ (S ∧ ∃u.CPre(X))``, with
    the controller of :func:`.fixed_points.cobuchi`."""
    t0 = time.perf_counter()
    top = np.ones(game.n_x, dtype=bool) if safe_set is None else safe_set.copy()
    X, chosen, outer, inner = kernels.cobuchi(game.indptr, game.preds, game.blocking, game.counts, game.n_u,
                                              phi & top, top)
    _tick(progress, "cobuchi", outer, X)
    return ExplicitResult("reach_and_stay/cobuchi", X, game.pairs(chosen), None, outer, inner,
                          time.perf_counter() - t0)


def reach_safe(game: ExplicitGame, phi: np.ndarray, *, safe_set: np.ndarray | None = None,
               progress: IterationProgress | None = None) -> ExplicitResult:
    """``◇□φ`` as ``Reach_S(Safe(φ ∧ S))`` (:func:`.fixed_points.reach_safe`): the safety controller on the
    invariant (layer 0), the progress controller outside it."""
    t0 = time.perf_counter()
    s = safe(game, phi if safe_set is None else phi & safe_set, kind="reach_safe/safe", progress=progress)
    r = reach(game, s.domain, safe_set=safe_set, kind="reach_safe/reach", progress=progress)
    admissible = np.where(s.domain[:, None], s.admissible, r.admissible)
    details = {"safe_states": s.domain_states, "safe_seconds": s.seconds, "reach_seconds": r.seconds}
    return ExplicitResult("reach_and_stay/reach_safe", r.domain, admissible, r.layer, r.iterations, s.iterations,
                          time.perf_counter() - t0, details)


def reach_and_stay(game: ExplicitGame, phi: np.ndarray, methods: Sequence[str] = ("cobuchi", "reach_safe"), *,
                   safe_set: np.ndarray | None = None,
                   progress: IterationProgress | None = None) -> dict[str, ExplicitResult]:
    """``◇□φ`` by each of ``methods`` (:func:`.fixed_points.reach_and_stay`)."""
    out: dict[str, ExplicitResult] = {}
    for name in methods:
        if name == "cobuchi":
            out[name] = cobuchi(game, phi, safe_set=safe_set, progress=progress)
        elif name == "reach_safe":
            out[name] = reach_safe(game, phi, safe_set=safe_set, progress=progress)
        else:
            raise ValueError(f"unknown reach-and-stay fixed point {name!r}: use cobuchi or reach_safe")
    return out


def solve(game: ExplicitGame, specification: SpecificationSpec, grid: Any,
          reach_and_stay_methods: Sequence[str] = ("cobuchi", "reach_safe"),
          progress: IterationProgress | None = None) -> dict[str, ExplicitResult]:
    """The specification's fixed points on ``game`` (regions approximated as for the BDD back end: targets and
    safe sets from inside, avoid sets from outside; docs/method.md §1); keys as
    :func:`~.synthesize.synthesize`'s results."""

    def states(name: str) -> np.ndarray:
        return game.states(abstract_region(getattr(specification, name), grid, f"specification.{name}",
                                           outer=(name == "avoid")))

    kind = specification.kind
    S = states("safe") if kind != "safe" and specification.safe is not None else None
    if kind == "safe":
        return {"safe": safe(game, states("safe"), progress=progress)}
    if kind == "reach":
        return {"reach": reach(game, states("target"), safe_set=S, progress=progress)}
    if kind == "reach_avoid":
        return {"reach_avoid": reach(game, states("target"), states("avoid"), safe_set=S, kind="reach_avoid",
                                     progress=progress)}
    return reach_and_stay(game, states("target"), reach_and_stay_methods, safe_set=S, progress=progress)

