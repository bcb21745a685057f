"""``∃u.CPre(Z)`` on parts of the state space at once, one part per process (issue 6).

CUDD is single-threaded and the fixed points spend nearly all of synthesis in ``∃u.CPre``.
:class:`PartitionedPredecessors` is a ``partitioned`` factory for
:class:`~pipelines.synthesis.cpre.ControllablePredecessor`: it splits the current states into the parts of
:mod:`pipelines.synthesis.partition` (where to cut, why that is exact, how the cuts are balanced) and computes
each part in its own process: the first here, the others in helper processes that hold a copy of the chain.

Failures: a helper that dies or fails is a :class:`HelperError` (a
:class:`~pipelines.synthesis.cpre.PartitionFailed`), after which the pool is closed (pending answers would
desynchronise the next call); :meth:`.ControllablePredecessor.predecessors` then answers in one process. CUDD
out of memory in a helper is a :class:`~pipelines.symbolic.model.BDDMemoryError`, raised to the caller.

Transport: BDDs as DDDMP files in a private temporary directory; a helper declares the variables from the
model's header (:func:`~pipelines.symbolic.files.model_from_header`), so levels match. Messages are pickled
tuples of strings and numbers on two pipes; helpers are ``python -m workers.processes.partitioned_cpre`` child
processes (not ``multiprocessing``'s spawn, which would re-run the caller's ``__main__`` script).
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
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from pipelines.symbolic.files import header, model_from_header
from pipelines.symbolic.model import BDDMemoryError, Function, SymbolicModel
from pipelines.synthesis.cpre import ControllablePredecessor, PartitionFailed, Within, predecessors_of
from pipelines.synthesis.partition import (
    damped_cuts,
    equal_work_cuts,
    lexicographic_part,
    split_digits,
    update_density,
)
from pipelines.synthesis.symmetry import Symmetry, cached_symmetry
from workers.processes.children import start_module

log = logging.getLogger(__name__)

READY_TIMEOUT = 120.0
"""Seconds a helper may take to start (import numpy, dd and the model) before synthesis gives up on it."""


OUT_OF_MEMORY = "if it ran out of memory, run synthesis in one process (options.synthesis_processes: 1)"


class HelperError(PartitionFailed):
    """A helper process failed or died; the message says which and why."""


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
    """``∃u.CPre(Z)`` of a :class:`.ControllablePredecessor` computed in ``processes`` parts at once (see the module
    docstring).

    Parameters
    ----------
    cpre : ControllablePredecessor
    processes : int
        Parts, this process included (>= 2): ``processes - 1`` helpers start now, in the background.

    Call it like :meth:`.ControllablePredecessor.predecessors`; :meth:`close` (or garbage collection) stops the helpers.
    ``cuts`` and ``seconds`` show the current cuts and the last call's time per part.
    """

    takes_symmetry = True  # each part closes its representatives' answer (__call__)

    def __init__(self, cpre: ControllablePredecessor, processes: int) -> None:
        if processes < 2:
            raise ValueError(f"PartitionedPredecessors needs at least 2 processes, got {processes}")
        m = cpre.model
        # A weak reference: the CPre holds the pool, and a cycle through CUDD objects would leave their
        # destruction order to the garbage collector (dd refuses to free a manager with live nodes).
        self._cpre = weakref.ref(cpre)
        self.digits = split_digits(m)
        self.shape = tuple(int(m.sizes[d]) for d in self.digits)
        self.cells = math.prod(self.shape)
        parts = min(processes, self.cells)
        self._density = np.ones(self.cells)
        self._cuts = equal_work_cuts(self._density, parts)
        self._seconds: list[float] = []
        self._calls = 0
        self._tmp = tempfile.mkdtemp(prefix="compabs-cpre-")
        head = header(m)
        share = None if m.max_memory is None else m.max_memory // parts
        self._helpers = [_Helper(head, share, k) for k in range(1, parts)]
        self._problem: Any = None  # the Within (or "all") the helpers hold
        self._files = 0
        self._finalizer = weakref.finalize(self, _shutdown, self._helpers, self._tmp)

    @property
    def cpre(self) -> ControllablePredecessor:
        cpre = self._cpre()
        if cpre is None:
            raise RuntimeError("the ControllablePredecessor of this PartitionedPredecessors is gone")
        return cpre

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
        with self.cpre.model.guard("writing a BDD for a synthesis helper"):
            self.cpre.bdd.dump(path, [f])
        return path

    def _load(self, path: str) -> Function:
        with self.cpre.model.guard("reading a synthesis helper's BDD"):
            (f,) = self.cpre.bdd.load(path)
        os.unlink(path)
        return f

    def bounds(self) -> list[tuple[int, int]]:
        """The parts' ranges ``[lo, hi]`` of cells (row-major indices, see :attr:`cuts`)."""
        edges = [0, *self._cuts, self.cells]
        return [(a, b - 1) for a, b in zip(edges, edges[1:])]

    def _starts(self) -> list[tuple[int, ...] | None]:
        """Each part's first cell, then ``None`` (the end of the last part: past every code)."""
        return [(0,) * len(self.shape), *self.cut_cells, None]

    def _send_problem(self, within: Within | None) -> None:
        key = "all" if within is None else within
        if self._problem is key:
            return
        g = self.cpre
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
    def __call__(self, Z: Function, outside: Function | None = None, within: Within | None = None,
                 symmetry: Symmetry | None = None) -> Function:
        """``∃u.CPre(Z)`` as :meth:`.ControllablePredecessor.predecessors` computes it. Any error stops the helpers first (their
        pending answers would otherwise be read by the next call), so the pool is unusable after one. With
        ``symmetry`` (the sets of the call invariant under it) every part works on its representatives and closes
        its own answer (the union of the closures is the whole: closing distributes over unions)."""
        try:
            return self._call(Z, outside, within, symmetry)
        except BaseException:
            self.close()
            raise

    def _call(self, Z: Function, outside: Function | None, within: Within | None,
              symmetry: Symmetry | None) -> Function:
        g, m = self.cpre, self.cpre.model
        t_start = time.perf_counter()
        self._send_problem(within)
        z_file = self._dump(Z)
        not_z = outside is not None and outside == ~Z  # the reach loop's: each helper complements its Z
        o_file = None if outside is None or not_z else self._dump(outside)
        bounds, starts = self.bounds(), self._starts()
        classes = None if symmetry is None else symmetry.classes
        for h, start, end in zip(self._helpers, starts[1:], starts[2:]):
            h.send(("pred", z_file, o_file, not_z, self.digits, start, end, self._path(), classes))
        t0 = time.perf_counter()
        mine = lexicographic_part(m, self.digits, (0,) * len(self.shape), starts[1])  # starts[0], never None
        result = g.predecessors(Z, outside, within, part=mine,
                                states=None if symmetry is None else symmetry.representatives)
        if symmetry is not None:
            with m.guard("closing a part of CPre"):
                result = symmetry.close(result)
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
    model: SymbolicModel | None = None
    problem: tuple | None = None
    symmetries: dict[tuple, Symmetry] = {}  # the model's, by classes
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
                model = model_from_header(head, max_memory)
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
                _, z_file, o_file, not_z, digits, start, end, result_file, classes = msg
                t0 = time.perf_counter()
                with model.guard("computing a part of CPre"):
                    Z = model.bdd.load(z_file)[0]
                    outside = ~Z if not_z else None if o_file is None else model.bdd.load(o_file)[0]
                    chain, admissible, M, u_bits, w_bits = problem
                    part = lexicographic_part(model, digits, start, end)
                    sym = None if classes is None else cached_symmetry(symmetries, model, classes)
                    P = predecessors_of(model, chain, admissible, M, w_bits, u_bits, Z, outside, part,
                                        None if sym is None else sym.representatives)
                    if sym is not None:
                        P = sym.close(P)
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
    # Everything the helper owes the parent went through the pipe. Skipping the interpreter's teardown keeps its
    # collector from clearing CUDD functions held in reference cycles after their manager (dd then printed
    # "Still N nodes referenced upon shutdown" from every helper).
    sys.stderr.flush()
    os._exit(0)
