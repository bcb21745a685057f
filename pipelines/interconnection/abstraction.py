"""Algorithm 3 (IA) without the exponential loop: :func:`abstract_interconnection`.

The steps: sample ``M`` and fit lasso rows (Eq. (lasso), :mod:`~pipelines.interconnection.learning`); fix the
supports by the dependence test and refit; decompose ``M̄`` by MDec (Algorithm 2,
:mod:`~pipelines.interconnection.mdec`); certify ``eps_j`` per output
(:mod:`~pipelines.interconnection.certification`) or build a ``direct`` node; then the grids of the
intermediate variables and the node relations in topological order (:mod:`~pipelines.interconnection.nodes`).
An output whose support exceeds ``sigma`` in ``direct`` mode falls back to ``certify`` + MDec (recorded per
output in ``output_modes``).

Beyond the paper: the training and support-check counts grow with the number of coordinates
(:func:`~pipelines.interconnection.sampling.training_count`, :func:`~pipelines.interconnection.sampling.check_count`);
the joint support check adds the coordinates the one-at-a-time test missed
(:func:`~pipelines.interconnection.learning.complete_support`); and an output whose certified range covers its
internal box everywhere gets one node without inputs, the relation its tree would be
(:func:`~pipelines.interconnection.nodes.covers_box`; listed in ``details["whole_box_outputs"]``).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from pipelines.errors import LipschitzError, SpecError
from pipelines.grid import UniformGrid
from pipelines.interconnection.certification import MAX_CERTIFY_CELLS, check_lipschitz, eps_certify, eps_linear
from pipelines.interconnection.grids import axis_grid
from pipelines.interconnection.learning import complete_support, dependence, lasso_row, refit, support_of
from pipelines.interconnection.mdec import mdec
from pipelines.interconnection.nodes import box_node, covers_box, direct_node, intermediate_grid, linear_node
from pipelines.interconnection.reduction import REDUCTIONS, check_reduction, reduction_nodes
from pipelines.interconnection.relation import InterconnectionAbstraction, NodeRelation
from pipelines.interconnection.sampling import Sampler, check_count, training_count
from pipelines.network import Network

__all__ = ["abstract_interconnection", "empty_interconnection", "Progress"]

#: ``progress(stage, done, total, message)``, called as the stages advance.
Progress = Callable[[str, int, int, str], None]


def empty_interconnection(network: Network) -> InterconnectionAbstraction:
    """The abstraction of a map with no outputs (a network without ``interconnection``): no nodes, ``p = 0``.

    Exact, hence sound: ``M̂(x̂)`` is the one empty tuple of internal cells for every ``x̂``.
    """
    grid = network.composed_state_grid()
    n = network.state_dim
    return InterconnectionAbstraction(
        mode="none",
        M_bar=np.zeros((0, n)),
        supports=(),
        offsets=np.zeros(0),
        error_bounds=np.zeros(0),
        nodes=(),
        intermediate_grids={},
        output_modes=(),
        details={"evaluations": 0, "seconds": 0.0, "state_sizes": [axis_grid(grid, i).size for i in range(n)]},
    )


def abstract_interconnection(
    network: Network,
    rng: np.random.Generator,
    progress: Progress | None = None,
    *,
    max_certify_cells: int = MAX_CERTIFY_CELLS,
) -> InterconnectionAbstraction:
    """Algorithm 3 (IA) without the exponential loop: lasso, support check, ``eps``, MDec, node relations.

    Parameters
    ----------
    network : Network
        Its ``interconnection_map`` maps states ``(B, n_total)`` to ``(B, p)``; its internal grids are 1-D.
    rng : numpy.random.Generator
        All sampling (training, hold-out, support checks) draws from it.
    progress : callable, optional
        ``progress(stage, done, total, message)`` with ``stage == "interconnection"``.
    max_certify_cells : int
        Cap on the cells ``certify`` evaluates per output (coarser uniform partition above it).

    Raises
    ------
    SpecError
        A map value outside its internal box; ``certify``/``direct`` without ``lipschitz``; ``sigma = 1`` with
        an output reading two variables; a node relation too large.
    CertificationError
        A dependence outside the learned support; a map declared linear that is not.
    LipschitzError
        ``L_M`` contradicted by the data.
    """
    ic = network.spec.interconnection
    report = progress or (lambda *_: None)
    if ic is None:  # a single system, or subsystems reading nothing: M has no outputs
        return empty_interconnection(network)
    t0 = time.perf_counter()
    mode = ic.error
    if mode in ("certify", "direct") and ic.lipschitz is None:
        raise SpecError(
            f"interconnection.error is '{mode}', which needs interconnection.lipschitz (L_M, infinity norm)"
        )
    if ic.alpha == "cv" and ic.samples < 4:
        raise SpecError(f"interconnection.samples is {ic.samples}; cross-validated lasso needs at least 4")
    L = float(ic.lipschitz) if ic.lipschitz is not None else None
    sample = Sampler(network)
    n, p = sample.lb.size, sample.w_lb.size
    xmax = float(np.maximum(np.abs(sample.lb), np.abs(sample.ub)).max())
    steps = 4 + p
    # Counts that grow with the n coordinates the map may read; the spec's are minimums (sampling.py).
    n_train, n_check = training_count(ic.samples, n), check_count(ic.holdout, n)
    report("interconnection", 0, steps, f"sampling the map ({n_train} states)")

    # 1. Samples and lasso (Eq. (lasso)), one row at a time.
    X = sample.uniform(n_train, rng)
    Y = sample(X)
    fits = [lasso_row(X, Y[:, j], ic.alpha) for j in range(p)]
    lasso_supports = [support_of(coef) for coef, _ in fits]
    report("interconnection", 1, steps, "lasso fitted")

    # 2. Supports: drop candidates M_j does not depend on, refit by least squares, validate the rest.
    # Lasso only sees linear correlation: an even function of a coordinate (0.3 x^2 on [-2, 2]) has none and
    # is left out. The one-coordinate-at-a-time dependence test sees any dependence, so it adds what lasso
    # missed (recorded in the report) instead of failing the job; the joint check below still certifies.
    dep = dependence(sample, ic.holdout, rng)
    supports = [tuple(i for i in range(n) if dep[i, j]) for j in range(p)]
    added = [sorted(set(supports[j]) - set(lasso_supports[j])) for j in range(p)]
    # The joint check, completing a support the one-at-a-time test left short (learning.complete_support).
    checked = [complete_support(sample, j, supports[j], dep, n_check, rng) for j in range(p)]
    supports = [c[0] for c in checked]
    moved = [c[1] for c in checked]
    M_bar = np.zeros((p, n))
    offsets = np.zeros(p)
    for j in range(p):
        M_bar[j], offsets[j] = refit(X, Y[:, j], supports[j])
    if mode in ("certify", "direct"):  # only where eps relies on L_M
        assert L is not None  # both modes need it (checked above)
        check_lipschitz(sample, L, ic.holdout, rng)
    report("interconnection", 2, steps, f"supports {[list(s) for s in supports]}")

    # MDec (Algorithm 2) now, so that a sigma too small fails before the costly steps. A direct output gets
    # one node from the black box instead (an empty row here, replaced below).
    is_direct = [mode == "direct" and len(supports[j]) <= ic.sigma for j in range(p)]
    is_reduction = mode in REDUCTIONS  # every output declared max (min) of what it reads: exact trees below
    plans = mdec(M_bar, [() if is_direct[j] or is_reduction else supports[j] for j in range(p)], ic.sigma)

    # 3. Error bounds per output.
    X_hold = sample.uniform(ic.holdout, rng)
    Y_hold = sample(X_hold)
    eps = np.zeros(p)
    output_modes: list[str] = []
    residuals: list[float] = []
    resolution: dict[str, dict] = {}
    direct_nodes: dict[int, NodeRelation] = {}
    for j in range(p):
        res = np.abs(Y_hold[:, j] - (X_hold @ M_bar[j] + offsets[j]))
        residuals.append(float(res.max(initial=0.0)))
        if is_reduction:
            check_reduction(mode, j, supports[j], X, Y)
            check_reduction(mode, j, supports[j], X_hold, Y_hold)
            output_modes.append(mode)  # eps stays 0: the node tree is exact (reduction.py)
        elif mode == "linear":
            eps[j], _ = eps_linear(j, M_bar[j], offsets[j], X_hold, Y_hold, xmax, len(supports[j]), n_train)
            output_modes.append("linear")
        elif is_direct[j]:
            assert L is not None
            direct_nodes[j], eps[j] = direct_node(sample, j, supports[j], L, ic.samples_per_cell, moved[j])
            output_modes.append("direct")
        else:
            assert L is not None
            bound, resolution[f"w{j}"] = eps_certify(
                sample, j, supports[j], M_bar[j], offsets[j], L, max_certify_cells, xmax
            )
            eps[j] = bound + moved[j]
            if residuals[-1] > eps[j]:
                raise LipschitzError(
                    f"interconnection output w{j}: held-out residual {residuals[-1]:.6g} exceeds the certified "
                    f"bound {eps[j]:.6g}; the Lipschitz constant L_M = {L} is too small"
                )
            output_modes.append("certify")
        report("interconnection", 3 + j, steps, f"w{j}: {output_modes[-1]}, eps = {eps[j]:.4g}")

    # 4-5. Grids of the intermediate variables and the node relations, in topological order. An output whose
    # certified range covers its internal box at every state is that box: one node without inputs, the same
    # relation as its MDec tree (nodes.covers_box), without building the tree.
    grid = network.composed_state_grid()
    x_grids = [axis_grid(grid, i) for i in range(n)]
    whole_box = [j for j in range(p) if j not in direct_nodes and supports[j] and not is_reduction
                 and covers_box(network.internal_grids[j], M_bar[j], offsets[j], eps[j], sample.lb, sample.ub)]
    z_grids: dict[str, UniformGrid] = {}
    nodes: list[NodeRelation] = []
    for plan in plans:
        j = plan.target
        if is_reduction:
            tree, grids = reduction_nodes(mode, j, supports[j], x_grids, network.internal_grids[j], len(z_grids))
            nodes.extend(tree)
            z_grids.update(grids)
            continue
        if j in direct_nodes:
            if plan.is_final:
                nodes.append(direct_nodes[j])
            continue
        if j in whole_box:
            if plan.is_final:
                nodes.append(box_node(plan.output, network.internal_grids[j], eps[j]))
            continue
        in_grids = [x_grids[int(v[1:])] if v.startswith("x") else z_grids[v] for v in plan.inputs]
        if plan.is_final:
            nodes.append(linear_node(plan, network.internal_grids[j], in_grids, offsets[j], eps[j]))
        else:
            eta = ic.intermediate_eta or network.internal_grids[j].eta[0]
            z_grids[plan.output] = intermediate_grid(plan, [(g.lb[0], g.ub[0]) for g in in_grids], eta)
            nodes.append(linear_node(plan, z_grids[plan.output], in_grids, 0.0, 0.0))
    report("interconnection", steps, steps, f"{len(nodes)} nodes, {len(z_grids)} intermediate variables")

    details = {
        "alpha": [a for _, a in fits],
        "lasso_supports": [list(s) for s in lasso_supports],
        "support_added_by_dependence_test": added,
        "support_added_by_joint_check": [c[2] for c in checked],
        "samples_used": {"training": n_train, "joint_check": n_check, "dependence": ic.holdout,
                         "holdout": ic.holdout},
        "whole_box_outputs": whole_box,
        "support_change": moved,
        "holdout_residual": residuals,
        "certify_resolution": resolution,
        "lipschitz": L,
        "sigma": ic.sigma,
        "evaluations": sample.evaluations,
        "seconds": time.perf_counter() - t0,
        "state_sizes": [g.size for g in x_grids],
    }
    return InterconnectionAbstraction(
        mode=mode,
        M_bar=M_bar,
        supports=tuple(tuple(s) for s in supports),
        offsets=offsets,
        error_bounds=eps,
        nodes=tuple(nodes),
        intermediate_grids=z_grids,
        output_modes=tuple(output_modes),
        details=details,
    )
