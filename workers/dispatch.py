"""Which part of a call runs next, and on which worker: parts handed out as workers free up (issue 24).

:class:`workers.dask_cpre.DaskPredecessors` cuts a call into more parts than it has workers, or as many; this
decides, each time a worker's part ends, what that worker runs next, so that no worker waits while a part does.

Why not leave it to Dask: its scheduler places a task on a worker when the task is submitted (by estimated
occupancy; its queuing until a thread frees applies only to "root-ish" task groups larger than twice the cluster's
threads without worker restrictions), and can place the parts unevenly (on 16 workers, consensus N = 5: five parts
of a call one after another on one worker). Here each worker holds one part at a time: the first wave goes one
part per worker, and each further part is submitted, pinned, when a worker's part ends.

With at most one range per worker the split cut's joins are submitted at once with the first phases, each on the
worker of its own range's first phase and depending on the first phases it reads: Dask starts each when they have
ended, without a round trip through this process (whose thread may be reading an answer into CUDD, holding the
GIL, when a first phase ends).

What goes first: the ranges predicted largest (the parts' work estimate of the last calls, ``work``), as in
longest-processing-time list scheduling, whose slowest worker finishes within one part of the mean; the split cut's
second phase of a range (its *join*) once every first phase it reads has ended, on the worker that computed its
own range's first phase if that worker is free (it keeps that answer: :data:`workers.dask_parts._KEPT`), else on
any free worker (waiting for that one would leave this one idle).

On 16 cores (consensus N = 7) two parts per worker handed out this way brought the busiest worker of a call from
1.53x to 1.24x the mean, and cost 1.6x the CPU: one part per worker stays the default
(:data:`workers.dask_cpre.PARTS_PER_WORKER`).

Pure bookkeeping, no Dask: tested on its own (``tests/test_dispatch.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple


class Task(NamedTuple):
    """A task to submit: ``kind`` ``'part'`` (a one-phase cut's part), ``'core'`` (the split cut's first phase of
    range ``k``) or ``'join'`` (its second phase), on worker slot ``slot``."""

    kind: str
    k: int
    slot: int


class Dispatch:
    """The order in which a call's parts run on ``slots`` workers (module docstring).

    Parameters
    ----------
    work : sequence of float
        The predicted work of each range (any unit; only the order counts).
    slots : int
        Workers (threads) to hand parts to, at least 1.
    needs : sequence of sequences of int, optional
        Of the split cut: for each range ``k``, the ranges whose first phase its join reads (``k`` among them).
        Without it the parts are one-phase.

    :meth:`start` gives the first wave; :meth:`done` what to submit once a task ended, until :attr:`finished`.
    """

    def __init__(self, work: Sequence[float], slots: int, needs: Sequence[Sequence[int]] | None = None) -> None:
        if slots < 1:
            raise ValueError(f"Dispatch needs at least one slot, got {slots}")
        self.work = [float(w) for w in work]
        self.two_phase = needs is not None
        self.needs = [frozenset(n) | {k} for k, n in enumerate(needs)] if needs is not None else []
        self._first = sorted(range(len(self.work)), key=lambda k: (-self.work[k], k))  # largest first
        self._free = list(range(slots))
        self._core_slot: dict[int, int] = {}
        self._cores_done: set[int] = set()
        self._joins_left = set(range(len(self.work))) if self.two_phase else set()
        self._running = 0
        #: The split cut with at most one range per worker: every join goes with the first phases (module
        #: docstring). Its first phases' ends then need not be reported (:meth:`done`): a join depends on its own
        #: range's first phase and ends after it.
        self.at_once = self.two_phase and len(self.work) <= slots
        #: The most tasks at once that could run, submitted and not yet ended (at most ``slots``: one per worker; a
        #: join submitted with the first phases runs on the worker of its own range's, after it).
        self.most_in_flight = 0

    @property
    def finished(self) -> bool:
        return not self._first and not self._joins_left and self._running == 0

    def start(self) -> list[Task]:
        out = self._fill()
        if self.at_once:  # every join now, after the first phases it depends on; each stands for its own range's
            out += [self._join(k, self._core_slot[k]) for k in sorted(self._joins_left)]
        return out

    def done(self, task: Task) -> list[Task]:
        """``task`` ended: its slot is free; the tasks to submit now (with :attr:`at_once`, none: only joins count,
        and a first phase's end may go unreported)."""
        if self.at_once:
            if task.kind == "join":
                self._running -= 1
            return []
        self._running -= 1
        self._free.append(task.slot)
        if task.kind == "core":
            self._cores_done.add(task.k)
        return self._fill()

    def _ready(self) -> list[int]:
        """Joins whose first phases have all ended, largest first."""
        ready = [k for k in self._joins_left if self.needs[k] <= self._cores_done]
        return sorted(ready, key=lambda k: (-self.work[k], k))

    def _fill(self) -> list[Task]:
        out: list[Task] = []
        while self._free and self._first:  # first phases (or one-phase parts), largest first
            k = self._first.pop(0)
            slot = self._free.pop(0)
            self._core_slot[k] = slot
            out.append(Task("core" if self.two_phase else "part", k, slot))
        if self._free and self._joins_left:
            ready = self._ready()
            for k in list(ready):  # where its own pairs are kept, if that worker is free
                if self._core_slot[k] in self._free:
                    self._free.remove(self._core_slot[k])
                    ready.remove(k)
                    out.append(self._join(k, self._core_slot[k]))
            while self._free and ready:
                out.append(self._join(ready.pop(0), self._free.pop(0)))
        self._running += len(out)
        self.most_in_flight = max(self.most_in_flight, self._running)
        return out

    def _join(self, k: int, slot: int) -> Task:
        self._joins_left.discard(k)
        return Task("join", k, slot)


__all__ = ["Dispatch", "Task"]
