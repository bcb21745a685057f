"""Closed loop: the concrete black boxes under a refined controller (Theorem 4.2, docs/method.md §6).

Refinement by the feedback refinement relation is memoryless quantization: measure ``x``, take its cell
``x̂``, apply any input of ``C(x̂)``, and step the concrete subsystems with ``w = M(x)``. Runs of the concrete
system are the end-to-end check of everything before: an abstraction that misses a transition or a
synthesis bug shows up as a run that leaves the controller's domain or misses the specification.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from pipelines.grid import UniformGrid
from pipelines.network import Network
from pipelines.spec.regions import AbstractRegion

#: policy(x) -> admissible concrete inputs at x, shape (k, m_total); k = 0 outside the controller's domain.
#: A :class:`~pipelines.controller.Controller` may be passed instead: its ``choose`` draws one input directly.
Policy = Callable[[np.ndarray], np.ndarray]


class InputChooser(Protocol):
    """What :func:`simulate_many` uses of a :class:`~pipelines.controller.Controller` passed as the policy."""

    def choose_many(self, X: np.ndarray, rng: np.random.Generator, how: str = ...) -> list[np.ndarray | None]: ...


def input_dim(network: Network) -> int:
    return sum(s.m for s in network.subsystems)


def step(network: Network, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """One step of the concrete interconnected system.

    Parameters
    ----------
    x : ndarray, shape (R, n_total)
        Composed states (subsystem states concatenated).
    u : ndarray, shape (R, m_total)
        Composed external inputs.

    Returns
    -------
    ndarray, shape (R, n_total)
    """
    w = network.interconnection_map(x)
    out = np.empty_like(x)
    col = 0
    for s in network.subsystems:
        xs = x[:, s.state_offset : s.state_offset + s.n]
        us = u[:, col : col + s.m]
        ws = w[:, list(s.reads)] if s.reads else np.zeros((x.shape[0], 0))
        out[:, s.state_offset : s.state_offset + s.n] = s.dynamics(xs, us, ws)
        col += s.m
    return out


@dataclass
class Run:
    """One closed-loop run."""

    states: np.ndarray  # (K+1, n_total)
    inputs: np.ndarray  # (K, m_total)
    in_target: np.ndarray  # (K+1,) bool: the state's cell is in the target (or safe) region
    violation: str | None = None
    settled_at: int | None = None  # first step from which the run stays in the target to the end
    controlled: bool = True
    extra: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "states": self.states.tolist(),
            "inputs": self.inputs.tolist(),
            "in_target": self.in_target.tolist(),
            "violation": self.violation,
            "settled_at": self.settled_at,
            "controlled": self.controlled,
        }


#: How a run chooses among the admissible inputs: drawn at random (the paper's figures), the first one, or the
#: previous input while it stays admissible, else the first (no chattering between extreme inputs inside a target).
CHOOSE = ("random", "first", "steady")


def input_codes(grids: Sequence[UniformGrid], U: np.ndarray) -> np.ndarray:
    """Per-subsystem flat codes of concrete inputs (grid points), shape (B, m_total) or (m_total,) -> (B, N); -1
    where an input is off its subsystem's grid."""
    U = np.asarray(U, dtype=float).reshape(-1, sum(g.dim for g in grids))
    out = np.empty((U.shape[0], len(grids)), dtype=np.int64)
    col = 0
    for s, g in enumerate(grids):
        k = np.rint((U[:, col:col + g.dim] - np.asarray(g.origin)) / g.eta_array).astype(np.int64)
        k -= np.asarray(g.k_lo, dtype=np.int64)
        on = g.on_grid(k)
        out[:, s] = np.where(on, g.ravel(np.where(on[:, None], k, 0)), -1)
        col += g.dim
    return out


def admits(controller: Any, x: np.ndarray, u: np.ndarray) -> bool:
    """Whether the concrete input ``u`` (grid points, shape (m_total,)) is admissible at the state ``x`` under a
    controller: its cell's input set (one BDD conjunction per subsystem), or its listed inputs."""
    idx = controller.cell(np.asarray(x, dtype=float))
    codes = input_codes(controller.input_grids, u)[0].tolist()
    if idx is None or min(codes) < 0:
        return False
    model = getattr(controller, "model", None)
    if model is not None and hasattr(controller, "input_set"):  # a BDD controller: no listing of its inputs
        f = controller.input_set(idx)
        for digit, code in zip(model.u_digits(), codes):
            f = f & model.interval(digit, code, code)
        return f != model.bdd.false
    return bool(np.any(np.all(controller.input_indices(idx) == np.asarray(codes), axis=1)))


def _steady(policy: Any, X: np.ndarray, previous: list[np.ndarray | None], rng: np.random.Generator
            ) -> list[np.ndarray | None]:
    """``choose="steady"``: the previous input at each row of ``X`` where it is still admissible, else the first."""
    kept = _still_allowed(policy, X, previous)
    chosen = [u if kept[k] else None for k, u in enumerate(previous)]
    redo = [k for k, u in enumerate(chosen) if u is None]
    if redo:
        for k, u in zip(redo, policy.choose_many(X[redo], rng, "first")):
            chosen[k] = u
    return chosen


def _still_allowed(policy: Any, X: np.ndarray, previous: list[np.ndarray | None]) -> np.ndarray:
    """Whether each row's previous input (``None``: none) is admissible at its state, shape (B,): for all rows at
    once where the controller answers for many (:meth:`~pipelines.controller.Controller.allows`), else row by row."""
    rows = [k for k, u in enumerate(previous) if u is not None]
    out = np.zeros(len(previous), dtype=bool)
    allows = getattr(policy, "allows", None)
    if rows and allows is not None:
        idx, on_grid = policy.cells(X[rows])
        codes = input_codes(policy.input_grids, np.array([previous[k] for k in rows]))
        fits = on_grid & (codes >= 0).all(axis=1)
        answer = allows(idx, np.maximum(codes, 0))
        if answer is not None:
            out[rows] = fits & answer
            return out
    for k in rows:
        out[k] = admits(policy, X[k], np.asarray(previous[k]))
    return out


def _cells_in(grid: UniformGrid, region: AbstractRegion | None, x: np.ndarray) -> np.ndarray:
    """Whether each state's cell, shape (R, n_total) -> (R,), is on the grid and in ``region``."""
    if region is None:
        return np.zeros(x.shape[0], dtype=bool)
    idx, inside = grid.cell_of(x)
    return inside & region.contains(idx)


def simulate(network: Network, policy: Policy | InputChooser | None, x0: np.ndarray, steps: int,
             rng: np.random.Generator, kind: str, target: AbstractRegion | None = None,
             avoid: AbstractRegion | None = None, choose: str = "random", safe: AbstractRegion | None = None) -> Run:
    """Run the concrete system from ``x0`` for ``steps`` steps under ``policy`` (``None``: all inputs 0).

    ``choose`` picks among the admissible inputs (:data:`CHOOSE`): ``random`` (as in the paper's figures),
    ``first``, or ``steady``: the previous input while it is admissible, else the first (deterministic; the
    figures' choice, which does not chatter between extreme inputs where several are admissible).
    ``target`` is the safe set for a ``safe`` specification; ``safe`` the optional safe set of the other kinds
    (:func:`~pipelines.spec.regions.closed_loop_regions` gives all three).
    A violation is recorded, and the run stopped, when the state leaves the concrete state box, leaves the
    controller's domain (no admissible input), enters the avoid set, or leaves the safe set (``target`` of a
    ``safe`` specification, ``safe`` of any kind); a ``reach``/``reach_avoid`` run ends when its state is in the
    target (and none of those holds). At the end, ``reach``/``reach_avoid`` runs must have visited the target
    and ``reach_and_stay`` runs must be in it.
    """
    x0 = np.asarray(x0, dtype=float)
    return simulate_many(network, policy, x0[None, :], steps, rng, kind, target, avoid, choose, safe=safe)[0]


def simulate_many(
    network: Network,
    policy: Policy | InputChooser | None,
    x0: np.ndarray,
    steps: int,
    rng: np.random.Generator,
    kind: str,
    target: AbstractRegion | None = None,
    avoid: AbstractRegion | None = None,
    choose: str = "random",
    progress: Callable[[int, int], None] | None = None,
    safe: AbstractRegion | None = None,
) -> list[Run]:
    """:func:`simulate` from each row of ``x0``, shape (R, n_total), the runs in lockstep.

    Every run is the run :func:`simulate` defines (same checks, same stopping rules); the black boxes are
    evaluated once per step for all runs still going (one at a time, 100 tank runs cost seconds: eleven expression
    evaluations per step and run). Inputs are drawn run by run, in row order, from ``rng``:
    with one row this is exactly :func:`simulate`. ``progress(step, steps)`` is called after each step and
    with ``(steps, steps)`` at the end, also when every run ended early.
    """
    runs = _Lockstep(network, policy, np.array(x0, dtype=float, ndmin=2), kind, (target, avoid, safe), choose)
    for k in range(steps):
        live = np.flatnonzero(runs.going)
        if live.size == 0:
            break
        X = runs.states(live)
        choosing = runs.check(k, live, X)
        runs.advance(k, live, X, choosing, runs.choose_inputs(X, live, choosing, rng))
        if progress is not None and k + 1 < steps:
            progress(k + 1, steps)
    live = np.flatnonzero(runs.going)
    if live.size:  # the state after the last step is checked too: leaving S there is a violation as well
        runs.check(steps, live, runs.states(live))
    if progress is not None:  # also when every run ended early
        progress(steps, steps)
    return [_finish(np.array(runs.xs[r]), runs.us[r], np.array(runs.inside[r]), runs.violation[r],
                    policy is not None, kind, steps, runs.m) for r in range(len(runs.xs))]


class _Lockstep:
    """The runs of :func:`simulate_many`, advanced together: per run its states, inputs, target flags (the
    state's cell in ``target``), violation and whether it goes on; and the state checks and input choices of
    :func:`simulate` applied at once to the runs still going at a step."""

    def __init__(self, network: Network, policy: Policy | InputChooser | None, x: np.ndarray, kind: str,
                 regions: tuple[AbstractRegion | None, AbstractRegion | None, AbstractRegion | None],
                 choose: str) -> None:
        self.network, self.policy, self.kind, self.choose = network, policy, kind, choose
        self.target, self.avoid, self.safe = regions
        self.grid = network.composed_state_grid()
        self.lb, self.ub = np.asarray(self.grid.lb), np.asarray(self.grid.ub)
        self.m = input_dim(network)
        R = x.shape[0]
        self.xs: list[list[np.ndarray]] = [[row] for row in x]
        self.us: list[list[np.ndarray]] = [[] for _ in range(R)]
        self.inside: list[list[bool]] = [[bool(v)] for v in _cells_in(self.grid, self.target, x)]
        self.violation: list[str | None] = [None] * R
        self.going = np.ones(R, dtype=bool)

    def states(self, live: np.ndarray) -> np.ndarray:
        """The present states of the runs ``live``, shape (len(live), n_total)."""
        return np.array([self.xs[r][-1] for r in live])

    def _stop(self, r: int, violation: str | None) -> None:
        self.going[r] = False
        if violation is not None:
            self.violation[r] = violation

    def check(self, k: int, live: np.ndarray, X: np.ndarray) -> list[int]:
        """The state checks at step ``k`` of the runs ``live`` (states ``X``): stops the runs that violate the
        specification or reached a reach target; returns the positions in ``live`` of the runs going on."""
        controlled = self.policy is not None
        now_in = np.array([self.inside[r][-1] for r in live])
        out_of_box = np.any((X < self.lb) | (X > self.ub), axis=1)
        in_avoid = _cells_in(self.grid, self.avoid, X)
        in_safe = _cells_in(self.grid, self.safe, X) if self.safe is not None else np.ones(live.size, dtype=bool)
        going_on = []
        for j, r in enumerate(live):
            # Arriving in the target ends a reach run only if the way there was kept: a state out of the box,
            # in A or out of S is a violation even on a target cell.
            if out_of_box[j]:
                self._stop(r, f"step {k}: the state {X[j].tolist()} left the state set")
            elif in_avoid[j]:
                self._stop(r, f"step {k}: the state entered the avoid set")
            elif controlled and (not in_safe[j] or (self.kind == "safe" and not now_in[j])):
                self._stop(r, f"step {k}: the state left the safe set")
            elif self.kind in ("reach", "reach_avoid") and controlled and now_in[j]:
                self._stop(r, None)  # reached: a reach controller's job ends here
            else:
                going_on.append(j)
        return going_on

    def choose_inputs(self, X: np.ndarray, live: np.ndarray, choosing: list[int], rng: np.random.Generator
                      ) -> list[np.ndarray | None]:
        """An admissible input for each run ``live[j]``, ``j`` in ``choosing`` (``None`` outside the controller's
        domain): refinement takes any input of the state's cell (Theorem 4.2), picked as ``choose`` says. Only
        the choices draw from ``rng``, in row order, as :func:`simulate` does run by run."""
        policy, choose = self.policy, self.choose
        if policy is None:
            return [np.zeros(self.m) for _ in choosing]
        if not choosing:
            return []
        previous = [self.us[live[j]][-1] if self.us[live[j]] else None for j in choosing]
        if hasattr(policy, "choose_many") and choose == "steady":
            return _steady(policy, X[choosing], previous, rng)
        if hasattr(policy, "choose_many"):  # a Controller draws inputs without listing them all
            return policy.choose_many(X[choosing], rng, choose)
        chosen: list[np.ndarray | None] = []
        for j, before in zip(choosing, previous):
            options = policy(X[j])
            kept = (before is not None and choose == "steady"
                    and bool(np.any(np.all(np.isclose(options, before), axis=1))))
            chosen.append(None if options.shape[0] == 0 else before if kept else
                          options[rng.integers(options.shape[0])] if choose == "random" else options[0])
        return chosen

    def advance(self, k: int, live: np.ndarray, X: np.ndarray, choosing: list[int],
                chosen: list[np.ndarray | None]) -> None:
        """Step the concrete network (:func:`step`) once for every run ``live[j]`` that has an input; a run
        without one (outside the controller's domain) stops with that violation."""
        stepping, U = [], []
        for j, u in zip(choosing, chosen):
            if u is None:
                self._stop(live[j], f"step {k}: the state {X[j].tolist()} is outside the controller's domain")
                continue
            stepping.append(j)
            U.append(u)
        if not stepping:
            return
        sel = np.asarray(stepping)
        nxt = step(self.network, X[sel], np.array(U))
        flags = _cells_in(self.grid, self.target, nxt)
        for j, u, xn, f in zip(sel.tolist(), U, nxt, flags.tolist()):
            r = live[j]
            self.us[r].append(u)
            self.xs[r].append(xn)
            self.inside[r].append(f)


def _finish(states: np.ndarray, us: list[np.ndarray], flags: np.ndarray, violation: str | None, controlled: bool,
            kind: str, steps: int, m: int) -> Run:
    """The run's record, with the end-of-run checks of :func:`simulate`."""
    settled = None
    if flags.size and flags[-1]:
        outside = np.flatnonzero(~flags)
        settled = int(outside[-1] + 1) if outside.size else 0
    if violation is None and controlled:
        if kind in ("reach", "reach_avoid") and not flags.any():
            violation = f"the target was not reached in {steps} steps"
        elif kind == "reach_and_stay" and not flags[-1]:
            violation = f"not in the target after {steps} steps"
    inputs = np.array(us) if us else np.zeros((0, m))
    return Run(states, inputs, flags, violation, settled, controlled)


@dataclass
class ClosedLoop:
    """Closed-loop runs from the spec's initial states in the controller's domain and from random domain states.

    Attributes
    ----------
    runs : list of (origin, x0, Run)
        ``origin`` is ``"initial"`` (a spec's initial state) or ``"random"``.
    initial_states : list of dict
        Per initial state of the spec: ``x0``, ``in_domain`` and, for one in the domain, its run's
        ``violation``, ``settled_at`` and ``steps``.
    steps : int
        The horizon of every run.
    """

    runs: list[tuple[str, np.ndarray, Run]]
    initial_states: list[dict]
    steps: int

    @property
    def violations(self) -> int:
        return sum(1 for _, _, r in self.runs if r.violation)

    @property
    def first_violation(self) -> str | None:
        for _, x0, r in self.runs:
            if r.violation:
                return f"from {x0.tolist()}: {r.violation}"
        return None

    def summary(self) -> dict:
        """The report's ``closed_loop`` entry."""
        settled = [r.settled_at for _, _, r in self.runs if r.settled_at is not None]
        return {
            "runs": len(self.runs),
            "violations": self.violations,
            "first_violation": self.first_violation,
            "steps": self.steps,
            "steps_to_reach": ({"min": min(settled), "mean": float(np.mean(settled)), "max": max(settled)}
                               if settled else None),
            "initial_states": self.initial_states,
        }


def closed_loop_starts(network: Network, controller: Any, initial_states: Sequence[Sequence[float]], runs: int,
                       rng: np.random.Generator) -> tuple[list[tuple[str, np.ndarray]], list[dict[str, Any]], np.ndarray]:
    """Where the closed-loop runs start: each initial state in the controller's domain, then ``runs`` random states,
    uniform in cells drawn uniformly from the domain. Returns the starts (origin, state), one record per initial
    state (``x0``, ``in_domain``) and the starts as one array (R, n)."""
    starts: list[tuple[str, np.ndarray]] = []
    initial: list[dict[str, Any]] = []
    for x in initial_states:
        x0 = np.asarray(x, dtype=float)
        idx = controller.cell(x0)
        inside = idx is not None and bool(controller.in_domain(idx[None, :])[0])
        initial.append({"x0": x0.tolist(), "in_domain": inside})
        if inside:
            starts.append(("initial", x0))
    cells = controller.sample_cells(runs, rng) if runs else np.zeros((0, network.state_dim), dtype=np.int64)
    if cells.shape[0]:
        lo, hi = controller.state_grid.clipped_cells(cells)
        starts += [("random", x) for x in rng.uniform(lo, hi)]
    return starts, initial, np.array([x0 for _, x0 in starts]).reshape(len(starts), network.state_dim)


def run_closed_loop(
    network: Network,
    controller: Any,
    initial_states: Sequence[Sequence[float]],
    runs: int,
    steps: int,
    rng: np.random.Generator,
    kind: str,
    target: AbstractRegion | None = None,
    avoid: AbstractRegion | None = None,
    policy: Policy | None = None,
    progress: Callable[[int, int], None] | None = None,
    safe: AbstractRegion | None = None,
) -> ClosedLoop:
    """Refinement in closed loop (Theorem 4.2): the concrete network under ``controller`` from each initial state
    in its domain and from ``runs`` random states, uniform in cells drawn uniformly from its domain.

    ``controller`` is a :class:`~pipelines.controller.Controller`; ``policy`` (default: the controller itself, which
    draws one admissible input directly) is what chooses the inputs. ``target``, ``avoid``, ``safe``: as in
    :func:`simulate`.
    """
    starts, initial, X0 = closed_loop_starts(network, controller, initial_states, runs, rng)
    done = simulate_many(network, controller if policy is None else policy, X0, steps, rng, kind, target, avoid,
                         progress=progress, safe=safe)
    records = [(origin, x0, run) for (origin, x0), run in zip(starts, done)]
    for rec in initial:
        for origin, x0, run in records:
            if origin == "initial" and np.allclose(x0, rec["x0"]):
                rec.update(violation=run.violation, settled_at=run.settled_at, steps=int(run.inputs.shape[0]))
    return ClosedLoop(records, initial, steps)
