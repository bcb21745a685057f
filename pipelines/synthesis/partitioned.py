"""``∃u.CPre(Z)`` in parts at once: one partitioned controllable predecessor, the transport of its parts left out.

The fixed points spend nearly all of synthesis in ``∃u.CPre`` and CUDD is single-threaded, so
:class:`PartitionedCPre` (what a ``partitioned`` factory of :class:`~.cpre.ControllablePredecessor` gives) cuts
each call into parts, has a transport compute them, joins their answers and moves the cuts towards equal
measured work. This module plans; a transport only moves problems and parts (a subclass's :meth:`~PartitionedCPre._send`
and :meth:`~PartitionedCPre._run`): local helper processes (:mod:`workers.processes.partitioned_cpre`) or the
job's Dask workers (:mod:`workers.dask_cpre`). Every part is computed by :func:`~.parts.compute`, whichever
process runs it, so every mode gives the one-process answer.

* **Parts.** A call is cut into ranges of cells (:mod:`.partition`: exact, the union of the parts is the whole).
  What they split is the cut (:func:`cut_digits`): ``x``, ranges of the top two current-state digits, each part
  ``part ∧ ∃u.CPre(Z)``; for the shared CPre ``window``, ranges of the shared internal variable ``ŵ``, each part
  ``∃u.CPre`` on the states whose lowest admissible ``ŵ`` lies in its range (the chain run on the ``ŵ`` cells
  they admit); ``split``, the same answers in two phases (each range's bad pairs on its own ``ŵ`` cells, then each
  range's states from the ranges they reach: :func:`~.parts.join`); ``w``, the bad pairs of each range, joined
  here before one ``∃u`` step. Except for ``w``, a part's answer is a set of states, final on its own: the parts
  are only OR-ed.
* **Balancing.** After every call the per-cell work estimate is scaled to what each range took (its CPU seconds
  where the transport measures them) and the cuts move half way to its equal-work quantiles.
* **Failures.** Any error abandons the parts (their pending answers must not be read by the next call); a
  transport's failure is a :class:`~.cpre.PartitionFailed`, after which
  :meth:`~.cpre.ControllablePredecessor.predecessors` goes on in one process; CUDD out of memory in a part is a
  :class:`~pipelines.symbolic.symbolic_model.BDDMemoryError`.
"""

from __future__ import annotations

import logging
import math
import time
import weakref
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from pipelines.symbolic.symbolic_model import BDDMemoryError, Function, and_exists
from pipelines.synthesis.cpre import PartitionFailed
from pipelines.synthesis.partition import damped_cuts, equal_work_cuts, split_digits, update_density, w_window
from pipelines.synthesis.parts import PartSpec, Problem
from pipelines.synthesis.symmetry import Symmetry

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.synthesis.cpre import ControllablePredecessor, Within

log = logging.getLogger(__name__)

CUTS = ("auto", "window", "split", "w", "x")
"""What the parts of a call split (:func:`cut_digits`)."""

SPLIT_FROM = 4
"""From this many parts of the shared CPre on, ``cut='auto'`` is the split cut, below it the window cut. Summed
seconds of the parts over a Reach(Safe) of consensus N = 6 (two workers), window against split: 2 parts 28.3 and
28.5 s, 4 parts 36.0 and 33.7, 8 parts 47.1 and 38.9, 16 parts 65.7 and 54.0: the windows overlap by ``M̂``'s
spread (1.12x the cells of ``ŵ`` at 2 parts, 2.7x at 16 on N = 7), the split cut's second phase costs a transfer."""


def cut_digits(cpre: ControllablePredecessor, cut: str = "auto") -> tuple[str, tuple[str, ...]]:
    """The cut (``'window'``, ``'split'``, ``'w'`` or ``'x'``) and the digits it splits, for ``cut`` in
    :data:`CUTS` (``auto``: ``window`` for the shared CPre, ``x`` otherwise).

    Why along ``ŵ`` for the shared CPre: ``w`` sits above the states in its variable order and the chain's cost
    is spread over its cells, so ranges of ``ŵ`` split the work where CUDD's recursion splits it (on the largest
    call of consensus N = 6, in CUDD cache lookups, two ``ŵ`` halves summed to 1.04x the whole, two state halves
    to 1.31x). ``window`` gives each part the states whose admissible ``ŵ`` start in its range, so each part's
    answer is final and the parts are only OR-ed; ``w`` leaves the bad pairs of every part to be joined and one
    ``∃u`` step to run in the caller's process, a quarter of consensus N = 8's time on two workers, while the
    workers wait.
    """
    if cut not in CUTS:
        raise ValueError(f"cut must be one of {CUTS}, got {cut!r}")
    m = cpre.model
    w_digits = [d for d in dict.fromkeys(v.rsplit("_", 1)[0] for v in m.variables)
                if d.startswith("w") and m.sizes[d] > 1]
    if cut in ("w", "window", "split") or (cut == "auto" and cpre.M is not None and w_digits):
        if cpre.M is None or not w_digits:
            raise ValueError(f"the {cut} cut needs the shared CPre (a shared internal variable)")
        return ("window" if cut == "auto" else cut), (w_digits[0],)
    return "x", split_digits(m)


class Call(NamedTuple):
    """One call as a transport gets it (:meth:`PartitionedCPre._run`)."""

    Z: Function
    outside: Function | None
    not_z: bool
    """``outside`` is ``¬Z`` (the reach loop's): a part may complement its ``Z`` (:data:`~.parts.NOT_Z`)."""
    symmetry: Symmetry | None
    problem: Problem
    """The problem in the caller's model (what :meth:`PartitionedCPre._send` sent last)."""
    specs: list[PartSpec]
    """The parts, in range order."""
    work: list[float]
    """The predicted work of each part (only the order counts)."""
    reads: list[list[int]] | None
    """Of the split cut: for each range, the ranges whose first phase its join reads, its own first."""
    started: float
    """``time.perf_counter()`` when the call began."""


class Answer(NamedTuple):
    """A part's answer as a transport gives it back."""

    k: int
    result: Function
    """Its answer in the caller's model."""
    seconds: float
    cpu: float | None = None
    """The CPU seconds of its computing thread, if the transport measures them."""


class PartitionedCPre:
    """``∃u.CPre(Z)`` of a :class:`~.cpre.ControllablePredecessor` in ``parts`` parts at once (module docstring).

    Parameters
    ----------
    cpre : ControllablePredecessor
        Held by a weak reference (it holds this object; a cycle through CUDD objects would leave their
        destruction order to the garbage collector, and ``dd`` refuses to free a manager with live nodes).
    parts : int
        Parts per call (>= 2; at most the cells of the digits cut).
    cut : str
        One of :data:`CUTS` (:func:`cut_digits`); ``auto`` is the split cut from :data:`SPLIT_FROM` parts on.

    Call it like :meth:`~.cpre.ControllablePredecessor.predecessors`; :meth:`close` stops the transport. A subclass
    moves the problem (:meth:`_send`) and the parts (:meth:`_run`), and stops (:meth:`_stop`).

    Attributes
    ----------
    parts : int
        Parts per call.
    cut : str
        The cut the parts split (``window``, ``split``, ``w`` or ``x``), along the digits ``digits`` (of
        ``shape`` cells, ``cells`` in all).
    calls : int
        Calls answered so far.
    seconds : list of float
        Seconds each part took in the last call, in part order.
    """

    on = "here"
    """Where the parts run (:meth:`report`)."""

    def __init__(self, cpre: ControllablePredecessor, parts: int, cut: str = "x") -> None:
        if parts < 2:
            raise ValueError(f"{type(self).__name__} needs at least 2 parts, got {parts}")
        self._cpre = weakref.ref(cpre)
        self.cut, self.digits = cut_digits(cpre, cut)
        if cut == "auto" and self.cut == "window" and parts >= SPLIT_FROM:
            self.cut = "split"
        m = cpre.model
        self.shape = tuple(int(m.sizes[d]) for d in self.digits)
        self.cells = math.prod(self.shape)
        self.parts = min(parts, self.cells)
        self._density = np.ones(self.cells)
        self._cuts = equal_work_cuts(self._density, self.parts)
        self.seconds: list[float] = []
        self.calls = 0
        self._held: Any = None  # the Within (or "all") whose problem the transport holds
        self._problem: Problem | None = None
        self._last_bounds: list[tuple[int, int]] | None = None
        self._reach: np.ndarray | None = None  # the split cut's: highest ŵ admitted, by lowest (reads)

    # ------------------------------------------------------------------ the plan
    @property
    def cpre(self) -> ControllablePredecessor:
        cpre = self._cpre()
        if cpre is None:
            raise RuntimeError(f"the ControllablePredecessor of this {type(self).__name__} is gone")
        return cpre

    @property
    def takes_symmetry(self) -> bool:
        """Whether a call may pass ``symmetry=``: each part then works on its representatives and closes its own
        answer; the ``w`` cut's parts are pairs of states and inputs, joined here (not supported)."""
        return self.cut != "w"

    @property
    def cuts(self) -> list[int]:
        """First cell of every part but the first, as an index into the cells of :attr:`digits` in row-major
        order. They move after each call; set them to try another balance (strictly increasing, in
        ``1 .. cells - 1``, one fewer than :attr:`parts`)."""
        return list(self._cuts)

    @cuts.setter
    def cuts(self, cuts: Sequence[int]) -> None:
        new = [int(c) for c in cuts]
        edges = [0, *new, self.cells]
        if len(new) != self.parts - 1 or any(a >= b for a, b in zip(edges, edges[1:])):
            raise ValueError(f"{self.parts - 1} strictly increasing cuts in 1 .. {self.cells - 1} needed, got {new}")
        self._cuts = new

    @property
    def cut_cells(self) -> list[tuple[int, ...]]:
        """:attr:`cuts` as cells (one code per digit)."""
        return [tuple(int(c) for c in np.unravel_index(k, self.shape)) for k in self._cuts]

    def bounds(self) -> list[tuple[int, int]]:
        """The parts' ranges ``[lo, hi]`` of cells (row-major indices, see :attr:`cuts`)."""
        edges = [0, *self._cuts, self.cells]
        return [(a, b - 1) for a, b in zip(edges, edges[1:])]

    def specs(self) -> list[PartSpec]:
        """The parts of the next call: each range from its first cell to the next part's (the last one with no upper
        end, so that the codes past the grid belong to it)."""
        kind = {"x": "states", "window": "window"}.get(self.cut, "bad")
        starts: list[tuple[int, ...] | None] = [(0,) * len(self.shape), *self.cut_cells, None]
        return [PartSpec(kind, self.digits, a, b) for a, b in zip(starts[:-1], starts[1:]) if a is not None]

    def reads(self, bounds: list[tuple[int, int]]) -> list[list[int]]:
        """Of the split cut: for each range of ``bounds``, the ranges of the ``ŵ`` cells that its states admit,
        its own first (:func:`~.parts.join` reads their first phases)."""
        if self._reach is None:  # the highest ŵ a state admits, by its lowest: once, M̂ does not change
            self._reach = np.array([max(self._window_hits(c, c + 1), default=c) for c in range(self.cells)])
        out = []
        for k, (lo, hi) in enumerate(bounds):
            top = int(self._reach[lo:hi + 1].max())
            out.append([k] + [j for j, (a, b) in enumerate(bounds) if j != k and a <= top and b >= lo])
        return out

    def _window_hits(self, start: int, end: int | None) -> list[int]:
        """The ``ŵ`` cells admitted by the states whose lowest admissible ``ŵ`` lies in ``[start, end)``
        (:func:`~.partition.w_window`'s window, cell by cell)."""
        g, m = self.cpre, self.cpre.model
        assert g.M is not None
        digit = self.digits[0]
        with m.guard("finding the cells of a window of ŵ"):
            _, window = w_window(m, g.M, digit, start, end)
            return [c for c in range(self.cells) if (window & m.interval(digit, c, c)) != m.bdd.false]

    @property
    def window_cells(self) -> list[int]:
        """Of the window and split cuts, the ``ŵ`` cells each part of the last call ran the chain on (a window
        reaches past its range by the spread of ``M̂``, so with many windows the chain runs on the same cells more
        than once: on consensus N = 7, 1.12x the 33 cells with 2 parts, 2.70x with 16; the split cut's first phase
        runs on each range's own cells); empty for the other cuts or before a call. Computed when asked (reports),
        not during the calls."""
        bounds = self._last_bounds
        if self.cut not in ("window", "split") or bounds is None:
            return []
        if self.cut == "split":
            return [b - a + 1 for a, b in bounds]
        return [len(self._window_hits(a, None if k == len(bounds) - 1 else b + 1)) for k, (a, b) in enumerate(bounds)]

    def report(self) -> dict[str, Any]:
        """How the parts ran: where, calls, the digits cut along, the cuts (each the first cell of a part), seconds
        per part in the last call, the cut, and what the transport adds (:meth:`_report`)."""
        out: dict[str, Any] = {"on": self.on, "processes": len(self._cuts) + 1, "calls": self.calls,
                               "digits": list(self.digits), "cuts": [list(c) for c in self.cut_cells],
                               "last_seconds": [round(s, 3) for s in self.seconds], **self._report()}
        window_cells = self.window_cells
        if window_cells:  # ŵ cells the last call's parts ran the chain on
            out["window_cells"] = {"parts": window_cells, "cells": int(self.cells)}
        out["cut"] = self.cut
        return out

    # ------------------------------------------------------------------ the call
    def __call__(self, Z: Function, outside: Function | None = None, within: Within | None = None,
                 symmetry: Symmetry | None = None) -> Function:
        """``∃u.CPre(Z)`` as :meth:`~.cpre.ControllablePredecessor.predecessors` computes it. With ``symmetry`` (the
        sets of the call invariant under it) every part works on its representatives and closes its own answer.
        Any error abandons the parts first (:meth:`_abandon`); a failure of the transport is a
        :class:`~.cpre.PartitionFailed`."""
        if symmetry is not None and not self.takes_symmetry:
            raise ValueError(f"the {self.cut} cut does not take a symmetry")
        try:
            return self._call(Z, outside, within, symmetry)
        except (BDDMemoryError, PartitionFailed):
            self._abandon()
            raise
        except Exception as exc:
            self._abandon()
            failed = self._failure(exc)
            if failed is None:
                raise
            raise failed from None
        except BaseException:
            self._abandon()
            raise

    def _call(self, Z: Function, outside: Function | None, within: Within | None,
              symmetry: Symmetry | None) -> Function:
        g, m = self.cpre, self.cpre.model
        started = time.perf_counter()
        key = "all" if within is None else within
        if self._problem is None or self._held is not key:
            self._problem = Problem.of(g, within)
            self._send(self._problem)
            self._held = key
        bounds = self.bounds()
        self._last_bounds = bounds
        call = Call(Z, outside, outside is not None and outside == ~Z, symmetry, self._problem, self.specs(),
                    [float(self._density[lo:hi + 1].sum()) for lo, hi in bounds],
                    self.reads(bounds) if self.cut == "split" else None, started)
        result = m.bdd.false
        seconds, cpu = [0.0] * len(bounds), [0.0] * len(bounds)
        measured_cpu = True
        for answer in self._run(call):
            with m.guard("joining the parts of CPre"):
                result |= answer.result
            seconds[answer.k] = answer.seconds
            cpu[answer.k] = answer.cpu or 0.0
            measured_cpu = measured_cpu and bool(answer.cpu)
        t_parts = time.perf_counter()
        if self.cut == "w":  # the parts are the bad pairs: the one ∃u step, on the whole set, here
            with m.guard("joining the parts of CPre"):
                result = and_exists(call.problem.admissible, ~result, list(g.u_bits))
        self.seconds = seconds
        self.calls += 1
        # the parts' CPU seconds are their work even where they share cores (a worker per core: about their seconds)
        self._density = update_density(self._density, bounds, cpu if measured_cpu else seconds)
        self._cuts = damped_cuts(self._cuts, equal_work_cuts(self._density, len(bounds)))
        self._record(call, seconds, cpu, t_parts, time.perf_counter())
        return result

    def close(self) -> None:
        """Stop the transport and forget the problem (idempotent); the statistics stay readable."""
        self._problem, self._held = None, None
        self._stop()

    # ------------------------------------------------------------------ what a transport does
    def _send(self, problem: Problem) -> None:
        """Give the parts ``problem`` (once per problem: the parts of the next calls read it)."""
        raise NotImplementedError

    def _run(self, call: Call) -> Iterator[Answer]:
        """Compute the parts of ``call`` (``call.specs``), each by :func:`~.parts.compute`, and yield their answers
        as they come (the caller joins each before the next)."""
        raise NotImplementedError

    def _stop(self) -> None:
        """Stop moving parts and drop what the parts hold (idempotent)."""

    def _abandon(self) -> None:
        """After an error in a call: no answer pending may be read by the next call. By default :meth:`close`."""
        self.close()

    def _failure(self, exc: Exception) -> PartitionFailed | None:
        """What ``exc``, raised by the transport, is: a :class:`~.cpre.PartitionFailed` to go on in one process
        after, or ``None`` to raise it as it is."""
        return None

    def _record(self, call: Call, seconds: list[float], cpu: list[float], joined: float, ended: float) -> None:
        """Account for a call that ended (``joined``: the parts' answers joined; ``ended``: the ``∃u`` step of the
        ``w`` cut too, both ``time.perf_counter()``)."""
        log.info("partitioned CPre (%s): parts took %s s; next cuts %s; call %.2f s", self.on,
                 [round(s, 2) for s in seconds], self.cut_cells, ended - call.started)

    def _report(self) -> dict[str, Any]:
        """What the transport adds to :meth:`report`."""
        return {}


__all__ = ["CUTS", "SPLIT_FROM", "Answer", "Call", "PartitionedCPre", "cut_digits"]
