"""Matrix decomposition, MDec (Algorithm 2 of the paper, Section 4.2): bounded in-degree via partial sums.

The sparse linear map ``M̄`` (lasso, Eq. (lasso)) is read as a weighted DAG from the state coordinates ``x_i`` to
the internal variables ``w_j`` (Eq. (e_func)). An output that reads more than ``sigma`` coordinates is split into
intermediate variables ``z_k`` so that every node of the DAG reads at most ``sigma`` variables; each node then
becomes a relation over a grid of dimension ``<= sigma`` instead of the full product grid.

Departures from the paper, and why
----------------------------------
* Algorithm 2 as printed rescales edges by ``1/d`` and ``z`` to a mean (Sec. 5.2 scales ``z`` by 4 and 2).
  Here an intermediate variable is the plain *weighted partial sum* ``z_k = sum_i a_i v_i`` of its inputs
  (``a_i = M̄_{j,i}`` for a state coordinate, ``1`` for another ``z``), and the parent node adds its inputs
  with weight 1. The two are equal up to a constant factor on ``z``'s grid; partial sums keep every weight
  of ``M̄`` in exactly one place, so the final node is ``w_j = sum(inputs) + b_j ± eps_j`` with no division.
* The grouping is deterministic: the support (in coordinate order) is cut into consecutive chunks of at most
  ``sigma``; each chunk of two or more becomes one ``z``, a singleton stays as it is; the resulting list is
  cut again until at most ``sigma`` inputs remain. For the consensus map (``M̄ = 1/8 · 1ᵀ``, ``sigma = 4``) this
  gives ``z0 = x0..x3``, ``z1 = x4..x7``, ``w = z0 + z1``: the shape of the paper's Fig. 2 and Sec. 5.2.
* Every ``z`` is read by exactly one node, so the DAG is a forest with one tree per output. This makes
  ``∃z. ∧ R_node`` computable exactly bottom-up, and the interconnection relation a product over outputs.
* ``sigma = 1`` cannot form a sum of two variables: it is refused for an output that reads more than one.

The paper's ``while deg(v) > sigma for all v`` is read as "while some vertex has in-degree above ``sigma``";
the literal reading would stop as soon as one output is small enough.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipelines.errors import SpecError


@dataclass(frozen=True)
class NodePlan:
    """One node of the decomposed DAG, before grids and relations are attached.

    Attributes
    ----------
    output : str
        ``"w3"`` (internal variable 3, a final node) or ``"z0"`` (an intermediate variable).
    inputs : tuple of str
        ``"x5"`` (composed-state coordinate 5) or ``"z0"``; at most ``sigma`` of them.
    weights : tuple of float
        One per input: ``M̄_{j,i}`` for ``x_i``, ``1.0`` for a ``z``. The node's value is ``sum w_k v_k``
        (plus intercept and error for a final node, which the caller adds).
    target : int
        Index ``j`` of the output this node belongs to (a ``z`` belongs to the tree of one output).
    """

    output: str
    inputs: tuple[str, ...]
    weights: tuple[float, ...]
    target: int

    @property
    def is_final(self) -> bool:
        return self.output.startswith("w")


def _chunks(items: list, size: int) -> list[list]:
    """Consecutive chunks of at most ``size`` items."""
    return [items[k : k + size] for k in range(0, len(items), size)]


def decompose_row(
    j: int, support: Sequence[int], weights: Sequence[float], sigma: int, z_start: int
) -> list[NodePlan]:
    """MDec (Algorithm 2) for one output row ``j``: nodes in topological order, the final node last.

    Parameters
    ----------
    j : int
        Output index (the final node is ``"w{j}"``).
    support : sequence of int, length s
        State coordinates the row depends on, in increasing order.
    weights : sequence of float, length s
        ``M̄_{j,i}`` for ``i`` in ``support``.
    sigma : int
        Largest in-degree allowed (>= 1).
    z_start : int
        Number of intermediate variables created so far (``z`` names are global: ``z{z_start}``, ...).

    Raises
    ------
    SpecError
        ``sigma == 1`` while the row reads two or more coordinates: a sum cannot be formed.
    """
    if sigma < 1:
        raise SpecError(f"sigma must be >= 1, got {sigma}")
    if len(support) != len(weights):
        raise ValueError("support and weights differ in length")
    items: list[tuple[str, float]] = [(f"x{int(i)}", float(a)) for i, a in zip(support, weights)]
    if len(items) > sigma and sigma < 2:
        raise SpecError(
            f"sigma must be >= 2 when an output depends on more than one variable "
            f"(output w{j} depends on {len(items)}: {[name for name, _ in items]})"
        )
    nodes: list[NodePlan] = []
    k = z_start
    # Each pass replaces every chunk of >= 2 by one z: ceil(L / sigma) < L when L > sigma >= 2, so it ends.
    while len(items) > sigma:
        merged: list[tuple[str, float]] = []
        for chunk in _chunks(items, sigma):
            if len(chunk) == 1:
                merged.append(chunk[0])
                continue
            name = f"z{k}"
            k += 1
            nodes.append(NodePlan(name, tuple(n for n, _ in chunk), tuple(a for _, a in chunk), j))
            merged.append((name, 1.0))
        items = merged
    nodes.append(NodePlan(f"w{j}", tuple(n for n, _ in items), tuple(a for _, a in items), j))
    return nodes


def mdec(M_bar: np.ndarray, supports: Sequence[Sequence[int]], sigma: int) -> list[NodePlan]:
    """MDec (Algorithm 2) for every output: all nodes, in topological order (``z`` before its reader).

    Parameters
    ----------
    M_bar : ndarray, shape (p, n)
        The learned linear map (Eq. (lasso)); only entries on the supports are read.
    supports : sequence of p sequences of int
        Per output, the state coordinates it depends on.
    sigma : int
        Largest in-degree of any node.

    Returns
    -------
    list of NodePlan
        Exactly one final node ``"w{j}"`` per output ``j`` (a constant output gets a node with no inputs),
        preceded by its intermediate nodes.
    """
    M_bar = np.asarray(M_bar, dtype=float)
    if M_bar.ndim != 2 or M_bar.shape[0] != len(supports):
        raise ValueError(f"M_bar has shape {M_bar.shape}, expected ({len(supports)}, n)")
    nodes: list[NodePlan] = []
    z_count = 0
    for j, sup in enumerate(supports):
        sup = sorted(int(i) for i in sup)
        row = decompose_row(j, sup, [M_bar[j, i] for i in sup], sigma, z_count)
        z_count += len(row) - 1
        nodes.extend(row)
    return nodes
