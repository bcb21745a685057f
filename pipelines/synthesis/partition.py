"""Partitioning the current states for ``∃u.CPre(Z)`` computed in parts (docs/method.md §6), the arithmetic only.

The fixed points spend nearly all of synthesis in ``∃u.CPre`` and CUDD is single-threaded, so the partitioned
form (:class:`~.partitioned.PartitionedCPre`) computes it on several parts of the state space at once. This module
says where to cut; what a part computes is :mod:`.parts`, running the parts a transport's business.

Exactness: for a set ``H`` of current states, ``H ∧ ∃u.CPre(Z)`` is computed exactly by conjoining ``H`` into
the chain's first operand, the shared ``∃w`` step and the admissible pairs (the ``part`` of
:func:`~.cpre.predecessors_of`): ``H`` reads current-state bits only, so it commutes with ``∃x'``, ``∃w`` and
``∃u``. The parts are lexicographic ranges of the codes of the top two current-state digits of the variable
order (:func:`split_digits`, :func:`lexicographic_part`); they partition every code pair, the last one including
the codes past the grid, so the union of the parts is ``∃u.CPre(Z)`` itself.

Why those digits: CUDD's recursion splits at the top-most variables first, so parts cut there share little
work (the parts' summed time stays within 1.0-1.17x of the whole on consensus and the tanks, where a lower
digit costs up to 2x). A cut may fall inside a cell of the top digit, between cells of the second one: consensus
concentrates its work on a few cells of the top agent, and whole cells alone leave the parts of its largest call
badly unbalanced.

Balancing: the work is not uniform over the cells, so after every call a per-cell estimate of the work is
scaled to the measured time of each range (:func:`update_density`) and the cuts move half way to its equal-work
quantiles (:func:`equal_work_cuts`, :func:`damped_cuts`: consensus's heavy cells made undamped cuts oscillate).
A cell here is a pair (top digit, second digit), indexed row-major.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from pipelines.symbolic.symbolic_model import Function, SymbolicModel


def update_density(density: np.ndarray, bounds: Sequence[tuple[int, int]], seconds: Sequence[float]) -> np.ndarray:
    """Scale a per-cell work estimate so that each range's sum is the time it took (its shape within a range kept).

    Parameters
    ----------
    density : ndarray, shape (cells,)
        Seconds per cell, the previous estimate (uniform at first).
    bounds : sequence of (int, int)
        Ranges ``[lo, hi]`` of cells, in order; the last may extend past the cells.
    seconds : sequence of float
        Time each range took, same length.

    Returns
    -------
    ndarray, shape (cells,)
        The new estimate. Moving cuts over the iterations of a fixed point refines the shape: consensus work
        sits on a few cells of the top agent (the consensus centre), which a uniform estimate per range sends
        back and forth across the cut.
    """
    out = np.array(density, dtype=float)
    cells = out.size
    for (lo, hi), s in zip(bounds, seconds):
        hi = min(hi, cells - 1)
        if hi < lo:
            continue
        s = max(float(s), 1e-6)  # an instant range still gets cells
        seg = out[lo:hi + 1]
        total = seg.sum()
        out[lo:hi + 1] = seg * (s / total) if total > 0 else s / (hi - lo + 1)
    return out


def equal_work_cuts(density: np.ndarray, parts: int) -> list[int]:
    """``parts - 1`` cuts that give each range the same share of ``density`` (seconds per cell).

    Returns strictly increasing cuts in ``1 .. cells - 1`` (range ``k`` starts at cut ``k - 1``), each at the
    cell boundary nearest its quantile.
    """
    cum = np.cumsum(np.asarray(density, dtype=float))
    cells = cum.size
    cuts: list[int] = []
    for k in range(1, parts):
        c = int(np.argmin(np.abs(cum[:-1] - cum[-1] * k / parts))) + 1  # range k starts after the nearest cell
        lowest = (cuts[-1] + 1) if cuts else 1
        cuts.append(min(max(c, lowest), cells - (parts - k)))
    return cuts


def damped_cuts(old: Sequence[int], target: Sequence[int]) -> list[int]:
    """Each cut moved half way from ``old`` to ``target`` (at least one cell when they differ).

    The work of a call is that of the next call only roughly (each iterate of a fixed point is another set), and
    a few heavy cells near a cut make the equal-work cut jump across them; consensus N = 8 went 16, 18, 15, 18,
    15 with the undamped cuts. Half steps keep order: ``old`` and ``target`` are both strictly increasing.
    """
    out = []
    for o, t in zip(old, target):
        d = t - o
        out.append(o if d == 0 else o + (1 if d > 0 else -1) * max(1, abs(d) // 2))
    return out


def split_digits(model: SymbolicModel) -> tuple[str, ...]:
    """The current-state digits the parts are cut along: the top two of the variable order (one if only one).

    A cut falls between cells of the top digit, or inside one of its cells between cells of the second digit:
    consensus's work sits on a few cells of the top agent, and a cut between whole cells of it leaves one part of
    the largest call about 1.4x as long as the other.
    """
    out: list[str] = []
    for v in model.variables:
        d = v.rsplit("_", 1)[0]
        if d.startswith("x") and not d.startswith("xn") and d not in out:
            out.append(d)
            if len(out) == 2:
                break
    if not out:
        raise ValueError("the model has no current-state digits to cut along")
    return tuple(out)


def lexicographic_part(
    model: SymbolicModel, digits: Sequence[str], start: Sequence[int], end: Sequence[int] | None
) -> Function:
    """Current states whose codes of ``digits``, read as a tuple, lie in ``[start, end)`` lexicographically.

    ``end = None``: no upper end (codes past the grid included). Consecutive parts ``[s_0, s_1), [s_1, s_2), ...,
    [s_k, None)`` with ``s_0 = (0, ...)`` therefore partition every code, inside the grid or not: the union of
    the parts' predecessors is the whole (module docstring). Cells are codes: cell ``c`` of a digit has code ``c``.
    """
    if len(start) != len(digits) or (end is not None and len(end) != len(digits)):
        raise ValueError("a part's start and end need one code per digit")

    def top(d: str) -> int:
        return (1 << len(model.bits[d])) - 1

    def at_least(k: int, s: Sequence[int]) -> Function:  # digits[k:] >= s[k:]
        d = digits[k]
        if k == len(digits) - 1:
            return model.interval(d, s[k], top(d))
        return model.interval(d, s[k] + 1, top(d)) | (model.interval(d, s[k], s[k]) & at_least(k + 1, s))

    def below(k: int, e: Sequence[int]) -> Function:  # digits[k:] < e[k:]
        d = digits[k]
        if k == len(digits) - 1:
            return model.interval(d, 0, e[k] - 1)
        return model.interval(d, 0, e[k] - 1) | (model.interval(d, e[k], e[k]) & below(k + 1, e))

    part = at_least(0, start)
    if end is not None:
        part &= below(0, end)
    return part


def admitting_below(model: SymbolicModel, M: Function, digit: str, c: int) -> Function:
    """``∃ŵ. M̂ ∧ code(ŵ_digit) ≤ c``: the states admitting some internal input whose code of ``digit`` is at
    most ``c`` (:func:`w_window`'s sets are differences of two of these)."""
    return model.bdd.exist(model.w_bits, M & model.interval(digit, 0, c))


def w_window(
    model: SymbolicModel, M: Function, digit: str, start: int, end: int | None,
    below: Callable[[int], Function] | None = None,
) -> tuple[Function, Function]:
    """The states whose lowest admissible code of ``digit`` lies in ``[start, end)``, and every ``ŵ`` they admit.

    Parameters
    ----------
    model : SymbolicModel
    M : Function
        The shared interconnection ``M̂(x̂, ŵ)`` (:attr:`~.cpre.ControllablePredecessor.M`).
    digit : str
        An internal variable's digit (``w0``); ``end = None``: no upper end.
    below : callable, optional
        ``c -> admitting_below(model, M, digit, c)``, if the caller keeps those sets (a Dask worker computes each
        once per problem, not once per part and call).

    Returns
    -------
    states : Function
        ``{x̂ : min{code(ŵ_digit) : M̂(x̂, ŵ)} ∈ [start, end)}``: the states admitting a code at most ``end - 1``
        and none below ``start``. Consecutive ranges ``[s_0, s_1), ..., [s_k, None)`` with ``s_0 = 0`` partition
        the states with ``M̂(x̂) ≠ ∅`` (the only states with admissible inputs).
    window : Function
        ``∃x̂. M̂ ∧ states``, over ``w`` bits: every ``ŵ`` a state of ``states`` admits. It reaches past ``end``
        by the spread of ``M̂(x̂)`` (one or two cells for consensus), which is what the parts of
        :func:`~.parts.window_predecessors` compute twice.
    """
    states = lowest_code_states(model, M, digit, start, end, below)
    return states, model.bdd.exist(model.x_bits, M & states)


def lowest_code_states(
    model: SymbolicModel, M: Function, digit: str, start: int, end: int | None,
    below: Callable[[int], Function] | None = None,
) -> Function:
    """:func:`w_window`'s ``states`` alone (the split cut's second phase needs no window)."""
    if below is None:
        def below(c: int) -> Function:
            return admitting_below(model, M, digit, c)
    top = (1 << len(model.bits[digit])) - 1
    states = below(top if end is None else end - 1)
    if start > 0:
        states &= ~below(start - 1)
    return states
