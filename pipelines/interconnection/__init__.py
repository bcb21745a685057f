"""Interconnection abstraction (Section 4.2: lasso, Lemma lem1, Algorithm 2 MDec, Algorithm 3 IA).

Paper references name the labels of its source, because its printed numbering is ambiguous: Eq. (lasso) is
the lasso problem, Lemma lem1 the error bound with Eq. (eps_hat), Eq. (e_func) the DAG edges, Theorem
thrm_inter the soundness of IA ("Theorem 4.7" in docs/method.md), Definition intercon the interconnection map.

The map ``M`` (all states -> all internal variables) is a black box. We learn a sparse linear map ``M̄`` and
intercept ``b`` from samples, certify per output ``j`` an error bound ``eps_j`` with
``|M_j(x) - M̄_j x - b_j| <= eps_j`` on the whole state box, decompose ``M̄`` into nodes of in-degree
``<= sigma`` (MDec), and build one relation per node on its low-dimensional input grid. The abstraction is
``M̂(x̂) = {ŵ : ∃ẑ. ∧_node R_node}``. Soundness (Theorem thrm_inter): for every concrete ``x`` in
``cell(x̂)``, every cell containing ``M(x)`` is in ``M̂(x̂)``. Algorithm 3 as printed loops over every ``x̂``
of the full product grid (exponential in ``N``); here nothing is enumerated beyond the product of at most
``sigma`` one-dimensional grids (docs/method.md §4).

Modules
-------
:mod:`~pipelines.interconnection.node_relations`
    :class:`NodeRelation` and :class:`InterconnectionAbstraction`: ``M̂`` as a forest of node relations and the
    exact ``∃z. ∧ R_node`` query (Algorithm 3's result, Theorem thrm_inter).
:mod:`~pipelines.interconnection.sampling`
    The black-box sampler of ``M``, checking every value against the internal boxes (Definition intercon).
:mod:`~pipelines.interconnection.learning`
    Lasso rows (Eq. (lasso)), supports by the dependence test, least-squares refit, support validation.
:mod:`~pipelines.interconnection.certification`
    The error bounds ``eps_j`` (Lemma lem1 with Eq. (eps_hat), made sound), the check of ``L_M``, the
    floating-point margins.
:mod:`~pipelines.interconnection.mdec`
    MDec (Algorithm 2): the DAG of Eq. (e_func) cut into nodes of in-degree ``<= sigma`` by partial sums.
:mod:`~pipelines.interconnection.grids`
    The low-dimensional grids a node reads: axis grids, clipped cells, cell ranges, flat indexing.
:mod:`~pipelines.interconnection.nodes`
    The node relations (Algorithm 3, line 8): linear nodes, intermediate grids, ``direct`` nodes.
:mod:`~pipelines.interconnection.abstraction`
    :func:`abstract_interconnection`: Algorithm 3 (IA) end to end, without the exponential loop.
"""

from __future__ import annotations

from pipelines.interconnection.abstraction import abstract_interconnection
from pipelines.interconnection.node_relations import InterconnectionAbstraction, NodeRelation

__all__ = ["abstract_interconnection", "InterconnectionAbstraction", "NodeRelation"]
