"""The exact-image-box reference of a linear single system: the tightest sound interval abstraction (issue 46).

For an affine map ``x+ = A x + B u + c``, the image of a box with centre ``x_c`` and half-widths ``r`` is contained
in the box ``A x_c + B u + c ± |A| r``, and that box is its interval hull: each component reaches both bounds at a
vertex of the cell. So the relation that maps each (cell, input) to the cells this box meets, with the state cells
clipped to the state box as the per-cell stage samples them (docs/method.md §1, §2), is contained in every sound
relation built from boxes of successor cells: it is the reference a data-driven abstraction is compared with.
Nothing is sampled and no constant is assumed: the map is read as affine from the black box and checked
(:func:`identify_affine`), and a map that is not affine is refused.

The reference uses the per-cell stage's conventions exactly, so that a difference is the bound's, not the
rounding's: the box rounded outwards by :func:`~pipelines.abstraction.growth_bound.widen`, successor cells by
:meth:`~pipelines.grid.UniformGrid.cells_touching`, blocking where the box leaves the state box, and the cells no
fixed point can let in blocking under every input (:func:`~pipelines.spec.regions.never_winning`). Its game is
solved by the explicit back end (:mod:`pipelines.synthesis.explicit`), as a job solves a single system's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipelines.abstraction.growth_bound import widen
from pipelines.abstraction.relation import SubsystemRelation
from pipelines.network import Network, Subsystem

#: Largest deviation from the identified affine map, relative to the magnitude of its terms, that still counts as
#: affine: the identification's own rounding (differences of float64 values, an ODE's integrator) is far below it.
AFFINE_RTOL = 1e-9
#: Random (state, input) points on which an identified map is checked.
CHECK_POINTS = 4096
#: (cell, input) pairs per bulk step (bounds the float64 temporaries to a few hundred MB).
BLOCK_PAIRS = 1 << 21


class NotAffine(ValueError):
    """The black box is not an affine map (the reference is only defined for one)."""


@dataclass(frozen=True)
class AffineMap:
    """``x+ = A x + B u + c``: ``A`` of shape (n, n), ``B`` of shape (n, m), ``c`` of shape (n,).

    ``residual`` is the largest deviation seen on the check points, relative to the magnitude of the terms."""

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray
    residual: float

    def __call__(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return x @ self.A.T + u @ self.B.T + self.c


def single_system(network: Network) -> Subsystem:
    """The network's one subsystem, which reads no internal variable.

    Raises
    ------
    NotAffine
        A network of several subsystems, or one with internal inputs: no exact-image-box reference here.
    """
    if len(network.subsystems) != 1 or network.subsystems[0].reads:
        raise NotAffine(f"the exact-image-box reference is for a single system without internal inputs; this network "
                        f"has {len(network.subsystems)} subsystems"
                        + (" reading internal variables" if any(s.reads for s in network.subsystems) else ""))
    return network.subsystems[0]


def identify_affine(sub: Subsystem, rng: np.random.Generator | None = None, points: int = CHECK_POINTS,
                    rtol: float = AFFINE_RTOL) -> AffineMap:
    """Read ``A``, ``B``, ``c`` off the black box and check that it is that affine map.

    ``A``'s column ``j`` is the change of ``f`` from the centre of the state box to the point moved to its upper
    bound along coordinate ``j`` alone, divided by that move (``B`` likewise on the input box): points in the boxes,
    where the black box is defined. Then ``f`` is compared with ``A x + B u + c`` at ``points`` random states of the
    box under random points of the input grid.

    Raises
    ------
    NotAffine
        Naming the state and input where the map departs from the affine one, and by how much.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    xg, ug = sub.state_grid, sub.input_grid
    n, m = sub.n, sub.m
    x_lb, x_ub = np.asarray(xg.lb, dtype=float), np.asarray(xg.ub, dtype=float)
    u_lb, u_ub = np.asarray(ug.lb, dtype=float), np.asarray(ug.ub, dtype=float)
    x0, u0 = (x_lb + x_ub) / 2, (u_lb + u_ub) / 2
    hx, hu = x_ub - x0, u_ub - u0
    # The centre, then one point per coordinate of x and of u, in one call of the black box.
    X = np.repeat(x0[None], 1 + n + m, axis=0)
    U = np.repeat(u0[None], 1 + n + m, axis=0)
    X[1 + np.arange(n), np.arange(n)] += hx
    U[1 + n + np.arange(m), np.arange(m)] += hu
    F = np.asarray(sub.dynamics(X, U, np.zeros((1 + n + m, 0))), dtype=float).reshape(1 + n + m, n)
    with np.errstate(divide="ignore", invalid="ignore"):  # a box of zero width along a coordinate: no slope there
        A = np.where(hx[None] > 0, (F[1:1 + n] - F[0]).T / hx[None], 0.0)
        B = np.where(hu[None] > 0, (F[1 + n:] - F[0]).T / hu[None], 0.0) if m else np.zeros((n, 0))
    c = F[0] - A @ x0 - B @ u0
    affine = AffineMap(A, B, c, 0.0)

    xs = rng.uniform(x_lb, x_ub, (points, n))
    us = ug.all_points()[rng.integers(0, ug.size, points)]
    f = np.asarray(sub.dynamics(xs, us, np.zeros((points, 0))), dtype=float).reshape(points, n)
    g = affine(xs, us)
    scale = np.abs(xs) @ np.abs(A).T + np.abs(us) @ np.abs(B).T + np.abs(c) + np.abs(f) + 1e-300
    rel = np.abs(f - g) / scale
    worst = np.unravel_index(int(np.argmax(rel)), rel.shape)
    residual = float(rel[worst])
    if not residual <= rtol:  # also refuses a NaN
        k, i = int(worst[0]), int(worst[1])
        raise NotAffine(
            f"subsystem '{sub.name}' is not affine: at x = {xs[k].tolist()}, u = {us[k].tolist()} component {i} of "
            f"f is {f[k, i]!r}, the affine map read at the centre of its boxes gives {g[k, i]!r} (relative "
            f"deviation {residual:.3g} > {rtol:g}); the exact-image-box reference is for linear (affine) dynamics")
    return AffineMap(A, B, c, residual)


def reference_relation(sub: Subsystem, affine: AffineMap, dead: np.ndarray | None = None,
                       block_pairs: int = BLOCK_PAIRS) -> SubsystemRelation:
    """The exact-image-box relation of ``sub`` under ``affine``, as the per-cell stage stores a relation.

    Parameters
    ----------
    dead : ndarray of bool, shape (n_x,), optional
        Cells no fixed point can let in (:func:`~pipelines.spec.regions.never_winning`): blocking under every
        input, as the job leaves them.

    Returns
    -------
    SubsystemRelation
        ``lo``, ``hi`` of shape ``(n_x, n_u, 1, n)``, ``blocking`` of shape ``(n_x, n_u, 1)``; method ``exact``.
    """
    xg, ug = sub.state_grid, sub.input_grid
    n_x, n_u, n = xg.size, ug.size, sub.n
    lb, ub = np.asarray(xg.lb), np.asarray(xg.ub)
    top = np.asarray(xg.shape) - 1
    absA = np.abs(affine.A)
    drive = ug.all_points() @ affine.B.T + affine.c  # (n_u, n): B u + c per input
    lo = np.empty((n_x, n_u, 1, n), dtype=np.int32)
    hi = np.empty_like(lo)
    blocking = np.empty((n_x, n_u, 1), dtype=bool)
    step = max(1, block_pairs // max(1, n_u))
    for start in range(0, n_x, step):  # blocks of cells, each in one bulk pass
        stop = min(n_x, start + step)
        cl, ch = xg.clipped_cells(xg.unravel(np.arange(start, stop)))
        centre = ((cl + ch) / 2) @ affine.A.T  # (c, n)
        radius = ((ch - cl) / 2) @ absA.T
        mid = centre[:, None, :] + drive[None]  # (c, n_u, n)
        a, b = widen((mid - radius[:, None, :]).reshape(-1, n), (mid + radius[:, None, :]).reshape(-1, n))
        block = np.any((a < lb) | (b > ub), axis=1)
        first, last = xg.cells_touching(a, b)
        first, last = np.clip(first, 0, top), np.clip(last, 0, top)
        if dead is not None:
            block |= np.repeat(dead[start:stop], n_u)
        lo[start:stop] = np.where(block[:, None], 0, first).reshape(stop - start, n_u, 1, n)
        hi[start:stop] = np.where(block[:, None], -1, last).reshape(stop - start, n_u, 1, n)
        blocking[start:stop] = block.reshape(stop - start, n_u, 1)
    return SubsystemRelation("exact", lo, hi, blocking, 0.0, 0.0)


def exact_reference(spec: Any, allowed_modules: Any = None) -> dict[str, Any]:
    """A linear single system's exact-image-box relation and its game, solved explicitly.

    Parameters
    ----------
    spec : JobSpec
        The job; its one subsystem must be affine (else :class:`NotAffine`).

    Returns
    -------
    dict
        JSON-ready: ``states``, ``transitions``, ``domain_states`` (of the spec's fixed point; the first of several),
        ``domains`` (every fixed point's), ``A``, ``B``, ``c``, ``residual``, and the seconds of the relation and of
        the game.
    """
    from pipelines.network import build_network
    from pipelines.spec.regions import never_winning, spec_regions
    from pipelines.synthesis import explicit

    network = build_network(spec, allowed_modules)
    sub = single_system(network)
    affine = identify_affine(sub, np.random.default_rng(spec.options.seed))
    t0 = time.perf_counter()
    dead = never_winning(spec, network, spec_regions(spec, network))
    relation = reference_relation(sub, affine, dead)
    relation_seconds = time.perf_counter() - t0
    grid = network.composed_state_grid()
    t0 = time.perf_counter()
    game = explicit.ExplicitGame.from_relation(relation, grid.shape)
    results = explicit.solve(game, spec.specification, grid, tuple(spec.options.fixed_points))
    domains = {k: r.domain_states for k, r in results.items()}
    return {"states": grid.size, "transitions": explicit.transitions(relation),
            "domain_states": next(iter(domains.values())), "domains": domains,
            "A": affine.A.tolist(), "B": affine.B.tolist(), "c": affine.c.tolist(), "residual": affine.residual,
            "relation_seconds": relation_seconds, "game_seconds": time.perf_counter() - t0}


__all__ = ["AffineMap", "NotAffine", "exact_reference", "identify_affine", "reference_relation", "single_system"]
