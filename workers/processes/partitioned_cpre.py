"""``∃u.CPre(Z)`` on parts of the state space at once, one part per process (issue 6).

CUDD is single-threaded and the fixed points spend nearly all of synthesis in ``∃u.CPre`` (10 tanks: the 24
safety iterations; consensus N = 8: the 9 reach iterations, ~450 s). :class:`PartitionedPredecessors` splits
the current states into lexicographic ranges of the top two current-state digits and computes each range in its
own process: the first here, the others in helper processes that hold a copy of the chain.

Exactness: for a set ``H`` of current states, ``H ∧ ∃u.CPre(Z)`` is computed exactly by conjoining ``H`` into
the chain's first operand, the shared ``∃w`` step and the admissible pairs (:meth:`.Game.predecessors`'s
``part``): ``H`` reads current-state bits only, so it commutes with ``∃x'``, ``∃w`` and ``∃u``. The ranges
partition every code pair of the two digits (the last one includes the codes past the grid;
:func:`lexicographic_part`), so the union of the parts is ``∃u.CPre(Z)`` itself. Tested against the one-process
result, fixed points included.

The top digit is the top-most current-state digit of the variable order: CUDD's recursion splits there first,
so the parts share little work. Measured, summing the parts' times against the whole: consensus N = 6
1.0-1.17x, 10 tanks 1.03x (a digit lower in the order cost up to 2x). The work is not uniform over the digit's
cells (tanks: split at the middle of the safe range, 8.6 s against 4.9 s), so after every call a per-cell
estimate of the work is scaled to the measured time of each range (:func:`update_density`) and the cuts move
half way to its equal-work quantiles (:func:`damped_cuts`: consensus's heavy cells made undamped cuts
oscillate). A cell here is a pair (top digit, second digit), indexed row-major: a cut may fall inside a cell of
the top digit. Consensus N = 8 concentrates its work on the top agent's cells 15-17, and with whole cells only
the cut alternated between 16 and 17; the largest reach call (the sixth, half of the loop) then took 164 s and
114 s in its two parts (the same call cut at 16: 121 s and 131 s, each part in its own process, two at a
time). With the second digit the cut settles inside cell 16. Consensus N = 8's safe and reach fixed points,
three runs of each code alternated (2026-11-24): reach loop 294, 275 and 285 s against 328, 316 and 288 s; the
slower part over the mean of the parts, summed over the calls, 1.04-1.06 against 1.08-1.13; the parts' summed
work the same (no loss from cutting inside a cell).

Failures: a helper that dies or fails is a :class:`HelperError`, after which the pool is closed (pending
answers would desynchronise the next call); :meth:`.Game.predecessors` then answers in one process. CUDD out
of memory in a helper is a :class:`~.symbolic.BDDMemoryError`, raised to the caller.

Transport: BDDs as DDDMP files in a private temporary directory; a helper declares the variables from the
model's header (:meth:`.SymbolicModel.from_header`), so levels match. Messages are pickled tuples of strings
and numbers on two pipes; helpers are ``python -m workers.processes.partitioned_cpre`` child processes (not
``multiprocessing``'s spawn, which would re-run the caller's ``__main__`` script).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
import weakref
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from workers.processes.children import start_module
from pipelines.errors import CompabsError
from pipelines.symbolic.model import BDDMemoryError, Function, SymbolicModel

if TYPE_CHECKING:  # pragma: no cover
    from pipelines.synthesis.game import Game, Within

log = logging.getLogger(__name__)

READY_TIMEOUT = 120.0
"""Seconds a helper may take to start (import numpy, dd and the model) before synthesis gives up on it."""


OUT_OF_MEMORY = "if it ran out of memory, run synthesis in one process (options.synthesis_processes: 1)"


class HelperError(CompabsError):
    """A helper process failed or died; the message says which and why."""


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
    consensus's work sits on a few cells of the top agent, and a cut between whole cells of it left the parts
    of the largest call at 164 s and 114 s.
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


class _Helper:
    """One helper process and its two pipes."""

    def __init__(self, head: dict, max_memory: int | None, index: int) -> None:
        self.index = index
        to_child_r, to_child_w = os.pipe()
        from_child_r, from_child_w = os.pipe()
        self.proc = start_module("workers.processes.partitioned_cpre", str(to_child_r), str(from_child_w),
                                 pass_fds=(to_child_r, from_child_w), stdin=subprocess.DEVNULL)
        os.close(to_child_r)
        os.close(from_child_w)
        self.out = Connection(to_child_w, readable=False)
        self.inp = Connection(from_child_r, writable=False)
        self.send(("start", head, max_memory))
        self.ready = False

    def send(self, msg: tuple) -> None:
        try:
            self.out.send(msg)
        except OSError as exc:
            raise HelperError(
                f"synthesis helper {self.index} is gone ({self._status()}: {exc}); {OUT_OF_MEMORY}") from None

    def recv(self, timeout: float | None = None) -> tuple:
        try:
            if timeout is not None and not self.inp.poll(timeout):
                raise HelperError(f"synthesis helper {self.index} did not answer within {timeout:g} s")
            msg = self.inp.recv()
        except (EOFError, OSError):
            raise HelperError(f"synthesis helper {self.index} died ({self._status()}); {OUT_OF_MEMORY}") from None
        if msg[0] == "error":
            _, kind, text = msg
            if kind == "BDDMemoryError":
                raise BDDMemoryError(f"synthesis helper {self.index}: {text}")
            raise HelperError(f"synthesis helper {self.index} failed: {kind}: {text}")
        return msg

    def wait_ready(self) -> None:
        if not self.ready:
            self.recv(READY_TIMEOUT)
            self.ready = True

    def _status(self) -> str:
        code = self.proc.poll()
        return "still running" if code is None else f"exit code {code}"

    def close(self) -> None:
        for f in (lambda: self.out.send(None), self.out.close, self.inp.close):
            try:
                f()
            except OSError:
                pass
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def _shutdown(helpers: list[_Helper], tmp: str) -> None:
    for h in helpers:
        h.close()
    shutil.rmtree(tmp, ignore_errors=True)


class PartitionedPredecessors:
    """``∃u.CPre(Z)`` of a :class:`.Game` computed in ``processes`` parts at once (see the module docstring).

    Parameters
    ----------
    game : Game
    processes : int
        Parts, this process included (>= 2): ``processes - 1`` helpers start now, in the background.

    Call it like :meth:`.Game.predecessors`; :meth:`close` (or garbage collection) stops the helpers.
    ``cuts`` and ``seconds`` show the current cuts and the last call's time per part.
    """

    def __init__(self, game: "Game", processes: int) -> None:
        if processes < 2:
            raise ValueError(f"PartitionedPredecessors needs at least 2 processes, got {processes}")
        m = game.model
        # A weak reference: the game holds the pool, and a cycle through CUDD objects would leave their
        # destruction order to the garbage collector (dd refuses to free a manager with live nodes).
        self._game = weakref.ref(game)
        self.digits = split_digits(m)
        self.shape = tuple(int(m.sizes[d]) for d in self.digits)
        self.cells = math.prod(self.shape)
        parts = min(processes, self.cells)
        self._density = np.ones(self.cells)
        self._cuts = equal_work_cuts(self._density, parts)
        self._seconds: list[float] = []
        self._calls = 0
        self._tmp = tempfile.mkdtemp(prefix="compabs-cpre-")
        head = m.header()
        share = None if m.max_memory is None else m.max_memory // parts
        self._helpers = [_Helper(head, share, k) for k in range(1, parts)]
        self._problem: Any = None  # the Within (or "all") the helpers hold
        self._files = 0
        self._finalizer = weakref.finalize(self, _shutdown, self._helpers, self._tmp)

    @property
    def game(self) -> "Game":
        game = self._game()
        if game is None:
            raise RuntimeError("the Game of this PartitionedPredecessors is gone")
        return game

    @property
    def cuts(self) -> list[int]:
        """First cell of every part but the first, as an index into the cells of :attr:`digits` in row-major
        order (they move after each call)."""
        return list(self._cuts)

    @property
    def cut_cells(self) -> list[tuple[int, ...]]:
        """:attr:`cuts` as cells ``(code of digits[0], code of digits[1])``."""
        return [tuple(int(c) for c in np.unravel_index(k, self.shape)) for k in self._cuts]

    @property
    def seconds(self) -> list[float]:
        """Seconds each part took in the last call (this process first)."""
        return list(self._seconds)

    @property
    def calls(self) -> int:
        return self._calls

    @property
    def helpers(self) -> list[subprocess.Popen]:
        """The helper processes (for monitoring; :meth:`close` stops them)."""
        return [h.proc for h in self._helpers]

    # ------------------------------------------------------------------ plumbing
    def _path(self) -> str:
        self._files += 1
        return os.path.join(self._tmp, f"{self._files}.dddmp")

    def _dump(self, f: Function) -> str:
        path = self._path()
        with self.game.model.guard("writing a BDD for a synthesis helper"):
            self.game.bdd.dump(path, [f])
        return path

    def _load(self, path: str) -> Function:
        with self.game.model.guard("reading a synthesis helper's BDD"):
            (f,) = self.game.bdd.load(path)
        os.unlink(path)
        return f

    def bounds(self) -> list[tuple[int, int]]:
        """The parts' ranges ``[lo, hi]`` of cells (row-major indices, see :attr:`cuts`)."""
        edges = [0, *self._cuts, self.cells]
        return [(a, b - 1) for a, b in zip(edges, edges[1:])]

    def _starts(self) -> list[tuple[int, ...] | None]:
        """Each part's first cell, then ``None`` (the end of the last part: past every code)."""
        return [(0,) * len(self.shape), *self.cut_cells, None]

    def _send_problem(self, within: "Within | None") -> None:
        key = "all" if within is None else within
        if self._problem is key:
            return
        g = self.game
        chain, admissible = (g.chain, g.admissible) if within is None else within
        roots = [rel for rel, _ in chain] + [admissible] + ([] if g.M is None else [g.M])
        files = [self._dump(f) for f in roots]
        msg = ("problem", files, [list(xn) for _, xn in chain], list(g.u_bits), list(g.w_bits))
        for h in self._helpers:
            h.wait_ready()
            h.send(msg)
        for h in self._helpers:
            h.recv()
        for f in files:
            os.unlink(f)
        self._problem = key

    # ------------------------------------------------------------------ the call
    def __call__(self, Z: Function, outside: Function | None = None, within: "Within | None" = None) -> Function:
        """``∃u.CPre(Z)`` as :meth:`.Game.predecessors` computes it. Any error stops the helpers first (their
        pending answers would otherwise be read by the next call), so the pool is unusable after one."""
        try:
            return self._call(Z, outside, within)
        except BaseException:
            self.close()
            raise

    def _call(self, Z: Function, outside: Function | None, within: "Within | None") -> Function:
        g, m = self.game, self.game.model
        t_start = time.perf_counter()
        self._send_problem(within)
        z_file = self._dump(Z)
        o_file = None if outside is None else self._dump(outside)
        bounds, starts = self.bounds(), self._starts()
        for h, start, end in zip(self._helpers, starts[1:], starts[2:]):
            h.send(("pred", z_file, o_file, self.digits, start, end, self._path()))
        t0 = time.perf_counter()
        result = g.predecessors(Z, outside, within, part=lexicographic_part(m, self.digits, starts[0], starts[1]))
        seconds = [time.perf_counter() - t0]
        t_mine = time.perf_counter()
        for h in self._helpers:
            _, path, s = h.recv()
            result |= self._load(path)
            seconds.append(s)
        for f in filter(None, (z_file, o_file)):
            os.unlink(f)
        self._seconds = seconds
        self._calls += 1
        self._density = update_density(self._density, bounds, seconds)
        self._cuts = damped_cuts(self._cuts, equal_work_cuts(self._density, len(bounds)))
        log.info("parallel CPre: parts from %s took %s s; next cuts %s; call %.2f s, before %.2f s, after %.2f s",
                 starts[:-1], [round(s, 2) for s in seconds], self.cut_cells, time.perf_counter() - t_start, t0 - t_start,
                 time.perf_counter() - t_mine)
        return result

    def close(self) -> None:
        """Stop the helpers and remove the temporary files (idempotent)."""
        self._finalizer()


# ====================================================================================== the helper's side
def _serve(inp: Connection, out: Connection) -> None:
    """Answer ``problem`` and ``pred`` messages until ``None`` or end of input."""
    from pipelines.synthesis.game import predecessors_of

    model: SymbolicModel | None = None
    problem: tuple | None = None
    while True:
        try:
            msg = inp.recv()
        except EOFError:
            return
        if msg is None:
            return
        try:
            if msg[0] == "start":
                _, head, max_memory = msg
                model = SymbolicModel.from_header(head, max_memory)
                out.send(("ready",))
            elif msg[0] == "problem":
                assert model is not None
                _, files, xn_lists, u_bits, w_bits = msg
                with model.guard("reading the chain"):
                    roots = [model.bdd.load(f)[0] for f in files]
                n = len(xn_lists)
                chain = list(zip(roots[:n], xn_lists))
                M = roots[n + 1] if len(roots) > n + 1 else None  # the shared method's interconnection
                problem = (chain, roots[n], M, u_bits, w_bits)
                out.send(("ok",))
            elif msg[0] == "pred":
                assert model is not None and problem is not None
                _, z_file, o_file, digits, start, end, result_file = msg
                t0 = time.perf_counter()
                with model.guard("computing a part of CPre"):
                    Z = model.bdd.load(z_file)[0]
                    outside = None if o_file is None else model.bdd.load(o_file)[0]
                    chain, admissible, M, u_bits, w_bits = problem
                    P = predecessors_of(model, chain, admissible, M, w_bits, u_bits, Z, outside,
                                        lexicographic_part(model, digits, start, end))
                    model.bdd.dump(result_file, [P])
                del Z, outside, P
                out.send(("ok", result_file, time.perf_counter() - t0))
            else:
                raise ValueError(f"unknown message {msg[0]!r}")
        except Exception as exc:  # reported to the parent, which raises it
            try:
                out.send(("error", type(exc).__name__, str(exc)))
            except OSError:  # the parent is gone or stopped listening
                return


def main(argv: Sequence[str] | None = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    inp = Connection(int(args[0]), writable=False)
    out = Connection(int(args[1]), readable=False)
    _serve(inp, out)


if __name__ == "__main__":
    main()
