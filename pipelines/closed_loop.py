"""Closed loop: the concrete black boxes under a refined controller (Theorem 4.2, METHOD §6).

Refinement by the feedback refinement relation is memoryless quantization: measure ``x``, take its cell
``x̂``, apply any input of ``C(x̂)``, and step the concrete subsystems with ``w = M(x)``. Runs of the concrete
system are the end-to-end check of everything before: an abstraction that misses a transition or a
synthesis bug shows up as a run that leaves the controller's domain or misses the specification.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .grid import UniformGrid
from .network import Network
from .region import AbstractRegion

#: policy(x) -> admissible concrete inputs at x, shape (k, m_total); k = 0 outside the controller's domain.
#: A :class:`~pipelines.controller.Controller` may be passed instead: its ``choose`` draws one input directly.
Policy = Callable[[np.ndarray], np.ndarray]


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


def _cell_in(grid: UniformGrid, region: AbstractRegion | None, x: np.ndarray) -> bool:
    if region is None:
        return False
    idx, inside = grid.cell_of(x[None, :])
    return bool(inside[0] and region.contains(idx)[0])


def simulate(
    network: Network,
    policy: Policy | None,
    x0: np.ndarray,
    steps: int,
    rng: np.random.Generator,
    kind: str,
    target: AbstractRegion | None = None,
    avoid: AbstractRegion | None = None,
    choose: str = "random",
) -> Run:
    """Run the concrete system from ``x0`` for ``steps`` steps under ``policy`` (``None``: all inputs 0).

    ``choose`` picks among the admissible inputs: ``random`` (as in the paper's figures) or ``first``.
    A violation is recorded, and the run stopped, when the state leaves the concrete state box, leaves the
    controller's domain (no admissible input), enters the avoid set, or (``safe``) leaves the safe set; at the
    end, ``reach``/``reach_avoid`` runs must have visited the target and ``reach_and_stay`` runs must be in it.
    """
    grid = network.composed_state_grid()
    lb, ub = np.asarray(grid.lb), np.asarray(grid.ub)
    m = input_dim(network)
    xs = [np.asarray(x0, dtype=float)]
    us: list[np.ndarray] = []
    inside = [_cell_in(grid, target, xs[0])]
    violation = None
    for k in range(steps):
        x = xs[-1]
        if kind in ("reach", "reach_avoid") and policy is not None and inside[-1]:
            break  # reached: a reach controller's job ends here
        if np.any(x < lb) or np.any(x > ub):
            violation = f"step {k}: the state {x.tolist()} left the state set"
            break
        if avoid is not None and _cell_in(grid, avoid, x):
            violation = f"step {k}: the state entered the avoid set"
            break
        if kind == "safe" and policy is not None and not inside[-1]:
            violation = f"step {k}: the state left the safe set"
            break
        if policy is None:
            u = np.zeros(m)
        else:
            if hasattr(policy, "choose"):  # a Controller draws one input without listing them all
                u = policy.choose(x, rng, choose)
            else:
                options = policy(x)
                u = None if options.shape[0] == 0 else \
                    options[rng.integers(options.shape[0])] if choose == "random" else options[0]
            if u is None:
                violation = f"step {k}: the state {x.tolist()} is outside the controller's domain"
                break
        us.append(u)
        xs.append(step(network, x[None, :], u[None, :])[0])
        inside.append(_cell_in(grid, target, xs[-1]))
    states = np.array(xs)
    flags = np.array(inside)
    settled = None
    if flags.size and flags[-1]:
        outside = np.flatnonzero(~flags)
        settled = int(outside[-1] + 1) if outside.size else 0
    if violation is None and policy is not None:
        if kind in ("reach", "reach_avoid") and not flags.any():
            violation = f"the target was not reached in {steps} steps"
        elif kind == "reach_and_stay" and not flags[-1]:
            violation = f"not in the target after {steps} steps"
    inputs = np.array(us) if us else np.zeros((0, m))
    return Run(states, inputs, flags, violation, settled, policy is not None)
