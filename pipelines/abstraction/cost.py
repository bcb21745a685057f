"""Cost model of the per-cell stage (Algorithm 1): what a triple ``(x̂, û, ŵ)`` costs, in black-box evaluations.

An executor sizes its tasks with :func:`triple_cost`; :func:`statistics_fraction` keeps the successor statistics
of the SCP objectives that do not build the relation cheaper than the growth bound that does (docs/method.md §2: the
report counts every method, but a statistic must not cost more than the abstraction).

The unit is one evaluation of a linear 2-3-D expression black box on one core (about 30 ns with numba and numpy
2); every other constant is relative to it, so the model sizes tasks the same on a faster or slower machine.
"""

from __future__ import annotations

import numpy as np

from pipelines.abstraction.growth_bound import subgrid_counts
from pipelines.network import Subsystem

#: Per triple, after the black box: centre, boxes of every bound, successor cells, blocking, statistics.
#: About 0.55-0.65 us (n = 2) and 0.85 us (n = 3) on the numpy path; about 0.15 us in the scalar kernel.
TRIPLE_WORK = {1: 5.0, 2: 20.0, 3: 28.0}
#: Per triple, per additional state dimension beyond 3 (extrapolated).
TRIPLE_WORK_PER_DIM = 8.0
#: Per sample and state component: the hull's extremes and the neighbour slopes.
SAMPLE_WORK = 0.1
#: Per sample pair and output component: the SCP's pair maxima (about 1 ns: compiled, batch contiguous).
PAIR_WORK = 0.035
#: Per constraint of one SCP LP (one triple, one output row, one objective): the dual simplex, about 40 ns per
#: constraint (0.26 us with 8 constraints, 0.83 us with 27). An upper estimate: rows that cannot beat the
#: Lipschitz radius skip it.
LP_WORK = 1.3
#: Per pair ``i <= w < j`` of the scalar closed-form SCP, per objective.
SCALAR_PAIR_WORK = 0.05
#: Share of the chosen bound's work the sampled statistics may take (below 1: the estimates above are rough).
STATISTICS_BUDGET = 0.5
#: Upper share of triples the sampled statistics use (``block.STATISTICS_SAMPLE``, which imports it).
STATISTICS_SAMPLE = 1 / 8


def _work(sub: Subsystem) -> tuple[float, float, float, bool]:
    """``(base, pairs, lp, scalar)``: work per triple of the black box and the cheap bounds, of the SCP's pair
    maxima (shared by both objectives), of one SCP objective's LPs, and whether the scalar kernel runs."""
    n, p = sub.n, sub.p
    counts = subgrid_counts(max(1, sub.spec.samples), n + p)
    Sx = int(np.prod(counts[:n]))
    S = int(np.prod(counts))
    scalar = n == 1 and len(counts) - n <= 1
    triple = TRIPLE_WORK.get(n, TRIPLE_WORK[3] + TRIPLE_WORK_PER_DIM * (n - 3))
    base = (S + 1) * sub.spec.rhs_evaluations + SAMPLE_WORK * S * n + triple
    if scalar:
        return base, PAIR_WORK * Sx * Sx / 2, SCALAR_PAIR_WORK * Sx * Sx / 4, True
    return base, PAIR_WORK * n * Sx * (Sx + 1) / 2, LP_WORK * n * Sx, False


def statistics_fraction(sub: Subsystem, method: str, objective: str) -> float:
    """Share of the triples on which the SCP objective(s) that do not build the relation are counted when the
    statistics are sampled (``block.statistics_sample``).

    :data:`STATISTICS_SAMPLE` for a scalar state (its SCP is a closed form); for ``dim(x) > 1`` at most
    that, and small enough that the sampled SCP work is at most :data:`STATISTICS_BUDGET` of the chosen bound's
    work (pair maxima and LPs scale with the square of the samples and with the LP size, the black box with the
    samples). Depends on the subsystem and the method only, never on chunking.
    """
    if sub.n == 1:
        return STATISTICS_SAMPLE
    base, pairs, lp, _ = _work(sub)
    if method == "scp":
        chosen, extra = base + pairs + lp, lp
    else:
        chosen, extra = base, pairs + 2 * lp
    return float(min(STATISTICS_SAMPLE, STATISTICS_BUDGET * chosen / extra))


def triple_cost(sub: Subsystem, method: str, objective: str, full_statistics: bool | None = None) -> float:
    """Work of one triple of the per-cell stage, in black-box evaluations (the unit: one evaluation of a cheap
    expression, about 30 ns; a costlier black box makes the other terms relatively smaller).

    Counts the samples and the centre, the growth bounds, successor cells and statistics, and for the SCP its
    pair maxima and LPs: the chosen objective on every triple, the other on the statistics sample
    (:func:`statistics_fraction`), both on every triple where ``abstract_cells`` counts them all (a scalar state
    by default, or ``full_statistics=True``).

    Parameters
    ----------
    sub : Subsystem
    method : {'lipschitz', 'scp', 'hull'}
    objective : {'paper', 'radius'}
    full_statistics : bool or None
        As :func:`pipelines.abstraction.cells.abstract_cells`.

    Returns
    -------
    float
    """
    base, pairs, lp, scalar = _work(sub)
    full = sub.n == 1 if full_statistics is None else full_statistics
    if full:
        return base + pairs + 2 * lp
    share = statistics_fraction(sub, method, objective)
    if method == "scp":
        return base + pairs + lp + share * lp
    return base + share * (pairs + 2 * lp)
