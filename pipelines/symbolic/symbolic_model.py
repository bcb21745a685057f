"""The symbolic model: one CUDD manager and the binary encoding of the abstraction (Algorithm 5; docs/method.md §5).

One :class:`SymbolicModel` owns one CUDD manager (``dd.cudd``) and every BDD built in it: the subsystem
relations ``T_i(x_i, u_i, w_i, x'_i)`` and their non-blocking sets ``NB_i(x_i, u_i, w_i)``, the interconnection
``M̂(x, w) = ∃z. ∧ R_node``, regions, and controllers (:mod:`.relations`). This package is the only place that
imports ``dd``: :data:`Function` and :func:`and_exists` are re-exported for the synthesis.

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
(:meth:`SymbolicModel.domain`). docs/method.md §5 says ``ceil(log2(K+1))`` bits; ``ceil(log2 K)`` is enough for the
codes ``0 .. K-1`` and saves a bit wherever ``K`` is a power of two.

The variables are declared in the level order of :mod:`.order`, dynamic reordering off (ENGINEERING "dd/CUDD").
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from dd import cudd
from dd.cudd import Function, and_exists  # re-exported: the synthesis reaches CUDD through this package only

from pipelines.errors import CompabsError
from pipelines.interconnection.reduction import REDUCTIONS
from pipelines.symbolic.order import (
    ORDERS,
    SubsystemLayout,
    block_order,
    blocks_below,
    dependency_arcs,
    reader_order,
    tree_owners,
    variable_order,
)

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.interconnection import InterconnectionAbstraction
    from pipelines.network import Network

__all__ = ["BDDMemoryError", "Function", "Relational", "SymbolicModel", "and_exists", "bit_width",
           "default_max_memory"]
# Function: a BDD of the manager. and_exists(f, g, bits) = ∃bits. f ∧ g in one CUDD call (Cudd_bddAndAbstract),
# the relational product.


class Relational(Protocol):
    """What the controllable predecessor's products need of a BDD manager (:func:`pipelines.synthesis.cpre.bad_inputs`):
    a :class:`SymbolicModel` (CUDD) or an :class:`~.oxidd_mirror.OxiddMirror` (oxidd, on several threads)."""

    def to_next(self, f: Function) -> Function: ...

    def and_exists(self, f: Function, g: Function, bits: Sequence[str]) -> Function: ...


#: Fraction of physical memory CUDD may use by default (ENGINEERING: set max_memory below the budget).
DEFAULT_MEMORY_FRACTION = 0.75
#: Unique-table slots up to which CUDD keeps its table "loose" (collects garbage only once dead nodes outnumber the
#: slots). CUDD's default (~6.7 M) let the 10 tanks' safety loop leave 8.7 M nodes in the table for at most 0.33 M
#: live ones, so that every lookup missed the processor's caches; with 1e5 the loop is about 20 % faster for the
#: same result, and consensus's peak memory about a third.
GC_LOOSE_UP_TO = 100_000
#: Largest computed table (entries, 32 bytes each) CUDD may grow to. CUDD grows it only while its hit rate is high and
#: to at most 4x the unique table's slots, so a small job keeps a small table (the tanks at spacing 2.5: 2 M entries,
#: with this cap or 2^20). A cap of 2^20 is too small at spacing 1.25 (safety iterates of 1-5 M nodes): the table
#: thrashes and one CPre takes about 6x as long (and_exists recomputes what it has forgotten); CUDD grows the table
#: to 2^24 entries (512 MB) there and no further.
MAX_CACHE_ENTRIES = 1 << 25


class BDDMemoryError(CompabsError):
    """CUDD ran out of the memory it was allowed (``max_memory``)."""


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
    z_below : mapping of str to sequence of int, optional
        Intermediate variables placed below the blocks of these subsystems (reduction trees;
        :func:`~.order.variable_order`).
    order : {'interleaved', 'shared_top'}
    max_memory : int, optional
        Bytes CUDD may use (default :func:`default_max_memory`); beyond it operations raise
        :class:`BDDMemoryError`.
    grids : dict, optional
        JSON-ready grid descriptions, only carried into controller headers.
    blocks : sequence of int, optional
        Order of the subsystems' blocks in the variable order (positions in ``subsystems``; default network
        order). :meth:`from_network` chooses it for the ``interleaved`` order: :func:`~.order.reader_order` when
        the couplings are acyclic, else :func:`~.order.block_order`.
    """

    def __init__(
        self,
        subsystems: Sequence[SubsystemLayout],
        w_sizes: Sequence[int],
        z_sizes: Mapping[str, int] | None = None,
        *,
        z_owner: Mapping[str, int] | None = None,
        z_below: Mapping[str, Sequence[int]] | None = None,
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
        self.z_below = {str(k): [int(b) for b in v] for k, v in (z_below or {}).items()}
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
        network: Network,
        interconnection: InterconnectionAbstraction | None = None,
        *,
        order: str = "interleaved",
        max_memory: int | None = None,
    ) -> SymbolicModel:
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
            z_below=(blocks_below(nodes, layouts)
                     if interconnection is not None and interconnection.mode in REDUCTIONS else None),
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
        """Bit names in level order (top first): :func:`~.order.variable_order` of this model's digits."""
        return variable_order(self.order, self.subsystems, self.blocks, self.bits, len(self.w_sizes),
                              list(self.z_sizes), self.z_owner, self.z_below)

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

    # The bits of each kind of variable (current and next state, inputs, internal variables, intermediate
    # variables), in level order: bits_of over that kind's digits.
    x_bits = property(lambda self: self.bits_of(self.x_digits()))
    xn_bits = property(lambda self: self.bits_of(self.xn_digits()))
    u_bits = property(lambda self: self.bits_of(self.u_digits()))
    w_bits = property(lambda self: self.bits_of(self.w_digits()))
    z_bits = property(lambda self: self.bits_of(list(self.z_sizes)))

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

    @staticmethod
    def and_exists(f: Function, g: Function, bits: Sequence[str]) -> Function:
        """``∃bits. f ∧ g`` (:func:`and_exists`; the :class:`Relational` method)."""
        return and_exists(f, g, list(bits))

    # ------------------------------------------------------------------ renaming and assignments
    def to_next(self, f: Function) -> Function:
        """``f(x) -> f(x')`` for ``f`` over current-state bits (and any others but next-state bits).

        A swap of the two sets of bits (``Cudd_bddSwapVariables``, a permutation) instead of ``let`` (vector
        compose): the same function when ``f`` does not read next-state bits, in half the time. ``f`` reading
        next-state bits is a caller's error, since those would move to the current-state bits.
        """
        if not self._xn_set.isdisjoint(self.bdd.support(f)):
            raise ValueError("to_next: the BDD already reads next-state bits")
        return self.bdd._swap(f, self._x_to_xn)

    def state_assignment(self, x_idx: Sequence[int]) -> dict[str, bool]:
        """Values of the current-state bits encoding composed cell indices ``x_idx`` (MSB first)."""
        assign: dict[str, bool] = {}
        for i, v in enumerate(x_idx):
            bits = self.bits[f"x{i}"]
            for k, b in enumerate(bits):
                assign[b] = bool((int(v) >> (len(bits) - 1 - k)) & 1)
        return assign

    # ------------------------------------------------------------------ reporting
    def stats(self) -> dict[str, Any]:
        """Live and peak node counts (CUDD's peak includes dead nodes not yet collected), memory in bytes."""
        with warnings.catch_warnings():  # dd warns that 'mem' is now in bytes
            warnings.simplefilter("ignore")
            st = self.bdd.statistics()
        return {"live_nodes": len(self.bdd), "peak_nodes": int(st["peak_nodes"]), "variables": len(self.variables),
                "memory_bytes": int(st["mem"])}
