"""Counting, sampling and listing the cells of a BDD exactly (domain constraints applied; docs/method.md §5).

CUDD's model count is a double, inexact above 2**53 (consensus N = 8 has ~1.4e10 winning states and far more
state-input pairs), so counts here are Python integers over a table of every node's model count
(:func:`count_table`). The same table drives :class:`Sampler`, which draws cells uniformly (a domain of 1e-5
of the state space costs no more than a large one, where rejection sampling would fail).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from pipelines.symbolic.symbolic_model import Function, SymbolicModel

CountTable = tuple[Callable[[Function], int], Callable[[Function], int], int]
"""``(count, position, N)`` of :func:`count_table`."""


class Sampler:
    """Draws cells of a set uniformly (:func:`sampler`), its model counts computed once.

    Exact model counts of every node (:func:`count_table`) guide a walk from the root to ``TRUE``
    that takes each branch with the probability of its share of the models (a skipped level is a free bit: 1/2).
    Cost: ``O(|f|)`` to make, ``O(bits)`` per draw; a closed loop keeps one per visited cell.
    """

    def __init__(self, f: Function, table: CountTable | None, widths: Sequence[int], columns: Sequence[int]) -> None:
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
        models, position, N = self._table
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
                w0, w1 = models(lo) << (position(lo) - q - 1), models(hi) << (position(hi) - q - 1)
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


def count(model: SymbolicModel, f: Function, digits: Sequence[str]) -> int:
    """Exact number of cells of ``digits`` in ``f`` (domain constraint applied; support must be inside)."""
    bits = model.bits_of(digits)
    extra = model.bdd.support(f) - set(bits)
    if extra:
        raise ValueError(f"count over {list(digits)}: the BDD also depends on {sorted(extra)[:6]}")
    return exact_count(model, f & model.domain(digits), bits)


def count_states(model: SymbolicModel, f: Function) -> int:
    """Exact number of composed abstract states in a BDD over the current-state bits."""
    return count(model, f, model.x_digits())


def count_table(model: SymbolicModel, f: Function, bits: Sequence[str]) -> CountTable:
    """Exact model counts of every node below ``f`` over ``bits`` (Python integers; CUDD's count is a
    double, inexact above 2**53). Returns ``models(g)``: the assignments of the bits from ``g``'s level down
    that satisfy ``g``, and ``position(g)``: the index of ``g``'s level among ``bits`` (``len(bits)`` for a
    constant)."""
    levels = sorted(model.bdd.level_of_var(b) for b in bits)
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

    def models(g: Function) -> int:
        r = regular(g)
        n = memo[int(r)]
        return (1 << (N - position(r))) - n if g.negated else n

    return models, position, N


def exact_count(model: SymbolicModel, f: Function, bits: Sequence[str]) -> int:
    """Model count over ``bits`` with Python integers (CUDD's count is a double: inexact above 2**53)."""
    models, position, _ = count_table(model, f, bits)
    return models(f) << position(f)


def sample(
    model: SymbolicModel, f: Function, digits: Sequence[str], rng: np.random.Generator | None, size: int | None = None
):
    """Cells of ``digits`` in ``f``, uniformly at random (``rng``) or the smallest (``rng=None``).

    ``sampler(model, f, digits).draw(rng, size)``: see :class:`Sampler`. Returns codes, shape (len(digits),)
    (``size=None``) or (size, len(digits)); ``None`` / shape (0, ...) if ``f`` is empty on the valid codes.
    """
    return sampler(model, f, digits).draw(rng, size)


def sampler(model: SymbolicModel, f: Function, digits: Sequence[str]) -> Sampler:
    """A :class:`Sampler` of the cells of ``digits`` in ``f`` (``f`` must read no other bits)."""
    bits = list(model.bits_of(digits))
    extra = model.bdd.support(f) - set(bits)
    if extra:
        raise ValueError(f"sample over {list(digits)}: the BDD also depends on {sorted(extra)[:6]}")
    f = f & model.domain(digits)
    if f == model.bdd.false:
        return Sampler(f, None, [len(model.bits[d]) for d in digits], [])
    table = count_table(model, f, bits)
    by_level = sorted(bits, key=model.bdd.level_of_var)
    col = {b: j for j, b in enumerate(by_level)}
    return Sampler(f, table, [len(model.bits[d]) for d in digits], [col[b] for d in digits for b in model.bits[d]])


def enumerate_cells(model: SymbolicModel, f: Function, digits: Sequence[str]) -> np.ndarray:
    """Every cell of ``digits`` in ``f`` as an array of codes, shape (B, len(digits)). Small sets only."""
    bits = model.bits_of(digits)
    extra = model.bdd.support(f) - set(bits)
    if extra:
        raise ValueError(f"enumerate over {list(digits)}: the BDD also depends on {sorted(extra)[:6]}")
    rows = []
    for a in model.bdd.pick_iter(f & model.domain(digits), care_vars=set(bits)):
        rows.append([sum(int(a[b]) << (len(model.bits[d]) - 1 - k) for k, b in enumerate(model.bits[d]))
                     for d in digits])
    out = np.array(rows, dtype=np.int64).reshape(-1, len(digits))
    return out[np.lexsort(out.T[::-1])] if out.size else out


def inputs_at(model: SymbolicModel, controller: Function, x_idx: Sequence[int]) -> np.ndarray:
    """Joint inputs (per-subsystem flat indices, shape (k, N)) the controller allows at one state."""
    return enumerate_cells(model, model.bdd.let(model.state_assignment(x_idx), controller), model.u_digits())

