"""Certified error bounds ``eps_j``: ``|M_j(x) - M̄_j x - b_j| <= eps_j`` on the state box (Lemma lem1, made sound).

Algorithm 3 as printed loops over every ``x̂`` of the full product grid, which is exponential in ``N``. Here
``eps_j`` is a single bound per output, certified on the support of row ``j`` only, per mode (``error`` in the
spec; docs/method.md §4):

* ``linear`` (the spec declares ``M`` affine, :func:`eps_linear`): ``M̄`` is identified exactly;
  ``eps_j = 2 * max held-out residual + a floating-point margin``. A residual above ``1e-9`` relative to the
  output scale refutes the declaration (:class:`CertificationError`, "not linear").
* ``certify`` (needs ``L_M``, :func:`eps_certify`): on the grid of the support coordinates (or a coarser uniform
  partition with at most ``max_certify_cells`` cells, down to one cell),
  ``|M_j(x) - M̄_j x - b_j| <= |M_j(c) - M̄_j c - b_j| + L_M ||r||_inf + sum_i |M̄_ji| r_i`` on a cell with
  centre ``c`` and half-widths ``r`` (the paper's Eq. (eps_hat) with the neighbourhood a cell, and with the
  linear part bounded over the cell instead of at one point). ``eps_j`` is the maximum over cells.

A given ``L_M`` is checked against slopes observed on random nearby pairs (:func:`check_lipschitz`, docs/method.md §3);
a larger slope is a :class:`LipschitzError`. Every bound is widened by a relative floating-point margin
``FP_RTOL`` (:func:`fp_margin`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pipelines.errors import CertificationError, LipschitzError
from pipelines.grid import UniformGrid
from pipelines.interconnection.grids import axis_grid, cell_bounds, unravel
from pipelines.interconnection.sampling import EVAL_ROWS, Sampler

__all__ = [
    "MAX_CERTIFY_CELLS",
    "LINEAR_RTOL",
    "FP_RTOL",
    "FP_ATOL",
    "fp_margin",
    "check_lipschitz",
    "eps_linear",
    "certify_axes",
    "eps_certify",
]

#: Largest number of cells of the support grid on which ``certify`` evaluates ``M`` (docs/method.md §4).
MAX_CERTIFY_CELLS = 4_000_000
#: Relative held-out residual above which a map declared linear is refuted.
LINEAR_RTOL = 1e-9
#: Relative floating-point margin added to every bound (values are sums of a few float64 products).
FP_RTOL = 1e-12
#: Absolute floor of the floating-point margin.
FP_ATOL = 1e-300


def fp_margin(row: np.ndarray, b: float, xmax: float) -> float:
    """Floating-point margin for ``M̄_j x + b_j`` over the box (``xmax = max |x|``)."""
    return FP_RTOL * (np.abs(row).sum() * xmax + abs(b)) + FP_ATOL


def check_lipschitz(sample: Sampler, L: float, count: int, rng: np.random.Generator) -> None:
    """Given ``L_M`` against slopes of random nearby pairs (docs/method.md §3): a larger slope is unsound.

    Pairs are ``x`` and ``x + d`` with ``d`` up to one cell width per coordinate (scaled down at random by up
    to 100), clipped to the box; the slope is ``|ΔM_j| / ||Δx||_inf``.
    """
    eta = np.asarray(sample.network.composed_state_grid().eta)
    x1 = sample.uniform(count, rng)
    scale = 10.0 ** rng.uniform(-2, 0, (count, 1))
    x2 = np.clip(x1 + rng.uniform(-1, 1, x1.shape) * eta * scale, sample.lb, sample.ub)
    dx = np.abs(x2 - x1).max(axis=1)
    keep = dx > 0
    x1, x2, dx = x1[keep], x2[keep], dx[keep]
    y1, y2 = sample(x1), sample(x2)
    dy = np.abs(y2 - y1)
    tol = FP_RTOL * np.maximum(np.abs(y1), np.abs(y2)) + FP_ATOL
    bad = dy > L * dx[:, None] * (1 + 1e-9) + tol
    if bad.any():
        r, j = np.unravel_index(int(np.argmax(bad)), bad.shape)
        slope = dy[r, j] / dx[r]
        raise LipschitzError(
            f"interconnection map output w{j}: slope {slope:.6g} between x = {x1[r].tolist()} and "
            f"x' = {x2[r].tolist()} exceeds the given Lipschitz constant L_M = {L} (infinity norm); the error "
            f"bound would be unsound: raise interconnection.lipschitz to at least {slope:.6g}"
        )


def eps_linear(
    j: int, row: np.ndarray, b: float, X: np.ndarray, Y: np.ndarray, xmax: float, n_support: int, n_train: int
) -> tuple[float, float]:
    """``eps_j`` of a map declared linear: ``2 * max held-out residual + fp margin``.

    ``X``, ``Y``: held-out states (H, n) and map values (H, p). Returns ``(eps_j, max residual)``.

    Raises
    ------
    CertificationError
        If the held-out residual exceeds ``LINEAR_RTOL`` of the output scale: the map is not linear.
    """
    res = np.abs(Y[:, j] - (X @ row + b))
    worst = float(res.max(initial=0.0))
    scale = max(float(np.abs(Y[:, j]).max(initial=0.0)), np.abs(row).sum() * xmax + abs(b))
    if worst > LINEAR_RTOL * scale:
        r = int(np.argmax(res))
        raise CertificationError(
            f"interconnection output w{j}: the map is declared linear (error: linear) but is not linear: "
            f"held-out residual {worst:.6g} (relative {worst / scale:.3g}) at x = {X[r].tolist()}; use "
            "error: certify with a Lipschitz constant"
            + (
                f" (or give more samples: {n_train} cannot identify {n_support} coefficients and an intercept)"
                if n_train <= n_support
                else ""
            )
        )
    return 2.0 * worst + fp_margin(row, b, xmax), worst


def certify_axes(
    grids: Sequence[UniformGrid], cap: int
) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
    """Cells on which ``certify`` evaluates ``M``: per support axis, centres and half-widths.

    The state grids' clipped cells if their product has at most ``cap`` cells; otherwise a uniform partition
    of the support box into ``k`` parts per axis with ``k^s <= cap`` (down to ``k = 1``: one cell, the box).
    """
    sizes = [g.size for g in grids]
    if math.prod(sizes) <= cap:
        bounds = [cell_bounds(g) for g in grids]
        info = {"source": "state grid", "cells_per_axis": sizes}
    else:
        s = len(grids)
        k = 1
        while (k + 1) ** s <= cap:
            k += 1
        bounds = []
        for g in grids:
            edges = np.linspace(g.lb[0], g.ub[0], k + 1)
            bounds.append(((edges[:-1] + edges[1:]) / 2, (edges[1:] - edges[:-1]) / 2))
        info = {"source": "uniform partition", "cells_per_axis": [k] * s}
    info["max_half_width"] = [float(r.max()) for _, r in bounds]
    return [c for c, _ in bounds], [r for _, r in bounds], info


def eps_certify(
    sample: Sampler,
    j: int,
    support: Sequence[int],
    row: np.ndarray,
    b: float,
    L: float,
    cap: int,
    xmax: float,
) -> tuple[float, dict]:
    """``eps_j`` from the Lipschitz bound on the support cells (Lemma lem1 made sound, docs/method.md §4).

    On a cell with centre ``c`` and half-widths ``r`` (support coordinates; the others are held at the box
    centre, which the support validation justifies):
    ``|M_j(x) - M̄_j x - b| <= |M_j(c) - M̄_j c - b| + L_M max_i r_i + sum_i |M̄_ji| r_i``.

    Returns ``(eps_j without the support-validation change, resolution info)``.
    """
    grid = sample.network.composed_state_grid()
    grids = [axis_grid(grid, i) for i in support]
    centres, radii, info = certify_axes(grids, cap)
    a = row[list(support)]
    shape = tuple(c.size for c in centres)
    total = math.prod(shape)
    worst = 0.0
    for start in range(0, total, EVAL_ROWS):
        flat = np.arange(start, min(total, start + EVAL_ROWS))
        idx = unravel(flat, shape)
        X = np.repeat(sample.centre[None], flat.size, axis=0)
        r_max = np.zeros(flat.size)
        lin_r = np.zeros(flat.size)
        for d, i in enumerate(support):
            X[:, i] = centres[d][idx[d]]
            r = radii[d][idx[d]]
            r_max = np.maximum(r_max, r)
            lin_r += abs(a[d]) * r
        y = sample(X, columns=[j])[:, j]
        bound = np.abs(y - (X @ row + b)) + L * r_max + lin_r
        worst = max(worst, float(bound.max(initial=0.0)))
    info["cells"] = total
    return worst + fp_margin(row, b, xmax), info
