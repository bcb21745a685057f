"""One input per domain state: the determinized controller as a BDD, and its node table over the state bits.

Rules (recorded in every export as ``rule``):

* ``earliest_layer`` (the default for a layered progress controller: reach, reach-avoid, reach-and-stay's
  ``reach_safe``): a cell first in layer ``k > 0`` gets an input of ``CPre(layers[j])`` for the smallest ``j``
  where that set is non-empty at the cell (the most progress one step can make; ``j < k``, so the input is one
  of the layered controller's, and every closed-loop step lowers the layer). Ties: the smallest input index.
  Cells of ``layers[0]``: the smallest input of ``CPre(layers[0])`` (the invariant, ``stay``) or the smallest
  valid input (a reach target: the specification is met on arrival).
* ``smallest_index`` (the default for an explicit controller, the only rule for safety): the smallest admissible
  input index. An explicit reach controller already allows, at a cell, only inputs into the iterate before the
  one where the cell entered (:func:`~pipelines.synthesis.fixed_points.reach`), so this is progress too.

"Smallest input index" is lexicographic in the per-subsystem flat input indices, subsystems in network order
(the row-major joint index). It is computed symbolically, bit by bit (:func:`lexmin`), never cell by cell.
"""

from __future__ import annotations

import numpy as np

from pipelines.controller import Controller, LayeredController
from pipelines.export.table import RULES, ExportError
from pipelines.symbolic.counting import enumerate_cells
from pipelines.symbolic.node_table import BDDTable, node_table
from pipelines.symbolic.symbolic_model import Function, SymbolicModel
from pipelines.synthesis.at_state import cpre_at_state
from pipelines.synthesis.cpre import bad_inputs


def resolve_rule(ctrl: Controller, rule: str) -> str:
    """``rule``, with ``auto`` replaced by ``earliest_layer`` for a layered progress controller, else (explicit,
    or safety) ``smallest_index``."""
    if rule not in RULES:
        raise ExportError(f"unknown rule {rule!r}; expected one of {', '.join(RULES)}")
    if rule != "auto":
        return rule
    return "earliest_layer" if isinstance(ctrl, LayeredController) and ctrl.meta.get("kind") != "safe" \
        else "smallest_index"


def lexmin(model: SymbolicModel, C: Function) -> Function:
    """The smallest joint input of ``C(x̂, û)`` at each state: ``D ⊆ C`` with exactly one ``û`` per state of
    ``∃û.C``.

    Input bits are taken most significant first, digit by digit in subsystem order: where some remaining input
    has the bit 0, the inputs with bit 1 are dropped (one ``∃û`` and two conjunctions per input bit).
    """
    bdd, u_bits = model.bdd, model.u_bits
    C = C & model.u_domain
    with model.guard("determinizing the controller"):
        for b in u_bits:
            v = model.var(b)
            has_zero = bdd.exist(u_bits, C & ~v)
            C = C & (~v | ~has_zero)
    return C


def _layered(ctrl: LayeredController) -> Function:
    """The ``earliest_layer`` rule over the layered controller's ingredients (module docstring)."""
    m, bdd = ctrl.model, ctrl.model.bdd
    layers = ctrl.layers
    chain, admissible, M = ctrl.ingredients
    with m.guard("determinizing the layered controller"):
        if ctrl.stay:
            D = lexmin(m, admissible & layers[0] & ~bad_inputs(m, chain, M, m.w_bits, layers[0], part=layers[0]))
        else:
            D = lexmin(m, layers[0])
        remaining = layers[-1] & ~layers[0]
        for Z in layers[:-1]:
            if remaining == bdd.false:
                break
            cp = admissible & remaining & ~bad_inputs(m, chain, M, m.w_bits, Z, part=remaining)
            D |= lexmin(m, cp)
            remaining &= ~bdd.exist(m.u_bits, cp)
    if remaining != bdd.false:
        raise ExportError("determinizing: some domain cells have no input into an earlier layer (a bug)")
    return D


def determinize(ctrl: Controller, rule: str = "auto") -> tuple[Function, str]:
    """The determinized controller ``D(x̂, û)`` (one input per domain cell, ``D ⊆ C``) and the rule used.

    ``rule``: one of :data:`RULES`; ``auto`` is ``earliest_layer`` for a layered progress controller, else
    (explicit, or safety) ``smallest_index``.
    """
    if rule not in RULES:
        raise ExportError(f"unknown rule {rule!r}; expected one of {', '.join(RULES)}")
    layered = isinstance(ctrl, LayeredController)
    rule = resolve_rule(ctrl, rule)
    m = ctrl.model
    if rule == "earliest_layer":
        if not layered:
            raise ExportError("rule earliest_layer needs a layered controller (controller_form: layered); this one is "
                              "explicit: use --rule smallest_index")
        assert isinstance(ctrl, LayeredController)
        D = _layered(ctrl)
    elif layered:
        assert isinstance(ctrl, LayeredController)
        chain, admissible, M = ctrl.ingredients
        layers = ctrl.layers
        parts = []  # the layered controller's inputs, layer by layer, then the smallest of them
        with m.guard("determinizing the layered controller"):
            parts.append(layers[0] & (admissible & ~bad_inputs(m, chain, M, m.w_bits, layers[0], part=layers[0])
                                      if ctrl.stay else m.u_domain))
            for k in range(1, len(layers)):
                new = layers[k] & ~layers[k - 1]
                parts.append(admissible & new & ~bad_inputs(m, chain, M, m.w_bits, layers[k - 1], part=new))
        C = m.bdd.false
        for p in parts:
            C |= p
        D = lexmin(m, C)
    else:
        D = lexmin(m, ctrl.relation)
    if m.bdd.exist(m.u_bits, D) != ctrl.domain:
        raise ExportError("determinizing: the determinized controller's domain differs from the controller's (a bug)")
    return D, rule


def determinized_at(ctrl: Controller, idx: np.ndarray, rule: str = "auto") -> np.ndarray | None:
    """The determinized controller's input at one cell (per-subsystem flat codes, shape (N,)), or ``None``
    outside the domain: the answer of :func:`determinize` there, computed at that cell only (a query needs no
    determinization of the whole controller)."""
    if rule not in RULES:
        raise ExportError(f"unknown rule {rule!r}; expected one of {', '.join(RULES)}")
    m = ctrl.model
    layered = isinstance(ctrl, LayeredController)
    if rule == "earliest_layer" and not layered:
        raise ExportError("rule earliest_layer needs a layered controller; use --rule smallest_index")
    S = ctrl.input_set(idx)
    rule = resolve_rule(ctrl, rule)
    if rule == "earliest_layer":
        assert isinstance(ctrl, LayeredController)
        k = ctrl.layer_of(idx)
        if k is not None and k > 0:
            chain, admissible, M = ctrl.ingredients
            state = m.state_assignment([int(v) for v in idx])
            for Z in ctrl.layers[:k]:  # the earliest layer reachable in one step
                S = cpre_at_state(m, chain, admissible, M, state, m.to_next(Z), ctrl.chain_at_states)
                if S != m.bdd.false:
                    break
    rows = enumerate_cells(m, lexmin(m, S), m.u_digits())
    return rows[0] if rows.shape[0] else None


def _cofactors(g: Function, level: int) -> tuple[Function, Function]:
    """``(g|v=0, g|v=1)`` for the variable at ``level``, where ``g``'s top level is ``>= level``."""
    if g.var is None or g.level != level:
        return g, g
    reg = ~g if g.negated else g
    return (~reg.low, ~reg.high) if g.negated else (reg.low, reg.high)


def restrict(model: SymbolicModel, f: Function, care: Function) -> Function:
    """A BDD equal to ``f`` wherever ``care`` holds, usually smaller (Coudert and Madre's restrict: a branch
    where ``care`` is empty is replaced by its sibling; CUDD's ``Cudd_bddRestrict``, which ``dd`` does not wrap).

    The exported input bits are read only inside the domain, so they are restricted to it.
    """
    bdd = model.bdd
    memo: dict[tuple[int, int], Function] = {}

    def go(f: Function, c: Function) -> Function:
        if c == bdd.true or f.var is None or c == bdd.false:
            return f
        key = (int(f), int(c))
        hit = memo.get(key)
        if hit is not None:
            return hit
        if c.level < f.level:  # care tests a variable f ignores: either branch will do
            c0, c1 = _cofactors(c, c.level)
            out = go(f, c0 | c1)
        else:
            top = f.level
            f0, f1 = _cofactors(f, top)
            c0, c1 = _cofactors(c, top)
            if c0 == bdd.false:
                out = go(f1, c1)
            elif c1 == bdd.false:
                out = go(f0, c0)
            else:
                out = bdd.ite(bdd.var(bdd.var_at_level(top)), go(f1, c1), go(f0, c0))
        memo[key] = out
        return out

    with model.guard("simplifying the exported controller"):
        return go(f, care)


def bdd_table(model: SymbolicModel, D: Function, simplify: bool = True) -> BDDTable:
    """The node table of ``D`` over the state bits: the domain ``∃û.D`` and each chosen input bit
    ``∃û.(D ∧ û_b)`` (digit by digit, most significant first), sharing their nodes; with ``simplify`` the input
    bits are :func:`restrict` ed to the domain (they are read only there).

    The walk visits every node once (Python work proportional to the BDD, never to the states).
    """
    bdd = model.bdd
    with model.guard("projecting the determinized controller on the state bits"):
        domain = bdd.exist(model.u_bits, D)
        outputs = [bdd.exist(model.u_bits, D & model.var(b)) for b in model.u_bits]
    if simplify:
        outputs = [restrict(model, f, domain) for f in outputs]
    return node_table(model, domain, outputs)
