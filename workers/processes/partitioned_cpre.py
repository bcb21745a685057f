"""The partitioned ``∃u.CPre`` with its parts in local helper processes, one part per process (issue 6).

:class:`PartitionedPredecessors` is a :class:`~pipelines.synthesis.partitioned.PartitionedCPre` (the plan of the
parts, the joining and the balancing) whose transport is helper processes: the first part of a call runs here, the
others in ``processes - 1`` helpers that hold a copy of the problem. It cuts along the current states (the ``x``
cut): each part is a set of states, final on its own.

Transport: the problem (:func:`~pipelines.synthesis.parts.pack`) and each call's sets go to the helpers as DDDMP
bytes in pickled messages on two pipes; a helper declares the variables from the model's header when it starts, so
levels match, and answers with its part as DDDMP bytes. Helpers are ``python -m workers.processes.partitioned_cpre``
child processes (not ``multiprocessing``'s spawn, which would re-run the caller's ``__main__`` script).

Failures: a helper that dies or fails is a :class:`HelperError` (a
:class:`~pipelines.synthesis.cpre.PartitionFailed`), after which the helpers are stopped (pending answers would
desynchronise the next call) and :meth:`~pipelines.synthesis.cpre.ControllablePredecessor.predecessors` answers in
one process. CUDD out of memory in a helper is a :class:`~pipelines.symbolic.symbolic_model.BDDMemoryError`.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
import weakref
from collections.abc import Iterator, Sequence
from multiprocessing.connection import Connection

from pipelines.symbolic.files import from_bytes, header, model_from_header, to_bytes
from pipelines.symbolic.symbolic_model import BDDMemoryError, SymbolicModel
from pipelines.synthesis.cpre import ControllablePredecessor, PartitionFailed
from pipelines.synthesis.partitioned import Answer, Call, PartitionedCPre
from pipelines.synthesis.parts import NOT_Z, Problem, compute, pack, solve, unpack
from workers.processes.children import start_module

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


def _shutdown(helpers: list[_Helper]) -> None:
    for h in helpers:
        h.close()


class PartitionedPredecessors(PartitionedCPre):
    """``∃u.CPre(Z)`` of a :class:`~pipelines.synthesis.cpre.ControllablePredecessor` in ``processes`` parts at
    once, the first here and the others in helper processes (module docstring).

    Parameters
    ----------
    cpre : ControllablePredecessor
    processes : int
        Parts, this process included (>= 2): ``processes - 1`` helpers start now, in the background, each allowed
        its share of the model's ``max_memory``.

    Call it like :meth:`~pipelines.synthesis.cpre.ControllablePredecessor.predecessors`; :meth:`close` (or garbage
    collection) stops the helpers.
    """

    on = "processes"

    def __init__(self, cpre: ControllablePredecessor, processes: int) -> None:
        if processes < 2:
            raise ValueError(f"PartitionedPredecessors needs at least 2 processes, got {processes}")
        super().__init__(cpre, processes, cut="x")
        m = cpre.model
        share = None if m.max_memory is None else m.max_memory // self.parts
        self._helpers = [_Helper(header(m), share, k) for k in range(1, self.parts)]
        self._finalizer = weakref.finalize(self, _shutdown, self._helpers)

    @property
    def helpers(self) -> list[subprocess.Popen]:
        """The helper processes (for monitoring; :meth:`close` stops them)."""
        return [h.proc for h in self._helpers]

    def _send(self, problem: Problem) -> None:
        msg = ("problem", pack(problem, "helpers"))
        for h in self._helpers:
            h.wait_ready()
            h.send(msg)
        for h in self._helpers:
            h.recv()

    def _run(self, call: Call) -> Iterator[Answer]:
        m = call.problem.model
        z = to_bytes(m, call.Z, "writing a set for the synthesis helpers")
        o = None if call.outside is None else NOT_Z if call.not_z else to_bytes(m, call.outside)
        classes = None if call.symmetry is None else call.symmetry.classes
        for h, spec in zip(self._helpers, call.specs[1:]):
            h.send(("part", z, o, spec, classes))
        t0 = time.perf_counter()
        with m.guard("computing a part of CPre"):
            mine = compute(call.problem, call.specs[0], call.Z, call.outside, call.symmetry)
        yield Answer(0, mine, time.perf_counter() - t0)
        del mine
        for h in self._helpers:
            _, blob, seconds = h.recv()
            yield Answer(h.index, from_bytes(m, blob, "reading a synthesis helper's part"), seconds)

    def _stop(self) -> None:
        self._finalizer()


# ====================================================================================== the helper's side
def _serve(inp: Connection, out: Connection) -> None:
    """Answer ``start``, ``problem`` and ``part`` messages until ``None`` or end of input."""
    model: SymbolicModel | None = None
    problem: Problem | None = None
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
                problem = None  # the previous one's nodes go first
                problem = unpack(msg[1], model)
                out.send(("ok",))
            elif msg[0] == "part":
                assert problem is not None
                _, z, outside, spec, classes = msg
                t0 = time.perf_counter()
                blob = to_bytes(problem.model, solve(problem, spec, z, outside, classes), "writing a part of CPre")
                out.send(("ok", blob, time.perf_counter() - t0))
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
