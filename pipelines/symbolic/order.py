"""The variable order of a symbolic model (Algorithm 5; docs/method.md §5: "choose the order on purpose and measure it").

Every grid dimension is a *digit* (``x{i}``, ``xn{i}``, ``u{s}``, ``w{j}``, ``z{k}``; :mod:`.model`), declared in
level order with dynamic reordering off. Two orders:

* ``"interleaved"`` (the tanks, docs/method.md §6): one block per subsystem, blocks in the order :func:`reader_order`
  picks (each below the blocks it reads, chains contiguous) or, for cyclic couplings, :func:`block_order`
  (coupled subsystems close together); in a block first the bits of the internal variables it reads (each
  preceded by the ``z`` of its MDec tree) unless already declared, then its input bits, then current and next
  bits interleaved (``x{i}_0, xn{i}_0, x{i}_1, ...``). Internal variables nobody reads go on top.
* ``"shared_top"`` (consensus, docs/method.md §6): every ``w`` then every ``z`` on top, then per subsystem the blocks
  ``x_i``, ``u_i``, ``x'_i``.

:func:`default_order` picks ``interleaved`` where each internal variable has one reader and ``shared_top``
otherwise, the orders docs/method.md §6 found best for the tanks and consensus.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.interconnection import NodeRelation
    from pipelines.network import Subsystem

ORDERS = ("interleaved", "shared_top")


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
    def of(cls, sub: Subsystem) -> SubsystemLayout:
        return cls(sub.index, tuple(sub.state_grid.shape), sub.input_grid.size, tuple(sub.reads), sub.key,
                   sub.state_offset, sub.name)


def dependency_arcs(layouts: Sequence[SubsystemLayout], nodes: Sequence[NodeRelation]) -> set[tuple[int, int]]:
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

    Why: the iterates of the safety game relate each tank to the tanks upstream of it, which this order keeps
    above it. On the 10 tanks it beat the minimum linear arrangement of :func:`block_order` (about 1.8x) and
    every other topological or non-topological block order tried.
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
    have a cycle; acyclic networks get :func:`reader_order`, which measured better on the 10 tanks (the edge
    length alone predicts the time only roughly).
    """
    E = np.array(sorted(edges), dtype=np.int64).reshape(-1, 2)
    if n <= 1 or E.shape[0] == 0:
        return list(range(n))

    def cost(order: Iterable[int]) -> int:
        pos = np.empty(n, dtype=np.int64)
        pos[list(order)] = np.arange(n)
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
        out: list[int] = []
        seen: set[int] = set()
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


def blocks_below(nodes: Sequence[NodeRelation], subsystems: Sequence[SubsystemLayout]) -> dict[str, list[int]]:
    """Per intermediate ``z``, the subsystems (positions) whose coordinates lie under it in its node tree."""
    owner = {i: k for k, s in enumerate(subsystems) for i in s.coords}
    under: dict[str, set[int]] = {}
    for node in nodes:  # topological order
        if node.output.startswith("z"):
            got: set[int] = set()
            for name in node.inputs:
                got |= {owner[int(name[1:])]} if name.startswith("x") else under.get(name, set())
            under[node.output] = got
    return {z: sorted(v) for z, v in under.items() if v}


def tree_owners(nodes: Sequence[NodeRelation]) -> dict[str, int]:
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



def default_order(subsystems: Sequence[SubsystemLayout] | Sequence[Subsystem]) -> str:
    """``interleaved`` where each internal variable has at most one reader, else ``shared_top`` (docs/method.md §6)."""
    counts: dict[int, int] = {}
    for s in subsystems:
        for j in s.reads:
            counts[j] = counts.get(j, 0) + 1
    return "interleaved" if all(c <= 1 for c in counts.values()) else "shared_top"


def variable_order(
    order: str,
    subsystems: Sequence[SubsystemLayout],
    blocks: Sequence[int],
    bits: Mapping[str, Sequence[str]],
    n_internal: int,
    z_digits: Sequence[str],
    z_owner: Mapping[str, int],
    z_below: Mapping[str, Sequence[int]] | None = None,
) -> list[str]:
    """Bit names in level order (top first) for ``order`` (see the module docstring).

    Parameters
    ----------
    order : {'interleaved', 'shared_top'}
    subsystems : sequence of SubsystemLayout
        In network order.
    blocks : sequence of int
        Order of the subsystems' blocks (positions in ``subsystems``).
    bits : mapping of str to sequence of str
        The bits of every digit, most significant first.
    n_internal : int
        Number of internal variables ``w{j}``.
    z_digits : sequence of str
        The intermediate variables, in topological (node) order.
    z_owner : mapping of str to int
        Output ``j`` whose MDec tree each ``z`` belongs to.
    z_below : mapping of str to sequence of int, optional
        Intermediate variables to place right below the last (in ``blocks`` order) of the given subsystems'
        blocks instead (the reduction trees of :mod:`~pipelines.interconnection.reduction`: a ``z`` below the
        coordinates under it keeps their conjunction a running maximum; above them it would branch on every
        combination of the open subtrees' values).
    """
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
    out: list[str] = []
    placed: set[str] = set()
    rank = {b: r for r, b in enumerate(blocks)}
    below: dict[int, list[str]] = {}
    for z in z_digits:  # topological order: a z's children come before it
        if z_below and z in z_below:
            below.setdefault(max(z_below[z], key=rank.__getitem__), []).append(z)
    z_free = [z for z in z_digits if not (z_below and z in z_below)]

    def put(digit: str) -> None:
        if digit not in placed:
            placed.add(digit)
            out.extend(bits[digit])

    def put_w(j: int) -> None:
        # The z of w_j's tree right above w_j: M̂_j's nodes then sit together.
        for z in z_free:
            if z_owner.get(z) == j:
                put(z)
        put(f"w{j}")

    if order == "shared_top":
        for j in range(n_internal):
            put(f"w{j}")
        for z in z_free:
            put(z)
        for blk in blocks:
            s = subsystems[blk]
            for i in s.coords:
                put(f"x{i}")
            put(f"u{s.index}")
            for i in s.coords:
                put(f"xn{i}")
            for z in below.get(blk, ()):
                put(z)
        return out
    read = {j for s in subsystems for j in s.reads}
    for z in z_free:  # intermediate variables of unread outputs, or of unknown owner
        if z_owner.get(z) not in read:
            put(z)
    for j in range(n_internal):
        if j not in read:
            put(f"w{j}")
    for blk in blocks:
        s = subsystems[blk]
        for j in s.reads:
            put_w(j)
        put(f"u{s.index}")
        for i in s.coords:
            placed.update((f"x{i}", f"xn{i}"))
            for a, b in zip(bits[f"x{i}"], bits[f"xn{i}"]):
                out.extend((a, b))
        for z in below.get(blk, ()):
            put(z)
    return out
