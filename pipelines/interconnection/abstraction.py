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
from dataclasses import dataclass

import numpy as np

from pipelines.errors import LipschitzError, SpecError
from pipelines.grid import UniformGrid
from pipelines.interconnection.certification import MAX_CERTIFY_CELLS, check_lipschitz, eps_certify, eps_linear
from pipelines.interconnection.grids import axis_grid
from pipelines.interconnection.learning import complete_support, dependence, lasso_row, refit, support_of
from pipelines.interconnection.mdec import mdec
from pipelines.interconnection.node_relations import InterconnectionAbstraction, NodeRelation
from pipelines.interconnection.nodes import box_node, covers_box, direct_node, intermediate_grid, linear_node
from pipelines.interconnection.reduction import REDUCTIONS, check_reduction, reduction_nodes
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
    steps = 4 + p
    # Counts that grow with the n coordinates the map may read; the spec's are minimums (sampling.py).
    n_train, n_check = training_count(ic.samples, n), check_count(ic.holdout, n)
    report("interconnection", 0, steps, f"sampling the map ({n_train} states)")
    learnt = _learn(sample, n_train, n_check, rng, report)
    if mode in ("certify", "direct"):  # only where eps relies on L_M
        assert L is not None  # both modes need it (checked above)
        check_lipschitz(sample, L, ic.holdout, rng)
    report("interconnection", 2, steps, f"supports {[list(s) for s in learnt.supports]}")

    # MDec (Algorithm 2) now, so that a sigma too small fails before the costly steps. A direct output gets
    # one node from the black box instead (an empty row here, replaced below).
    is_direct = [mode == "direct" and len(learnt.supports[j]) <= ic.sigma for j in range(p)]
    is_reduction = mode in REDUCTIONS  # every output declared max (min) of what it reads: exact trees below
    plans = mdec(learnt.M_bar, [() if is_direct[j] or is_reduction else learnt.supports[j] for j in range(p)],
                 ic.sigma)
    bounds = _error_bounds(sample, learnt, is_direct, L, max_certify_cells, rng, lambda j, text: report(
        "interconnection", 3 + j, steps, text))
    grid = network.composed_state_grid()
    x_grids = [axis_grid(grid, i) for i in range(n)]
    nodes, z_grids, whole_box = _node_relations(network, sample, learnt, bounds, plans, x_grids)
    report("interconnection", steps, steps, f"{len(nodes)} nodes, {len(z_grids)} intermediate variables")

    details = {
        "alpha": learnt.alphas,
        "lasso_supports": [list(s) for s in learnt.lasso_supports],
        "support_added_by_dependence_test": learnt.added_by_dependence,
        "support_added_by_joint_check": learnt.added_by_joint_check,
        "samples_used": {"training": n_train, "joint_check": n_check, "dependence": ic.holdout,
                         "holdout": ic.holdout},
        "whole_box_outputs": whole_box,
        "support_change": learnt.moved,
        "holdout_residual": bounds.residuals,
        "certify_resolution": bounds.resolution,
        "lipschitz": L,
        "sigma": ic.sigma,
        "evaluations": sample.evaluations,
        "seconds": time.perf_counter() - t0,
        "state_sizes": [g.size for g in x_grids],
    }
    return InterconnectionAbstraction(
        mode=mode,
        M_bar=learnt.M_bar,
        supports=tuple(tuple(s) for s in learnt.supports),
        offsets=learnt.offsets,
        error_bounds=bounds.eps,
        nodes=tuple(nodes),
        intermediate_grids=z_grids,
        output_modes=tuple(bounds.modes),
        details=details,
    )


@dataclass
class _Learnt:
    """Steps 1-2 of Algorithm 3: the training samples, the lasso fits and the supports, refitted."""

    X: np.ndarray
    Y: np.ndarray
    alphas: list[float | None]
    lasso_supports: list[tuple[int, ...]]
    supports: list[tuple[int, ...]]
    added_by_dependence: list[list[int]]
    added_by_joint_check: list
    moved: list[float]  # the support change each joint check adds to eps
    M_bar: np.ndarray
    offsets: np.ndarray


def _learn(sample: Sampler, n_train: int, n_check: int, rng: np.random.Generator, report: Progress) -> _Learnt:
    """Samples and lasso (Eq. (lasso)), one row at a time; then the supports: drop candidates ``M_j`` does not
    depend on, refit by least squares, validate the rest."""
    ic = sample.network.spec.interconnection
    assert ic is not None
    n, p = sample.lb.size, sample.w_lb.size
    X = sample.uniform(n_train, rng)
    Y = sample(X)
    fits = [lasso_row(X, Y[:, j], ic.alpha) for j in range(p)]
    lasso_supports = [support_of(coef) for coef, _ in fits]
    report("interconnection", 1, 4 + p, "lasso fitted")
    # Lasso only sees linear correlation: an even function of a coordinate (0.3 x^2 on [-2, 2]) has none and
    # is left out. The one-coordinate-at-a-time dependence test sees any dependence, so it adds what lasso
    # missed (recorded in the report) instead of failing the job; the joint check below still certifies.
    dep = dependence(sample, ic.holdout, rng)
    supports = [tuple(i for i in range(n) if dep[i, j]) for j in range(p)]
    added = [sorted(set(supports[j]) - set(lasso_supports[j])) for j in range(p)]
    # The joint check, completing a support the one-at-a-time test left short (learning.complete_support).
    checked = [complete_support(sample, j, supports[j], dep, n_check, rng) for j in range(p)]
    supports = [c[0] for c in checked]
    M_bar = np.zeros((p, n))
    offsets = np.zeros(p)
    for j in range(p):
        M_bar[j], offsets[j] = refit(X, Y[:, j], supports[j])
    return _Learnt(X, Y, [a for _, a in fits], lasso_supports, supports, added, [c[2] for c in checked],
                   [c[1] for c in checked], M_bar, offsets)


@dataclass
class _Bounds:
    """Step 3 of Algorithm 3: the error bound ``eps_j`` of each output and how it was found."""

    eps: np.ndarray
    modes: list[str]
    residuals: list[float]
    resolution: dict[str, dict]
    direct_nodes: dict[int, NodeRelation]


def _error_bounds(sample: Sampler, learnt: _Learnt, is_direct: list[bool], L: float | None,
                  max_certify_cells: int, rng: np.random.Generator, report: Callable[[int, str], None]) -> _Bounds:
    """``eps_j`` per output (Eq. (eps)): from the held-out residuals (``linear``), certified with ``L_M``
    (``certify``), a node from the black box (``direct``), or 0 for an exact reduction."""
    ic = sample.network.spec.interconnection
    assert ic is not None
    mode, p = ic.error, sample.w_lb.size
    xmax = float(np.maximum(np.abs(sample.lb), np.abs(sample.ub)).max())
    n_train = learnt.X.shape[0]
    X_hold = sample.uniform(ic.holdout, rng)
    Y_hold = sample(X_hold)
    out = _Bounds(np.zeros(p), [], [], {}, {})
    for j in range(p):
        support, M_j, offset = learnt.supports[j], learnt.M_bar[j], learnt.offsets[j]
        res = np.abs(Y_hold[:, j] - (X_hold @ M_j + offset))
        out.residuals.append(float(res.max(initial=0.0)))
        if mode in REDUCTIONS:
            check_reduction(mode, j, support, learnt.X, learnt.Y)
            check_reduction(mode, j, support, X_hold, Y_hold)
            out.modes.append(mode)  # eps stays 0: the node tree is exact (reduction.py)
        elif mode == "linear":
            out.eps[j], _ = eps_linear(j, M_j, offset, X_hold, Y_hold, xmax, len(support), n_train)
            out.modes.append("linear")
        elif is_direct[j]:
            assert L is not None
            out.direct_nodes[j], out.eps[j] = direct_node(sample, j, support, L, ic.samples_per_cell,
                                                          learnt.moved[j])
            out.modes.append("direct")
        else:
            assert L is not None
            bound, out.resolution[f"w{j}"] = eps_certify(sample, j, support, M_j, offset, L, max_certify_cells, xmax)
            out.eps[j] = bound + learnt.moved[j]
            if out.residuals[-1] > out.eps[j]:
                raise LipschitzError(
                    f"interconnection output w{j}: held-out residual {out.residuals[-1]:.6g} exceeds the certified "
                    f"bound {out.eps[j]:.6g}; the Lipschitz constant L_M = {L} is too small"
                )
            out.modes.append("certify")
        report(j, f"w{j}: {out.modes[-1]}, eps = {out.eps[j]:.4g}")
    return out


def _node_relations(network: Network, sample: Sampler, learnt: _Learnt, bounds: _Bounds, plans: list,
                    x_grids: list[UniformGrid]) -> tuple[list[NodeRelation], dict[str, UniformGrid], list[int]]:
    """Steps 4-5: the grids of the intermediate variables and the node relations, in topological order; and the
    outputs whose certified range covers their internal box at every state: that box, one node without inputs,
    the same relation as their MDec tree (nodes.covers_box), without building the tree."""
    ic = network.spec.interconnection
    assert ic is not None
    mode, p = ic.error, sample.w_lb.size
    eps, offsets, supports = bounds.eps, learnt.offsets, learnt.supports
    is_reduction = mode in REDUCTIONS
    whole_box = [j for j in range(p) if j not in bounds.direct_nodes and supports[j] and not is_reduction
                 and covers_box(network.internal_grids[j], learnt.M_bar[j], offsets[j], eps[j], sample.lb, sample.ub)]
    z_grids: dict[str, UniformGrid] = {}
    nodes: list[NodeRelation] = []
    for plan in plans:
        j = plan.target
        if is_reduction:
            tree, grids = reduction_nodes(mode, j, supports[j], x_grids, network.internal_grids[j], len(z_grids))
            nodes.extend(tree)
            z_grids.update(grids)
            continue
        if j in bounds.direct_nodes:
            if plan.is_final:
                nodes.append(bounds.direct_nodes[j])
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
    return nodes, z_grids, whole_box
