"""Symbolic encoding of the abstraction with BDDs (Algorithm 5, Section 4.3; METHOD §5).

One :class:`SymbolicModel` owns one CUDD manager (``dd.cudd``) and every BDD built in it: the subsystem
relations ``T_i(x_i, u_i, w_i, x'_i)`` and their non-blocking sets ``NB_i(x_i, u_i, w_i)``, the interconnection
``M̂(x, w) = ∃z. ∧ R_node``, regions, and controllers.

Encoding
--------
Every grid dimension is a *digit* encoded in binary, most significant bit first:

* ``x{i}`` / ``xn{i}``: current / next cell index of composed-state coordinate ``i`` (one per dimension of a
  subsystem's state grid, coordinates numbered by ``Subsystem.state_offset``);
* ``u{s}``: the *flat* (row-major) input index of subsystem ``s`` (inputs are choices, not intervals, so one
  digit per subsystem is enough and matches the relation arrays);
* ``w{j}``: cell index of internal variable ``j`` (scalar by construction of the network);
* ``z{k}``: cell index of an intermediate variable of MDec (Algorithm 2).

Bit ``b`` of digit ``d`` is the variable ``f"{d}_{b}"``, ``b = 0`` the most significant. A digit with ``K``
cells has ``max(1, ceil(log2 K))`` bits; codes ``>= K`` are excluded by domain constraints
(:meth:`SymbolicModel.domain`). METHOD §5 says ``ceil(log2(K+1))`` bits; ``ceil(log2 K)`` is enough for the
codes ``0 .. K-1`` and saves a bit wherever ``K`` is a power of two (the brief of this module asks for it).

Variable order (chosen on purpose, declared in level order, dynamic reordering off: ENGINEERING "dd/CUDD")

* ``"interleaved"`` (the tanks, METHOD §6): one block per subsystem, blocks in the order :func:`reader_order`
  picks (each below the blocks it reads, chains contiguous) or, for cyclic couplings, :func:`block_order`
  (coupled subsystems close together); in a block first the
  bits of the internal variables it reads (each preceded by the ``z`` of its MDec tree) unless already
  declared, then its input bits, then current and next bits interleaved (``x{i}_0, xn{i}_0, x{i}_1, ...``).
  Internal variables nobody reads go on top.
* ``"shared_top"`` (consensus, METHOD §6): every ``w`` then every ``z`` on top, then per subsystem the blocks
  ``x_i``, ``u_i``, ``x'_i``.

Bulk construction
-----------------
Relations are built from the interval arrays as a Shannon tree, bottom-up, never one point at a time:
every cell gets a leaf id (``np.unique`` over its ``(lo, hi)`` rows; a leaf is a memoised interval comparator
on the output bits), then for each input bit from the bottom level up siblings are paired, the distinct
``(low, high)`` id pairs are found with ``np.unique``, and one ``ite`` is made per distinct pair. The Python work
is proportional to the number of distinct subtrees, not to the number of cells.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Mapping, Sequence

import numpy as np
from dd import cudd

from pipelines.errors import CompabsError

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.interconnection.core import InterconnectionAbstraction, NodeRelation
    from pipelines.network import Network, Subsystem
    from pipelines.spec.regions import AbstractRegion
    from pipelines.abstraction.cells import SubsystemRelation

Function = cudd.Function

ORDERS = ("interleaved", "shared_top")
HEADER_FORMAT = "compabs-bdd/1"
#: Fraction of physical memory CUDD may use by default (ENGINEERING: set max_memory below the budget).
DEFAULT_MEMORY_FRACTION = 0.75
#: The Shannon-tree keys are int64: at most this many input bits per relation.
MAX_TREE_BITS = 62
#: Unique-table slots up to which CUDD keeps its table "loose" (collects garbage only once dead nodes outnumber the
#: slots). CUDD's default (~6.7 M) let the 10 tanks' safety loop leave 8.7 M nodes in the table for at most 0.33 M
#: live ones; every lookup then misses the processor's caches. With 1e5 (and ``MAX_CACHE_ENTRIES``) that loop took
#: 22.9-24.6 s instead of 28-29.5 s (five runs each way, 2026-11-24), for the same result and ~3 % more cache
#: lookups; consensus N = 6 and N = 7 took the same time (34 s, 97-99 s) with peak RSS 655 -> 239 MB and
#: 1224 -> 415 MB.
GC_LOOSE_UP_TO = 100_000
#: Largest computed table (entries) CUDD may grow to. Unbounded, it grew to 8 M entries (256 MB) on the tanks; 2^20
#: is as fast (2^19: 25 s, 2^18: 44 s on the same loop, so smaller is not better).
MAX_CACHE_ENTRIES = 1 << 20


class BDDMemoryError(CompabsError):
    """CUDD ran out of the memory it was allowed (``max_memory``)."""


class Sampler:
    """Draws cells of a set uniformly (:meth:`SymbolicModel.sampler`), its model counts computed once.

    Exact model counts of every node (:meth:`SymbolicModel._count_table`) guide a walk from the root to ``TRUE``
    that takes each branch with the probability of its share of the models (a skipped level is a free bit: 1/2).
    Cost: ``O(|f|)`` to make, ``O(bits)`` per draw; a closed loop keeps one per visited cell.
    """

    def __init__(self, f: Function, table, widths: Sequence[int], columns: Sequence[int]) -> None:
        self._f = f
        self._table = table
        self._widths = tuple(widths)
        self._columns = tuple(columns)  # per digit, MSB first: the column of each bit in level order

    @property
    def empty(self) -> bool:
        return self._table is None

    def draw(self, rng: np.random.Generator | None, size: int | None = None):
        """Codes of ``size`` cells (shape (size, digits)) or of one (shape (digits,)), uniform if ``rng`` is
        given, else the smallest in the variable order; ``None`` / shape (0, digits) if the set is empty."""
        if self._table is None:
            return None if size is None else np.zeros((0, len(self._widths)), dtype=np.int64)
        count, position, N = self._table
        k = 1 if size is None else int(size)
        rows = np.zeros((k, N), dtype=np.int64)
        for r in range(k):
            g, at = self._f, 0
            while at < N:
                q = position(g)
                if at < q:  # a level the function does not test: either value
                    rows[r, at] = 0 if rng is None else int(rng.integers(2))
                    at += 1
                    continue
                reg = ~g if g.negated else g
                lo, hi = (~reg.low, ~reg.high) if g.negated else (reg.low, reg.high)
                w0, w1 = count(lo) << (position(lo) - q - 1), count(hi) << (position(hi) - q - 1)
                take = (w0 == 0) if rng is None else bool(rng.random() * (w0 + w1) < w1)
                rows[r, q] = int(take)
                g = hi if take else lo
                at = q + 1
        out = np.zeros((k, len(self._widths)), dtype=np.int64)
        c = 0
        for d_i, width in enumerate(self._widths):
            for col in self._columns[c:c + width]:
                out[:, d_i] = (out[:, d_i] << 1) | rows[:, col]
            c += width
        return out[0] if size is None else out


def default_max_memory() -> int:
    """``DEFAULT_MEMORY_FRACTION`` of the machine's physical memory, in bytes."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        total = 8 << 30
    return int(total * DEFAULT_MEMORY_FRACTION)


def bit_width(size: int) -> int:
    """Bits of a digit with ``size`` cells: ``max(1, ceil(log2 size))``."""
    if size < 1:
        raise ValueError(f"a digit needs at least one cell, got {size}")
    return max(1, (size - 1).bit_length())


def factorize(keys: np.ndarray, bound: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True)`` for int64 keys in ``[0, bound)``.

    When ``bound`` is small against ``len(keys)`` the distinct keys are found by marking a dense table
    (``O(N + bound)``, no sort): the 10 tanks' 2.8 M-row interconnection node spent 0.5 s of its 1.4 s BDD
    build sorting such keys.
    """
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    if keys.size and bound <= 4 * keys.size + (1 << 16):
        present = np.zeros(bound, dtype=bool)
        present[keys] = True
        uniq = np.flatnonzero(present)
        slot = np.cumsum(present, dtype=np.int64) - 1
        return uniq, slot[keys]
    uniq, inverse = np.unique(keys, return_inverse=True)
    return uniq, inverse.reshape(-1)


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0, return_inverse=True)``, through one int64 mixed-radix key when it fits.

    Parameters
    ----------
    rows : ndarray of int, shape (N, k)

    Returns
    -------
    uniq : ndarray, shape (U, k), in lexicographic order
    inverse : ndarray of int64, shape (N,)
    """
    rows = np.asarray(rows, dtype=np.int64)
    lo = rows.min(axis=0)
    span = rows.max(axis=0) - lo + 1
    if rows.shape[0] == 0 or math.prod(int(v) for v in span) >= 1 << 62:
        uniq, inverse = np.unique(rows, axis=0, return_inverse=True)
        return uniq, inverse.reshape(-1)
    key = np.zeros(rows.shape[0], dtype=np.int64)
    for c in range(rows.shape[1]):
        key = key * int(span[c]) + (rows[:, c] - lo[c])
    ukey, inverse = factorize(key, math.prod(int(v) for v in span))
    first = np.empty(ukey.size, dtype=np.int64)
    first[inverse] = np.arange(rows.shape[0])  # rows with equal keys are equal: any one will do
    return rows[first], inverse


@dataclass(frozen=True)
class SubsystemLayout:
    """What the symbolic layer needs of a subsystem (a :class:`~pipelines.network.Subsystem` without black boxes).

    Attributes
    ----------
    index : int
        Position in the network (``u{index}`` is its input digit).
    state_shape : tuple of int, length n
        Cells per state dimension; coordinate ``state_offset + d`` of the composed state is dimension ``d``.
    n_inputs : int
        Size of the input grid (flat indices).
    reads : tuple of int
        Internal variables it reads; its relation's ``w`` axis is their row-major product.
    key : str
        Identical subsystems share a key and a relation.
    state_offset : int
    name : str
    """

    index: int
    state_shape: tuple[int, ...]
    n_inputs: int
    reads: tuple[int, ...]
    key: str
    state_offset: int
    name: str = ""

    @property
    def coords(self) -> tuple[int, ...]:
        """Composed-state coordinates of this subsystem."""
        return tuple(range(self.state_offset, self.state_offset + len(self.state_shape)))

    @classmethod
    def of(cls, sub: "Subsystem") -> "SubsystemLayout":
        return cls(sub.index, tuple(sub.state_grid.shape), sub.input_grid.size, tuple(sub.reads), sub.key,
                   sub.state_offset, sub.name)


def dependency_arcs(layouts: Sequence[SubsystemLayout], nodes: Sequence["NodeRelation"]) -> set[tuple[int, int]]:
    """Directed couplings ``(reader, read)`` between subsystems (positions in ``layouts``).

    Subsystem ``i`` reads ``j`` when it reads an internal variable whose MDec tree reads a state coordinate of
    ``j`` (``i != j``).
    """
    feeds: dict[str, set[str]] = {}
    for node in nodes:
        feeds.setdefault(node.output, set()).update(node.inputs)

    def x_support(name: str, seen: frozenset = frozenset()) -> set[int]:
        if name.startswith("x"):
            return {int(name[1:])}
        if name in seen:
            return set()
        out: set[int] = set()
        for src in feeds.get(name, ()):
            out |= x_support(src, seen | {name})
        return out

    owner = {c: k for k, s in enumerate(layouts) for c in s.coords}
    arcs: set[tuple[int, int]] = set()
    for i, s in enumerate(layouts):
        for j in s.reads:
            for c in x_support(f"w{j}"):
                k = owner.get(c)
                if k is not None and k != i:
                    arcs.add((i, k))
    return arcs


def reader_order(n: int, arcs: set[tuple[int, int]]) -> list[int] | None:
    """A topological order of ``n`` blocks (each after the blocks it reads) that follows the readers.

    Kahn's algorithm where, among the blocks whose inputs are all placed, the next is one that reads the most
    recently placed block (ties: lowest index): chains of the network (tank 1 -> 2 -> 3 -> 8, ...) stay
    contiguous and every block sits below what it reads. ``None`` when the couplings have a cycle.

    Why, measured on the 10 tanks (safety fixed point, relations restricted to the safe set, machine idle):
    this order 0,1,2,7,3,4,6,5,8,9 took 33 s; the minimum linear arrangement of :func:`block_order`
    (0,1,2,7,9,8,5,3,4,6, length 22) 58 s; over the first 12 iterations other topological orders took 1.5-3x
    and non-topological ones 1.6-9x (one ran out of time). The iterates of the safety game relate each tank to
    the tanks upstream of it, which this order keeps above it.
    """
    reads: dict[int, set[int]] = {k: set() for k in range(n)}
    readers: dict[int, list[int]] = {k: [] for k in range(n)}
    for a, b in arcs:
        reads[a].add(b)
        readers[b].append(a)
    waiting = {k: len(reads[k]) for k in range(n)}
    ready = sorted(k for k in range(n) if waiting[k] == 0)
    out: list[int] = []
    while ready:
        last = out[-1] if out else None
        follow = [k for k in ready if last is not None and last in reads[k]]
        k = min(follow) if follow else ready[0]
        ready.remove(k)
        out.append(k)
        for r in readers[k]:
            waiting[r] -= 1
            if waiting[r] == 0:
                ready.append(r)
        ready.sort()
    return out if len(out) == n else None


def block_order(n: int, edges: set[tuple[int, int]]) -> list[int]:
    """An order of ``n`` blocks with a small total edge length ``Σ |pos(a) - pos(b)|`` (minimum linear arrangement).

    Exhaustive for ``n <= 8``; otherwise local search (pairwise swaps, first improvement) from the given order,
    its reverse and breadth-first orders, keeping the best; ties keep the given order. Why: in the
    ``interleaved`` variable order the blocks of coupled subsystems should sit close. Used where the couplings
    have a cycle; acyclic networks get :func:`reader_order`, which measured better on the 10 tanks. Measured on
    the 10 tanks (six safety iterations, machine shared): network order (length 26) 15.0 s, four optimal orders
    (length 22) 3.7-5.0 s, two length-31 orders 4.5 and 15.5 s, a length-25 order 68 s; over the whole safety
    fixed point the reader order (length 31) took 33 s against 58 s for the optimal 0,1,2,7,9,8,5,3,4,6.
    """
    import itertools

    E = np.array(sorted(edges), dtype=np.int64).reshape(-1, 2)
    if n <= 1 or E.shape[0] == 0:
        return list(range(n))

    def cost(order: Sequence[int]) -> int:
        pos = np.empty(n, dtype=np.int64)
        pos[np.asarray(order)] = np.arange(n)
        return int(np.abs(pos[E[:, 0]] - pos[E[:, 1]]).sum())

    if n <= 8:
        return list(min(itertools.permutations(range(n)), key=cost))
    if E.shape[0] * n * n > 50_000_000:  # dense coupling: no order helps much, and the search would take minutes
        return list(range(n))
    adj: dict[int, list[int]] = {k: [] for k in range(n)}
    for a, b in E.tolist():
        adj[a].append(b)
        adj[b].append(a)

    def bfs(start: int) -> list[int]:
        out, seen = [], set()
        for root in [start, *range(n)]:
            if root in seen:
                continue
            queue, seen = [root], seen | {root}
            while queue:
                v = queue.pop(0)
                out.append(v)
                for w in sorted(adj[v], key=lambda t: len(adj[t])):
                    if w not in seen:
                        seen.add(w)
                        queue.append(w)
        return out

    starts = [list(range(n)), list(range(n))[::-1]]
    starts += [bfs(v) for v in sorted(range(n), key=lambda v: len(adj[v]))[: min(n, 4)]]
    best, best_cost = list(range(n)), cost(range(n))
    for order in starts:
        c = cost(order)
        improved = True
        while improved:
            improved = False
            for a in range(n):
                for b in range(a + 1, n):
                    order[a], order[b] = order[b], order[a]
                    c2 = cost(order)
                    if c2 < c:
                        c, improved = c2, True
                    else:
                        order[a], order[b] = order[b], order[a]
        if c < best_cost:
            best, best_cost = list(order), c
    return best


def tree_owners(nodes: Sequence["NodeRelation"]) -> dict[str, int]:
    """The output ``j`` whose MDec tree each intermediate ``z`` belongs to (follows the unique reader)."""
    reader = {name: node.output for node in nodes for name in node.inputs if name.startswith("z")}
    owners: dict[str, int] = {}
    for node in nodes:
        if node.output.startswith("z"):
            out, seen = node.output, set()
            while out.startswith("z") and out in reader and out not in seen:
                seen.add(out)
                out = reader[out]
            if out.startswith("w"):
                owners[node.output] = int(out[1:])
    return owners


class SymbolicModel:
    """One CUDD manager with the variables of a network declared on purpose (Algorithm 5).

    Parameters
    ----------
    subsystems : sequence of SubsystemLayout
        In network order; their coordinates must tile ``0 .. n-1``.
    w_sizes : sequence of int, length p
        Cells of each internal variable's grid.
    z_sizes : mapping of str to int, optional
        Cells of each intermediate variable's grid, in topological (node) order.
    z_owner : mapping of str to int, optional
        Output ``j`` whose tree each ``z`` belongs to (placement in the ``interleaved`` order).
    order : {'interleaved', 'shared_top'}
    max_memory : int, optional
        Bytes CUDD may use (default :func:`default_max_memory`); beyond it operations raise
        :class:`BDDMemoryError`.
    grids : dict, optional
        JSON-ready grid descriptions, only carried into controller headers.
    blocks : sequence of int, optional
        Order of the subsystems' blocks in the variable order (positions in ``subsystems``; default network
        order). :meth:`from_network` chooses it for the ``interleaved`` order: :func:`reader_order` when the
        couplings are acyclic, else :func:`block_order`.
    """

    def __init__(
        self,
        subsystems: Sequence[SubsystemLayout],
        w_sizes: Sequence[int],
        z_sizes: Mapping[str, int] | None = None,
        *,
        z_owner: Mapping[str, int] | None = None,
        order: str = "interleaved",
        max_memory: int | None = None,
        grids: dict | None = None,
        blocks: Sequence[int] | None = None,
    ) -> None:
        if order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
        self.subsystems = tuple(subsystems)
        self.blocks = tuple(int(b) for b in blocks) if blocks is not None else tuple(range(len(self.subsystems)))
        if sorted(self.blocks) != list(range(len(self.subsystems))):
            raise ValueError(f"blocks {list(self.blocks)} is not a permutation of the {len(self.subsystems)} subsystems")
        self.w_sizes = tuple(int(k) for k in w_sizes)
        self.z_sizes = {str(k): int(v) for k, v in (z_sizes or {}).items()}
        self.z_owner = {str(k): int(v) for k, v in (z_owner or {}).items()}
        self.order = order
        self.grids = grids or {}
        self.max_memory = int(max_memory) if max_memory is not None else default_max_memory()
        self.state_sizes = self._state_sizes()
        self.sizes: dict[str, int] = {}
        for i, k in enumerate(self.state_sizes):
            self.sizes[f"x{i}"] = k
            self.sizes[f"xn{i}"] = k
        for s in self.subsystems:
            self.sizes[f"u{s.index}"] = s.n_inputs
        for j, k in enumerate(self.w_sizes):
            self.sizes[f"w{j}"] = k
        self.sizes.update(self.z_sizes)
        self.bits: dict[str, tuple[str, ...]] = {
            d: tuple(f"{d}_{b}" for b in range(bit_width(k))) for d, k in self.sizes.items()
        }
        self.bdd = cudd.BDD()
        self.bdd.configure(reordering=False, max_memory=self.max_memory, loose_up_to=GC_LOOSE_UP_TO,
                           max_cache_hard=MAX_CACHE_ENTRIES)
        self.variables = self._variable_order()
        self._declare(self.variables)
        self._vars = {name: self.bdd.var(name) for name in self.variables}
        self._x_to_xn = dict(zip(self.x_bits, self.xn_bits))
        self._xn_set = frozenset(self.xn_bits)
        self._interval_memo: dict[tuple[str, int, int], Function] = {}
        self._bound_memo: dict[tuple[str, str, int], Function] = {}
        self._domain_memo: dict[tuple[str, ...], Function] = {}
        self.build_seconds: dict[str, float] = {}

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_network(
        cls,
        network: "Network",
        interconnection: "InterconnectionAbstraction | None" = None,
        *,
        order: str = "interleaved",
        max_memory: int | None = None,
    ) -> "SymbolicModel":
        """A model for a network and (optionally) its interconnection abstraction's intermediate variables."""
        nodes = interconnection.nodes if interconnection is not None else ()
        layouts = [SubsystemLayout.of(s) for s in network.subsystems]
        blocks = None
        if order == "interleaved":
            arcs = dependency_arcs(layouts, nodes)
            blocks = reader_order(len(layouts), arcs)
            if blocks is None:  # cyclic couplings: no block can sit below all it reads
                blocks = block_order(len(layouts), {(min(a, b), max(a, b)) for a, b in arcs})
        z_sizes = {n.output: n.output_grid.size for n in nodes if n.output.startswith("z")}
        grids = {
            "state": [s.state_grid.describe() for s in network.subsystems],
            "input": [s.input_grid.describe() for s in network.subsystems],
            "internal": [g.describe() for g in network.internal_grids],
            "intermediate": {n.output: n.output_grid.describe() for n in nodes if n.output.startswith("z")},
        }
        return cls(
            layouts,
            [g.size for g in network.internal_grids],
            z_sizes,
            z_owner=tree_owners(nodes),
            order=order,
            max_memory=max_memory,
            grids=grids,
            blocks=blocks,
        )

    def _state_sizes(self) -> list[int]:
        sizes: dict[int, int] = {}
        for s in self.subsystems:
            for i, k in zip(s.coords, s.state_shape):
                if i in sizes:
                    raise ValueError(f"composed-state coordinate {i} belongs to two subsystems")
                sizes[i] = int(k)
        if sorted(sizes) != list(range(len(sizes))):
            raise ValueError(f"subsystem coordinates {sorted(sizes)} do not tile 0 .. n-1")
        return [sizes[i] for i in range(len(sizes))]

    def _variable_order(self) -> list[str]:
        """Bit names in level order (top first) for the chosen order (see the module docstring)."""
        out: list[str] = []
        placed: set[str] = set()

        def put(digit: str) -> None:
            if digit not in placed:
                placed.add(digit)
                out.extend(self.bits[digit])

        def put_w(j: int) -> None:
            # The z of w_j's tree right above w_j: M̂_j's nodes then sit together.
            for z in self.z_sizes:
                if self.z_owner.get(z) == j:
                    put(z)
            put(f"w{j}")

        if self.order == "shared_top":
            for j in range(len(self.w_sizes)):
                put(f"w{j}")
            for z in self.z_sizes:
                put(z)
            for s in (self.subsystems[b] for b in self.blocks):
                for i in s.coords:
                    put(f"x{i}")
                put(f"u{s.index}")
                for i in s.coords:
                    put(f"xn{i}")
            return out
        read = {j for s in self.subsystems for j in s.reads}
        for z in self.z_sizes:  # intermediate variables of unread outputs, or of unknown owner
            if self.z_owner.get(z) not in read:
                put(z)
        for j in range(len(self.w_sizes)):
            if j not in read:
                put(f"w{j}")
        for s in (self.subsystems[b] for b in self.blocks):
            for j in s.reads:
                put_w(j)
            put(f"u{s.index}")
            for i in s.coords:
                placed.update((f"x{i}", f"xn{i}"))
                for a, b in zip(self.bits[f"x{i}"], self.bits[f"xn{i}"]):
                    out.extend((a, b))
        return out

    def _declare(self, names: Sequence[str]) -> None:
        """Declare in level order: with reordering off a new variable goes to the bottom level."""
        if len(set(names)) != len(names):
            raise ValueError("a variable is declared twice")
        self.bdd.declare(*names)
        for level, name in enumerate(names):
            if self.bdd.level_of_var(name) != level:
                raise RuntimeError(f"variable {name} at level {self.bdd.level_of_var(name)}, expected {level}")

    @contextlib.contextmanager
    def guard(self, what: str) -> Iterator[None]:
        """Turn CUDD's out-of-memory ``NULL`` results into a :class:`BDDMemoryError` naming the operation."""
        try:
            yield
        except (ValueError, RuntimeError) as exc:
            text = str(exc)
            if "NULL" in text or "out of memory" in text:
                raise BDDMemoryError(
                    f"CUDD ran out of memory while {what}: max_memory = {self.max_memory / 2**30:.2f} GiB, "
                    f"{len(self.bdd)} live nodes. Raise max_memory, use coarser grids, or try the other "
                    f"variable order (now '{self.order}')."
                ) from exc
            raise

    # ------------------------------------------------------------------ digits and bits
    def x_digits(self) -> list[str]:
        return [f"x{i}" for i in range(len(self.state_sizes))]

    def xn_digits(self) -> list[str]:
        return [f"xn{i}" for i in range(len(self.state_sizes))]

    def u_digits(self) -> list[str]:
        return [f"u{s.index}" for s in self.subsystems]

    def w_digits(self) -> list[str]:
        return [f"w{j}" for j in range(len(self.w_sizes))]

    def bits_of(self, digits: Sequence[str]) -> list[str]:
        """All bits of the digits, digit by digit, most significant first."""
        return [b for d in digits for b in self.bits[d]]

    def subsystem_digits(self, s: SubsystemLayout) -> dict[str, list[str]]:
        """Digits of one subsystem: ``x``, ``xn``, ``u``, ``w``."""
        return {
            "x": [f"x{i}" for i in s.coords],
            "xn": [f"xn{i}" for i in s.coords],
            "u": [f"u{s.index}"],
            "w": [f"w{j}" for j in s.reads],
        }

    @property
    def x_bits(self) -> list[str]:
        return self.bits_of(self.x_digits())

    @property
    def xn_bits(self) -> list[str]:
        return self.bits_of(self.xn_digits())

    @property
    def u_bits(self) -> list[str]:
        return self.bits_of(self.u_digits())

    @property
    def w_bits(self) -> list[str]:
        return self.bits_of(self.w_digits())

    @property
    def z_bits(self) -> list[str]:
        return self.bits_of(list(self.z_sizes))

    def var(self, name: str) -> Function:
        return self._vars[name]

    # ------------------------------------------------------------------ comparators and domains
    def _bound(self, digit: str, kind: str, k: int) -> Function:
        """``code(digit) <= k`` (``kind = 'le'``) or ``>= k`` (``'ge'``), built over the bits from the LSB up."""
        key = (digit, kind, k)
        f = self._bound_memo.get(key)
        if f is not None:
            return f
        bits = self.bits[digit]
        m = len(bits)
        if kind == "le" and k >= (1 << m) - 1 or kind == "ge" and k <= 0:
            f = self.bdd.true
        elif kind == "le" and k < 0 or kind == "ge" and k >= 1 << m:
            f = self.bdd.false
        else:
            f = self.bdd.true  # the empty suffix compares equal
            for pos in range(m - 1, -1, -1):
                v = self._vars[bits[pos]]
                one = (k >> (m - 1 - pos)) & 1
                if kind == "le":
                    f = (~v | f) if one else (~v & f)
                else:
                    f = (v & f) if one else (v | f)
        self._bound_memo[key] = f
        return f

    def interval(self, digit: str, lo: int, hi: int) -> Function:
        """``lo <= code(digit) <= hi`` (memoised; ``False`` when ``lo > hi``)."""
        lo, hi = int(lo), int(hi)
        key = (digit, lo, hi)
        f = self._interval_memo.get(key)
        if f is None:
            f = self.bdd.false if lo > hi else self._bound(digit, "ge", lo) & self._bound(digit, "le", hi)
            self._interval_memo[key] = f
        return f

    def domain(self, digits: Sequence[str]) -> Function:
        """Domain constraint: every digit's code is a cell (``code < K``)."""
        key = tuple(digits)
        f = self._domain_memo.get(key)
        if f is None:
            f = self.bdd.true
            for d in digits:
                f &= self._bound(d, "le", self.sizes[d] - 1)
            self._domain_memo[key] = f
        return f

    @property
    def x_domain(self) -> Function:
        return self.domain(self.x_digits())

    @property
    def u_domain(self) -> Function:
        return self.domain(self.u_digits())

    # ------------------------------------------------------------------ bulk construction
    def tree(
        self,
        digits: Sequence[str],
        values: np.ndarray,
        leaf_ids: np.ndarray,
        leaves: Sequence[Function],
    ) -> Function:
        """``∨_r (digits = values[r]) ∧ leaves[leaf_ids[r]]`` as a Shannon tree built bottom-up in bulk.

        Parameters
        ----------
        digits : sequence of str, length D
            The tree's branching digits (their bits may be interleaved with the leaves' variables; ``ite``
            handles any order).
        values : ndarray of int, shape (N, D)
            Distinct cells (codes per digit). Codes absent from ``values`` map to ``False``.
        leaf_ids : ndarray of int, shape (N,)
            Index into ``leaves`` per cell.
        leaves : sequence of Function
            Leaf functions (over variables other than the tree's bits).

        Notes
        -----
        Per bit, from the bottom level up, siblings are paired; one ``ite`` is made per distinct
        ``(low, high)`` pair of subtree ids, so Python work is proportional to the distinct subtrees.
        """
        values = np.asarray(values, dtype=np.int64).reshape(len(leaf_ids), len(digits))
        leaf_ids = np.asarray(leaf_ids, dtype=np.int64)
        funcs: list[Function] = [self.bdd.false]
        ident: dict[int, int] = {int(self.bdd.false): 0}

        def intern(f: Function) -> int:
            # Equal functions get equal ids, so subtrees that CUDD finds equal pair up as equal.
            k = int(f)
            i = ident.get(k)
            if i is None:
                i = ident[k] = len(funcs)
                funcs.append(f)
            return i

        leaf_map = np.array([intern(f) for f in leaves], dtype=np.int64)
        ids = leaf_map[leaf_ids] if leaf_ids.size else leaf_ids
        keep = ids != 0  # absent codes are False already
        ids, values = ids[keep], values[keep]
        if ids.size == 0:
            return self.bdd.false
        names: list[str] = []
        for d, digit in enumerate(digits):
            m = len(self.bits[digit])
            if values[:, d].min() < 0 or values[:, d].max() >= 1 << m:
                raise ValueError(f"codes of digit {digit} outside 0 .. {(1 << m) - 1}")
            names.extend(self.bits[digit])
        B = len(names)
        if B > MAX_TREE_BITS:
            raise ValueError(f"a relation over {B} bits exceeds the {MAX_TREE_BITS}-bit tree keys")
        names.sort(key=self.bdd.level_of_var)
        shift = {name: B - 1 - k for k, name in enumerate(names)}  # key bit of each variable (top = MSB)
        keys = np.zeros(ids.size, dtype=np.int64)
        for d, digit in enumerate(digits):
            # One lookup table per digit scatters its code's bits to their key positions (bits of different
            # digits may interleave in level order).
            bits = self.bits[digit]
            m = len(bits)
            codes = np.arange(1 << m, dtype=np.int64)
            table = np.zeros(1 << m, dtype=np.int64)
            for b, name in enumerate(bits):
                table |= ((codes >> (m - 1 - b)) & 1) << shift[name]
            keys |= table[values[:, d]]
        if not np.all(keys[1:] > keys[:-1]):  # often sorted already (row-major cells, digit-major order)
            srt = np.argsort(keys, kind="stable")
            keys, ids = keys[srt], ids[srt]
            if np.any(keys[1:] == keys[:-1]):
                raise ValueError("tree(): repeated cell in values")
        ite = self.bdd.ite
        for level in range(B - 1, -1, -1):
            var = self._vars[names[level]]
            parent = keys >> 1
            first = np.ones(parent.size, dtype=bool)
            first[1:] = parent[1:] != parent[:-1]
            # Keys are sorted, so a parent's one or two rows are adjacent, the 0-child first.
            starts = np.flatnonzero(first)
            ends = np.empty_like(starts)
            ends[:-1] = starts[1:] - 1
            ends[-1] = keys.size - 1
            low = np.where((keys[starts] & 1) == 0, ids[starts], 0)
            high = np.where((keys[ends] & 1) == 1, ids[ends], 0)
            M = len(funcs)
            pairs, inverse = factorize(low * M + high, M * M)
            made = np.empty(pairs.size, dtype=np.int64)
            for q, pair in enumerate(pairs.tolist()):
                lo_id, hi_id = divmod(pair, M)
                made[q] = lo_id if lo_id == hi_id else intern(ite(var, funcs[hi_id], funcs[lo_id]))
            ids = made[inverse.ravel()]
            keys = parent[starts]
        return funcs[int(ids[0])]

    def range_leaves(
        self, out_digits: Sequence[str], lo: np.ndarray, hi: np.ndarray, empty: np.ndarray | None = None
    ) -> tuple[np.ndarray, list[Function]]:
        """Leaf ids and leaf functions for per-cell output ranges (grouping equal ranges).

        Parameters
        ----------
        out_digits : sequence of str, length k
        lo, hi : ndarray of int, shape (N, k)
            Inclusive range per output digit; a row with ``lo > hi`` in any digit is empty.
        empty : ndarray of bool, shape (N,), optional
            Rows forced empty (blocking triples).

        Returns
        -------
        leaf_ids : ndarray of int64, shape (N,)
            0 for empty rows.
        leaves : list of Function
            ``leaves[0]`` is ``False``; the others are ``∧_d lo_d <= code(out_d) <= hi_d``.
        """
        lo = np.asarray(lo, dtype=np.int64).reshape(-1, len(out_digits))
        hi = np.asarray(hi, dtype=np.int64).reshape(-1, len(out_digits))
        dead = np.any(lo > hi, axis=1)
        if empty is not None:
            dead |= np.asarray(empty, dtype=bool).reshape(-1)
        leaf_ids = np.zeros(lo.shape[0], dtype=np.int64)
        leaves: list[Function] = [self.bdd.false]
        live = np.flatnonzero(~dead)
        if live.size == 0:
            return leaf_ids, leaves
        rows = np.concatenate([lo[live], hi[live]], axis=1)
        uniq, inverse = unique_rows(rows)
        k = len(out_digits)
        for row in uniq.tolist():
            f = self.bdd.true
            for d, digit in enumerate(out_digits):
                f &= self.interval(digit, row[d], row[k + d])
            leaves.append(f)
        leaf_ids[live] = inverse + 1
        return leaf_ids, leaves

    def state_set(self, x_idx: np.ndarray) -> Function:
        """The set of composed states given by per-coordinate indices, shape (B, n) (bulk, as a tree)."""
        x_idx = np.unique(np.asarray(x_idx, dtype=np.int64).reshape(-1, len(self.state_sizes)), axis=0)
        return self.tree(self.x_digits(), x_idx, np.ones(x_idx.shape[0], dtype=np.int64),
                         [self.bdd.false, self.bdd.true])

    def pair_set(self, x_idx: np.ndarray, u_idx: np.ndarray) -> Function:
        """A set of (state, joint input) pairs: x shape (B, n), per-subsystem flat inputs shape (B, N)."""
        vals = np.concatenate([np.asarray(x_idx, np.int64), np.asarray(u_idx, np.int64)], axis=1)
        vals = np.unique(vals, axis=0)
        return self.tree(self.x_digits() + self.u_digits(), vals, np.ones(vals.shape[0], dtype=np.int64),
                         [self.bdd.false, self.bdd.true])

    # ------------------------------------------------------------------ subsystem relations
    def subsystem_relation(self, s: SubsystemLayout, rel: "SubsystemRelation") -> tuple[Function, Function]:
        """``T_s(x_s, u_s, w_s, x'_s)`` over non-blocking triples and ``NB_s(x_s, u_s, w_s)`` (Def. 4.2).

        Parameters
        ----------
        s : SubsystemLayout
        rel : SubsystemRelation
            ``lo``, ``hi`` shape (n_x, n_u, n_w, n); ``blocking`` shape (n_x, n_u, n_w).
        """
        n_x, n_u, n_w = rel.blocking.shape
        w_shape = tuple(self.w_sizes[j] for j in s.reads) or (1,)
        if n_x != math.prod(s.state_shape) or n_u != s.n_inputs or n_w != math.prod(w_shape):
            raise ValueError(
                f"relation of shape {rel.blocking.shape} does not fit subsystem {s.index} "
                f"(states {s.state_shape}, inputs {s.n_inputs}, internal {w_shape})"
            )
        t0 = time.perf_counter()
        dg = self.subsystem_digits(s)
        N = n_x * n_u * n_w
        xi, ui, wi = np.unravel_index(np.arange(N, dtype=np.int64), (n_x, n_u, n_w))
        cols = list(np.unravel_index(xi, s.state_shape)) + [ui]
        if s.reads:
            cols += list(np.unravel_index(wi, w_shape))
        values = np.stack(cols, axis=1)
        digits = dg["x"] + dg["u"] + dg["w"]
        blocking = rel.blocking.reshape(N)
        with self.guard(f"building the relation of subsystem {s.index}"):
            ids, leaves = self.range_leaves(dg["xn"], rel.lo.reshape(N, -1), rel.hi.reshape(N, -1), blocking)
            T = self.tree(digits, values, ids, leaves)
            NB = self.tree(digits, values, (~blocking).astype(np.int64), [self.bdd.false, self.bdd.true])
        self.build_seconds[f"T{s.index}"] = time.perf_counter() - t0
        return T, NB

    def renaming(self, src: SubsystemLayout, dst: SubsystemLayout) -> dict[str, str]:
        """Bit renaming that maps the variables of ``src`` to those of ``dst`` (identical subsystems)."""
        a, b = self.subsystem_digits(src), self.subsystem_digits(dst)
        out: dict[str, str] = {}
        for kind in ("x", "xn", "u", "w"):
            if len(a[kind]) != len(b[kind]):
                raise ValueError(f"subsystems {src.index} and {dst.index} differ in their {kind} digits")
            for da, db in zip(a[kind], b[kind]):
                if len(self.bits[da]) != len(self.bits[db]):
                    raise ValueError(f"digits {da} and {db} differ in width")
                out.update({p: q for p, q in zip(self.bits[da], self.bits[db]) if p != q})
        return out

    def subsystem_relations(
        self, relations: Mapping[str, "SubsystemRelation"], share: str = "rename"
    ) -> tuple[list[Function], list[Function]]:
        """``T_i`` and ``NB_i`` of every subsystem, in network order.

        Parameters
        ----------
        relations : mapping of key to SubsystemRelation
        share : {'rename', 'build'}
            Identical subsystems share arrays; ``'rename'`` builds the BDDs of the first member and renames
            them (``let``) for the others, ``'build'`` builds each from the arrays.
        """
        first: dict[str, tuple[SubsystemLayout, Function, Function]] = {}
        T: list[Function] = []
        NB: list[Function] = []
        for s in self.subsystems:
            if share == "rename" and s.key in first:
                t0 = time.perf_counter()
                src, t, nb = first[s.key]
                ren = self.renaming(src, s)
                with self.guard(f"renaming the relation of subsystem {src.index} to {s.index}"):
                    t, nb = (self.bdd.let(ren, t), self.bdd.let(ren, nb)) if ren else (t, nb)
                self.build_seconds[f"T{s.index}"] = time.perf_counter() - t0
            else:
                t, nb = self.subsystem_relation(s, relations[s.key])
                first.setdefault(s.key, (s, t, nb))
            T.append(t)
            NB.append(nb)
        return T, NB

    # ------------------------------------------------------------------ interconnection
    def node_relation(self, node: "NodeRelation") -> Function:
        """``R_node(inputs, output)``: the output cell lies in the node's range for the input cell."""
        for name, g in zip(node.inputs, node.input_grids):
            if self.sizes.get(name) != g.size:
                raise ValueError(f"node {node.output}: input {name} has {g.size} cells, the model {self.sizes.get(name)}")
        if self.sizes.get(node.output) != node.output_grid.size:
            raise ValueError(f"node {node.output}: output grid does not match the model")
        shape = node.lo.shape
        N = int(np.prod(shape, dtype=np.int64))
        ids, leaves = self.range_leaves([node.output], node.lo.reshape(N, 1), node.hi.reshape(N, 1))
        if not node.inputs:
            return leaves[int(ids[0])]
        values = np.stack(np.unravel_index(np.arange(N, dtype=np.int64), shape), axis=1)
        return self.tree(list(node.inputs), values, ids, leaves)

    def interconnection_parts(self, nodes: Sequence["NodeRelation"]) -> dict[int, Function]:
        """``M̂_j(x, w_j) = ∃z. ∧ R_node`` over the nodes of output ``j``'s tree (Sec. 4.2, Theorem 4.7).

        Nodes are grouped by the ``z`` they share (MDec's forest has one tree per output); within a group they
        are conjoined in the given (topological) order and each ``z`` is quantified as soon as no remaining node
        mentions it (early quantification).
        """
        t0 = time.perf_counter()
        groups: dict[int, list["NodeRelation"]] = {}
        owners = tree_owners(nodes)
        for node in nodes:
            j = int(node.output[1:]) if node.output.startswith("w") else owners.get(node.output)
            if j is None:
                raise ValueError(f"intermediate {node.output} feeds no internal variable")
            groups.setdefault(j, []).append(node)
        parts: dict[int, Function] = {}
        with self.guard("building the interconnection relation"):
            for j, group in groups.items():
                last: dict[str, int] = {}
                for k, node in enumerate(group):
                    for name in (node.output, *node.inputs):
                        if name.startswith("z"):
                            last[name] = k
                acc = self.bdd.true
                for k, node in enumerate(group):
                    dead = [z for z, kk in last.items() if kk == k]
                    acc = cudd.and_exists(acc, self.node_relation(node), self.bits_of(dead))
                parts[j] = acc
        missing = set(range(len(self.w_sizes))) - set(parts)
        if missing:
            raise ValueError(f"no node produces w{sorted(missing)}")
        self.build_seconds["interconnection"] = time.perf_counter() - t0
        return parts

    def interconnection(self, nodes: Sequence["NodeRelation"]) -> Function:
        """``M̂(x, w) = ∧_j M̂_j`` (each part with its ``z`` quantified).

        Only the shared-``w`` CPre needs this conjunction. Where each ``w_j`` has one reader keep the parts
        (METHOD §5: never build what the partitioned form makes unnecessary): for the 10 tanks in the interleaved
        order the conjunction has 25 M nodes and takes 57 s, the parts 59 k nodes in all and 1.3 s.
        """
        f = self.bdd.true
        with self.guard("conjoining the interconnection relation"):
            for part in self.interconnection_parts(nodes).values():
                f &= part
        return f

    # ------------------------------------------------------------------ regions
    def region(self, region: "AbstractRegion") -> Function:
        """A union of index boxes as a BDD over the current-state bits (box = ∧ per-coordinate intervals)."""
        f = self.bdd.false
        for first, last in region.boxes:
            box = self.bdd.true
            for i, (a, b) in enumerate(zip(np.asarray(first).tolist(), np.asarray(last).tolist())):
                box &= self.interval(f"x{i}", max(0, a), min(b, self.state_sizes[i] - 1))
            f |= box
        return f

    # ------------------------------------------------------------------ renaming and counting
    def to_next(self, f: Function) -> Function:
        """``f(x) -> f(x')`` for ``f`` over current-state bits (and any others but next-state bits).

        A swap of the two sets of bits (``Cudd_bddSwapVariables``, a permutation) instead of ``let`` (vector
        compose): the same function when ``f`` does not read next-state bits, in half the time (tanks safety loop:
        2.6 s -> 1.2 s of renaming). ``f`` reading next-state bits is a caller's error, since those would move to
        the current-state bits.
        """
        if not self._xn_set.isdisjoint(self.bdd.support(f)):
            raise ValueError("to_next: the BDD already reads next-state bits")
        return self.bdd._swap(f, self._x_to_xn)

    def count(self, f: Function, digits: Sequence[str]) -> int:
        """Exact number of cells of ``digits`` in ``f`` (domain constraint applied; support must be inside)."""
        bits = self.bits_of(digits)
        extra = self.bdd.support(f) - set(bits)
        if extra:
            raise ValueError(f"count over {list(digits)}: the BDD also depends on {sorted(extra)[:6]}")
        return self._exact_count(f & self.domain(digits), bits)

    def count_states(self, f: Function) -> int:
        """Exact number of composed abstract states in a BDD over the current-state bits."""
        return self.count(f, self.x_digits())

    def _count_table(self, f: Function, bits: Sequence[str]):
        """Exact model counts of every node below ``f`` over ``bits`` (Python integers; CUDD's count is a
        double, inexact above 2**53). Returns ``count(g)``: the assignments of the bits from ``g``'s level down
        that satisfy ``g``, and ``position(g)``: the index of ``g``'s level among ``bits`` (``len(bits)`` for a
        constant)."""
        levels = sorted(self.bdd.level_of_var(b) for b in bits)
        pos = {lvl: k for k, lvl in enumerate(levels)}
        N = len(levels)

        def regular(g: Function) -> Function:
            return ~g if g.negated else g

        def position(g: Function) -> int:
            return N if g.var is None else pos[g.level]

        memo: dict[int, int] = {}
        stack = [regular(f)]
        while stack:
            g = stack[-1]
            key = int(g)
            if key in memo:
                stack.pop()
                continue
            if g.var is None:  # the regular constant is TRUE in CUDD
                memo[key] = 1
                stack.pop()
                continue
            kids = (g.low, g.high)
            regs = [regular(c) for c in kids]
            todo = [r for r in regs if int(r) not in memo]
            if todo:
                stack.extend(todo)
                continue
            p = position(g)
            total = 0
            for c, r in zip(kids, regs):
                q = position(r)
                n = memo[int(r)]
                if c.negated:
                    n = (1 << (N - q)) - n
                total += n << (q - p - 1)
            memo[key] = total
            stack.pop()

        def count(g: Function) -> int:
            r = regular(g)
            n = memo[int(r)]
            return (1 << (N - position(r))) - n if g.negated else n

        return count, position, N

    def _exact_count(self, f: Function, bits: Sequence[str]) -> int:
        """Model count over ``bits`` with Python integers (CUDD's count is a double: inexact above 2**53)."""
        count, position, N = self._count_table(f, bits)
        return count(f) << position(f)

    def sample(self, f: Function, digits: Sequence[str], rng: np.random.Generator | None, size: int | None = None):
        """Cells of ``digits`` in ``f``, uniformly at random (``rng``) or the smallest (``rng=None``).

        ``self.sampler(f, digits).draw(rng, size)``: see :class:`Sampler`. Returns codes, shape (len(digits),)
        (``size=None``) or (size, len(digits)); ``None`` / shape (0, ...) if ``f`` is empty on the valid codes.
        """
        return self.sampler(f, digits).draw(rng, size)

    def sampler(self, f: Function, digits: Sequence[str]) -> "Sampler":
        """A :class:`Sampler` of the cells of ``digits`` in ``f`` (``f`` must read no other bits)."""
        bits = list(self.bits_of(digits))
        extra = self.bdd.support(f) - set(bits)
        if extra:
            raise ValueError(f"sample over {list(digits)}: the BDD also depends on {sorted(extra)[:6]}")
        f = f & self.domain(digits)
        if f == self.bdd.false:
            return Sampler(f, None, [len(self.bits[d]) for d in digits], [])
        table = self._count_table(f, bits)
        by_level = sorted(bits, key=self.bdd.level_of_var)
        col = {b: j for j, b in enumerate(by_level)}
        return Sampler(f, table, [len(self.bits[d]) for d in digits], [col[b] for d in digits for b in self.bits[d]])

    def enumerate(self, f: Function, digits: Sequence[str]) -> np.ndarray:
        """Every cell of ``digits`` in ``f`` as an array of codes, shape (B, len(digits)). Small sets only."""
        bits = self.bits_of(digits)
        extra = self.bdd.support(f) - set(bits)
        if extra:
            raise ValueError(f"enumerate over {list(digits)}: the BDD also depends on {sorted(extra)[:6]}")
        rows = []
        for a in self.bdd.pick_iter(f & self.domain(digits), care_vars=set(bits)):
            rows.append([sum(int(a[b]) << (len(self.bits[d]) - 1 - k) for k, b in enumerate(self.bits[d]))
                         for d in digits])
        out = np.array(rows, dtype=np.int64).reshape(-1, len(digits))
        return out[np.lexsort(out.T[::-1])] if out.size else out

    def state_assignment(self, x_idx: Sequence[int]) -> dict[str, bool]:
        """Values of the current-state bits encoding composed cell indices ``x_idx`` (MSB first)."""
        assign: dict[str, bool] = {}
        for i, v in enumerate(x_idx):
            bits = self.bits[f"x{i}"]
            for k, b in enumerate(bits):
                assign[b] = bool((int(v) >> (len(bits) - 1 - k)) & 1)
        return assign

    def inputs_at(self, controller: Function, x_idx: Sequence[int]) -> np.ndarray:
        """Joint inputs (per-subsystem flat indices, shape (k, N)) the controller allows at one state."""
        return self.enumerate(self.bdd.let(self.state_assignment(x_idx), controller), self.u_digits())

    # ------------------------------------------------------------------ persistence (DDDMP + JSON header)
    def header(self) -> dict[str, Any]:
        return {
            "format": HEADER_FORMAT,
            "order": self.order,
            "variables": list(self.variables),
            "bit_widths": {d: len(b) for d, b in self.bits.items()},
            "sizes": dict(self.sizes),
            "subsystems": [asdict(s) for s in self.subsystems],
            "w_sizes": list(self.w_sizes),
            "z_sizes": dict(self.z_sizes),
            "z_owner": dict(self.z_owner),
            "grids": self.grids,
            "blocks": list(self.blocks),
        }

    @staticmethod
    def _paths(path: str | os.PathLike) -> tuple[Path, Path]:
        p = Path(path)
        if p.suffix.lower() == ".dddmp":
            p = p.with_suffix("")
        return p.with_name(p.name + ".dddmp"), p.with_name(p.name + ".json")

    def dump(self, path: str | os.PathLike, f: Function | Sequence[Function], meta: dict | None = None) -> tuple[Path, ...]:
        """Write ``f`` to ``<path>.dddmp`` and the header to ``<path>.json``; returns the paths written.

        ``f`` may be a list of roots: CUDD's DDDMP writer takes one root per file, so root ``k > 0`` goes to
        ``<path>.<k>.dddmp`` and the header lists the files in order.
        """
        bdd_path, head_path = self._paths(path)
        roots = [f] if isinstance(f, Function) else list(f)
        files = [bdd_path] + [bdd_path.with_name(f"{bdd_path.stem}.{k}.dddmp") for k in range(1, len(roots))]
        with self.guard(f"dumping {bdd_path}"):
            for root, file in zip(roots, files):
                self.bdd.dump(str(file), [root])
        head = self.header()
        head["meta"] = meta or {}
        head["roots"] = [file.name for file in files]
        head_path.write_text(json.dumps(head, indent=1))
        return (*files, head_path)

    @classmethod
    def from_header(cls, head: Mapping[str, Any], max_memory: int | None = None) -> "SymbolicModel":
        """A fresh model with the variables of a header, declared in its level order."""
        if head.get("format") != HEADER_FORMAT:
            raise ValueError(f"not a {HEADER_FORMAT} header: {head.get('format')!r}")
        subs = [SubsystemLayout(**{**s, "state_shape": tuple(s["state_shape"]), "reads": tuple(s["reads"])})
                for s in head["subsystems"]]
        model = cls(subs, head["w_sizes"], head["z_sizes"], z_owner=head["z_owner"], order=head["order"],
                    max_memory=max_memory, grids=head.get("grids"), blocks=head.get("blocks"))
        if model.variables != list(head["variables"]):
            raise ValueError("the header's variable order differs from the one this code declares")
        return model

    @classmethod
    def load_all(cls, path: str | os.PathLike, max_memory: int | None = None) -> tuple["SymbolicModel", list[Function], dict]:
        """Read ``<path>.dddmp`` (and the further roots its header lists) with the header:
        ``(model, roots in dump order, meta)``."""
        bdd_path, head_path = cls._paths(path)
        head = json.loads(head_path.read_text())
        model = cls.from_header(head, max_memory)
        names = head.get("roots", [bdd_path.name])
        roots = []
        with model.guard(f"loading {bdd_path}"):
            for name in names:
                (root,) = model.bdd.load(str(bdd_path.with_name(name)))
                roots.append(root)
        return model, roots, head.get("meta", {})

    @classmethod
    def load(cls, path: str | os.PathLike, max_memory: int | None = None) -> tuple["SymbolicModel", Function, dict]:
        """Read a single-function ``<path>.dddmp`` and its header: ``(model, function, meta)``."""
        model, roots, meta = cls.load_all(path, max_memory)
        if len(roots) != 1:
            raise ValueError(f"{path} holds {len(roots)} functions; use load_all")
        return model, roots[0], meta

    # ------------------------------------------------------------------ reporting
    def stats(self) -> dict[str, Any]:
        """Live and peak node counts (CUDD's peak includes dead nodes not yet collected), memory in bytes."""
        with warnings.catch_warnings():  # dd warns that 'mem' is now in bytes
            warnings.simplefilter("ignore")
            st = self.bdd.statistics()
        return {"live_nodes": len(self.bdd), "peak_nodes": int(st["peak_nodes"]), "variables": len(self.variables),
                "memory_bytes": int(st["mem"])}
