"""Resumable safety fixed points: what a fixed point asks of a checkpoint store (issue 24).

The safety fixed point of a large case runs for hours (the tanks at spacing 1.25: iterations of minutes each,
``docs/benchmarks.md``); a job that is stopped (cancelled, a worker lost, a machine rebooted) should not
start again from the target. :func:`~.fixed_points.safe` therefore hands its iterates to a :class:`Checkpoints`
store as it goes and, when the store has one of the same problem, starts from it.

**Why resuming cannot make a controller unsound.** The loop ``Z ← Z ∧ ∃u.CPre(Z)`` started from any ``Z₀ ⊆ S``
stops at the largest controlled invariant inside ``Z₀``, which is a controlled invariant inside ``S``: whatever
a store hands back (it is intersected with ``S`` first), the controller keeps every closed-loop run in its
domain. It is also the *same* invariant ``W`` as a fresh run's whenever ``W ⊆ Z₀``, which holds for every
iterate of the same problem (each lies between ``W`` and ``S``). A store therefore only has to make sure an
iterate belongs to the same problem (the same relations, interconnection and variables) and is intact: a wrong
one could only make the domain smaller, never the controller wrong.

Only safety iterates are stored. A reach iterate has no such property: a state wrongly in it would count as won
without a strategy, so resuming from one would mean trusting the store, or recomputing what it claims.
"""

from __future__ import annotations

from typing import Protocol

from pipelines.symbolic.symbolic_model import Function, SymbolicModel


class Checkpoints(Protocol):
    """Where a fixed point saves its iterates and finds them again (``workers.checkpoint_store`` writes them to a
    job's directory). ``name`` says which fixed point (``safe``, ``reach_safe/safe``)."""

    def resume(self, model: SymbolicModel, name: str) -> tuple[Function, int] | None:
        """A stored iterate of this problem's fixed point ``name`` and the iterations it had taken, or ``None``."""

    def iterate(self, model: SymbolicModel, name: str, Z: Function, iteration: int) -> None:
        """The iterate after ``iteration`` iterations; the store decides whether to write it now."""

    def converged(self, model: SymbolicModel, name: str, Z: Function, iteration: int) -> None:
        """The fixed point ``name`` stopped at ``Z`` after ``iteration`` iterations (always written)."""
