"""Closed loop with memory: the concrete black boxes under an ``ltl`` specification's product controller
(Theorem 4.2 on the product; docs/spec.md, "Temporal-logic tasks").

Each run tracks the automaton state on the letters its concrete states carry
(:meth:`~pipelines.product_controller.ProductController.automaton_state_after`), applies an input of
``C_q(x̂)`` and stops when ``q`` accepts: the concrete trace so far satisfies the formula. Its first product state
``(δ(q₀, σ(x₀)), x̂₀)`` has a layer ``L`` (:meth:`~pipelines.product_controller.ProductController.layer_of`): a
sound abstraction and controller accept within ``L`` steps. A run is a violation if it leaves the state set, reaches
a product state outside the winning set (no input), or has not accepted after ``L`` steps; a run still going when
``options.closed_loop_steps`` (if set, and below ``L``) ends is unfinished, not a violation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pipelines.network import Network
from pipelines.product_controller import ProductController
from pipelines.verification.closed_loop import ClosedLoop, Run, closed_loop_starts, input_dim, step


@dataclass
class ProductLoop(ClosedLoop):
    """:class:`~.closed_loop.ClosedLoop` of product runs: a run's ``in_target`` flags say where its automaton state
    accepts, ``settled_at`` is the step it accepted at, ``extra`` holds its automaton states and its bound."""

    @property
    def accepted(self) -> int:
        return sum(1 for _, _, r in self.runs if r.settled_at is not None and not r.violation)

    @property
    def unfinished(self) -> int:
        return sum(1 for _, _, r in self.runs if r.settled_at is None and not r.violation)

    def summary(self) -> dict:
        """The report's ``closed_loop`` entry: :meth:`ClosedLoop.summary` with the runs that accepted."""
        bounds = [r.extra["bound"] for _, _, r in self.runs]
        return {**super().summary(), "accepted": self.accepted, "unfinished": self.unfinished,
                "largest_bound": max(bounds) if bounds else None}


def simulate_product(network: Network, controller: ProductController, x0: np.ndarray, steps: int | None,
                     rng: np.random.Generator, choose: str = "random",
                     progress: Callable[[int, int], None] | None = None) -> list[Run]:
    """Runs from each row of ``x0`` (shape (R, n), in the controller's domain) in lockstep, each until its
    automaton state accepts, it violates (module docstring) or ``steps`` end (``None``: the largest bound)."""
    X = np.array(x0, dtype=float, ndmin=2)
    R = X.shape[0]
    q = controller.initial_state(X)
    idx, on = controller.cells(X)
    bound = np.array([controller.layer_of(idx[r], int(q[r])) if on[r] else None for r in range(R)], dtype=object)
    bound = np.array([-1 if b is None else int(b) for b in bound], dtype=np.int64)
    horizon = int(bound.max(initial=0)) if steps is None else int(steps)
    lb, ub = np.asarray(controller.state_grid.lb), np.asarray(controller.state_grid.ub)
    states: list[list[np.ndarray]] = [[x.copy()] for x in X]  # X advances in place
    inputs: list[list[np.ndarray]] = [[] for _ in range(R)]
    automaton: list[list[int]] = [[int(v)] for v in q]
    violation: list[str | None] = [None] * R
    accepted: list[int | None] = [None] * R
    going = np.ones(R, dtype=bool)
    for k in range(horizon + 1):
        live = np.flatnonzero(going)
        if live.size == 0:
            break
        now = controller.accepting(q[live])
        out = np.any((X[live] < lb) | (X[live] > ub), axis=1)
        for r in live[now & ~out]:
            accepted[r] = k
        for r in live[out]:
            violation[r] = f"step {k}: the state {X[r].tolist()} left the state set"
        late = ~now & ~out & (k >= bound[live])
        for r in live[late]:
            violation[r] = (f"step {k}: the formula is not satisfied within the bound of {bound[r]} steps its first "
                            f"product state's layer gives (automaton state {int(q[r])})")
        going[live[now | out | late]] = False
        live = np.flatnonzero(going)
        if k == horizon or live.size == 0:
            break
        chosen = controller.choose_many(X[live], q[live], rng, choose)
        stepping = np.array([u is not None for u in chosen], dtype=bool)
        for r in live[~stepping]:
            violation[r] = (f"step {k}: the product state (automaton state {int(q[r])}, state {X[r].tolist()}) is "
                            "outside the controller's winning set")
            going[r] = False
        moving = live[stepping]
        if moving.size:
            U = np.array([u for u in chosen if u is not None]).reshape(moving.size, input_dim(network))
            X[moving] = step(network, X[moving], U)
            q[moving] = controller.automaton_state_after(q[moving], X[moving])
            for j, r in enumerate(moving.tolist()):
                states[r].append(X[r].copy())
                inputs[r].append(U[j])
                automaton[r].append(int(q[r]))
        if progress is not None:
            progress(k + 1, horizon)
    if progress is not None:
        progress(horizon, horizon)
    m = input_dim(network)
    return [Run(np.array(states[r]), np.array(inputs[r]) if inputs[r] else np.zeros((0, m)),
                controller.accepting(np.array(automaton[r])), violation[r], accepted[r], True,
                {"automaton_states": automaton[r], "bound": int(bound[r])}) for r in range(R)]


def run_product_loop(network: Network, controller: ProductController, initial_states: Sequence[Sequence[float]],
                     runs: int, steps: int | None, rng: np.random.Generator,
                     progress: Callable[[int, int], None] | None = None, choose: str = "random") -> ProductLoop:
    """The closed loop of an ``ltl`` job: runs from each initial state in the controller's domain and from
    ``runs`` random states, uniform in cells drawn uniformly from the domain (as
    :func:`~.closed_loop.run_closed_loop`); ``steps``: ``options.closed_loop_steps`` (``None``: every run's own
    bound)."""
    starts, initial, X0 = closed_loop_starts(network, controller, initial_states, runs, rng)
    done = simulate_product(network, controller, X0, steps, rng, choose, progress)
    records = [(origin, x0, run) for (origin, x0), run in zip(starts, done)]
    for rec in initial:
        for origin, x0, run in records:
            if origin == "initial" and np.allclose(x0, rec["x0"]):
                rec.update(violation=run.violation, settled_at=run.settled_at, steps=int(run.inputs.shape[0]),
                           bound=run.extra["bound"])
    horizon = max([r.extra["bound"] for _, _, r in records], default=0) if steps is None else int(steps)
    return ProductLoop(records, initial, horizon)
