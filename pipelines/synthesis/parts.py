"""What one part of a partitioned ``∃u.CPre(Z)`` computes, wherever it runs (docs/method.md §6).

A :class:`Problem` is what every part of a call needs: the chain, the admissible pairs and (shared ``w``) ``M̂`` of
a :class:`~.cpre.ControllablePredecessor`, or of its :meth:`~.cpre.ControllablePredecessor.within` a set. It goes
to another process once (:func:`pack`: plain data and DDDMP bytes; :func:`unpack` there, into a model declared from
the same header), and each call then sends only ``Z`` (and ``outside``). A part is named by a :class:`PartSpec`;
:func:`compute` gives its answer from the problem, :func:`join` the split cut's second phase, and :func:`solve`
does both from the bytes a transport moves. Which parts a call has, and why their union is the whole, is
:mod:`.partitioned`'s business; the transports (``workers/``) only move problems and parts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

from pipelines.symbolic.files import from_bytes, header, model_from_header, to_bytes
from pipelines.symbolic.symbolic_model import Function, SymbolicModel, and_exists
from pipelines.synthesis.cpre import bad_inputs, predecessors_of
from pipelines.synthesis.partition import admitting_below, lexicographic_part, lowest_code_states, w_window
from pipelines.synthesis.schedule import Chain
from pipelines.synthesis.symmetry import Symmetry, cached_symmetry

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.synthesis.cpre import ControllablePredecessor, Within

KINDS = ("states", "window", "bad")
"""What a part computes (:class:`PartSpec`)."""

NOT_Z = "not Z"
"""What a part is sent for ``outside`` when it is ``¬Z`` (the reach loop's, every call): the part complements the
``Z`` it read (constant time in CUDD) instead of the caller writing, sending and each part reading a second set."""

Outside = bytes | str | None
"""A part's ``outside`` as sent: DDDMP bytes, :data:`NOT_Z`, or ``None`` (none)."""


class PartSpec(NamedTuple):
    """One part of a call: ``kind`` over the codes of ``digits`` in ``[start, end)`` (lexicographic; ``end =
    None``: no upper end, codes past the grid included).

    ``states``: ``part ∧ ∃u.CPre(Z)`` for the current states of the range (:func:`~.cpre.predecessors_of`).
    ``window``: ``∃u.CPre(Z)`` on the states whose lowest admissible code of the internal variable ``digits[0]``
    lies in the range, the chain run on the ``ŵ`` cells they admit (:func:`window_predecessors`).
    ``bad``: the pairs ``(x̂, û)`` with a successor outside ``Z`` for some admissible ``ŵ`` of the range
    (:func:`~.cpre.bad_inputs`): the ``w`` cut's parts and the split cut's first phase (:func:`join` is its
    second).
    """

    kind: str
    digits: tuple[str, ...]
    start: tuple[int, ...]
    end: tuple[int, ...] | None


class Problem(NamedTuple):
    """The ingredients every part of a call reads, in one process's model.

    ``memo`` holds sets every part of the problem would compute again (:func:`below`, :func:`care`, the
    symmetries of :func:`symmetry`): computed once per problem, dropped with it.
    """

    model: SymbolicModel
    chain: Chain
    admissible: Function
    M: Function | None
    u_bits: Sequence[str]
    w_bits: Sequence[str]
    memo: dict[tuple, Any]

    @classmethod
    def of(cls, cpre: ControllablePredecessor, within: Within | None = None) -> Problem:
        """The problem of ``cpre`` (restricted to the set of ``within``, if given)."""
        chain, admissible = (cpre.chain, cpre.admissible) if within is None else within
        return cls(cpre.model, list(chain), admissible, cpre.M, list(cpre.u_bits), list(cpre.w_bits), {})


def pack(problem: Problem, owner: str) -> dict[str, Any]:
    """``problem`` for another process: its model's header, the relations as DDDMP bytes, the bits; ``owner`` names
    the model the problem belongs to (problems of one owner share a model there, :func:`unpack`)."""
    m = problem.model
    roots = [rel for rel, _ in problem.chain] + [problem.admissible] + ([] if problem.M is None else [problem.M])
    return {"model": owner, "header": header(m), "max_memory": m.max_memory,
            "roots": [to_bytes(m, f, "writing the CPre's relations for another process") for f in roots],
            "xn": [list(xn) for _, xn in problem.chain], "u_bits": list(problem.u_bits),
            "w_bits": list(problem.w_bits)}


def unpack(payload: dict[str, Any], model: SymbolicModel | None = None) -> Problem:
    """The :class:`Problem` of a :func:`pack` payload, in ``model`` (one declared from the payload's header if
    ``None``; another problem of the same owner's model keeps both in one CUDD manager)."""
    if model is None:
        model = model_from_header(payload["header"], payload["max_memory"])
    roots = [from_bytes(model, b, "loading the CPre's relations") for b in payload["roots"]]
    n = len(payload["xn"])
    chain = list(zip(roots[:n], payload["xn"]))
    M = roots[n + 1] if len(roots) > n + 1 else None  # the shared method's interconnection
    return Problem(model, chain, roots[n], M, payload["u_bits"], payload["w_bits"], {})


def symmetry(problem: Problem, classes: Sequence[Sequence[int]] | None) -> Symmetry | None:
    """The :class:`~.symmetry.Symmetry` of ``classes`` on the problem's model, built once per problem (``None``
    without classes): a call ships only the classes."""
    return None if classes is None else cached_symmetry(problem.memo, problem.model, classes, owner="symmetry")


def below(problem: Problem, digit: str) -> Callable[[int], Function]:
    """:func:`~.partition.admitting_below` on the problem's ``M̂``, each code's set computed once per problem (a
    part's range moves between calls, but its ends are among the cells of ``ŵ``)."""
    assert problem.M is not None
    M = problem.M

    def admitting(c: int) -> Function:
        key = ("below", digit, c)
        f = problem.memo.get(key)
        if f is None:
            f = problem.memo[key] = admitting_below(problem.model, M, digit, c)
        return f

    return admitting


def care(problem: Problem, sym: Symmetry | None) -> Function | None:
    """``M̂`` on the orbit representatives of ``sym`` (``M̂`` itself without one; ``None`` for the per-subsystem
    CPre), computed once per problem and symmetry instead of by each part of each call: with the order of
    :func:`~.cpre.bad_inputs`' conjunctions (the part first) it is about 1 % of the parts' CPU over a Reach(Safe)
    of consensus N = 6 on 16 workers, 14 % computed by each part."""
    if problem.M is None or sym is None:
        return problem.M
    key = ("care", tuple(tuple(c) for c in sym.classes))
    f = problem.memo.get(key)
    if f is None:
        f = problem.memo[key] = problem.M & sym.representatives
    return f


def window_predecessors(
    model: SymbolicModel, chain: Chain, admissible: Function, M: Function, w_bits: Sequence[str],
    u_bits: Sequence[str], Z: Function, states: Function, window: Function, outside: Function | None = None,
) -> Function:
    """``states ∧ ∃u.CPre(Z)`` for the shared CPre, with ``ŵ`` restricted to ``window`` before the chain runs.

    ``states`` and ``window`` come from :func:`~.partition.w_window`: every internal input a state of ``states``
    admits lies in ``window`` (``states ∧ M̂ → window``). Then for ``x̂`` in ``states``

        ∃ŵ. M̂ ∧ B(x̂, û, ŵ)  =  ∃ŵ. M̂ ∧ states ∧ [window ∧ B](x̂, û, ŵ),   B = ∃x'.(∧_i T_i ∧ ¬Z'),

    and ``window`` reads only ``w`` bits, so it commutes with ``∃x'``: conjoined into the chain's first operand it
    cuts the chain down to the ``ŵ`` cells of the window (the chain's cost is spread over ``ŵ``, which sits on top
    of the shared order). ``states`` is conjoined only where the result is read (the ``∃w`` step and the
    admissible pairs): in the chain's first operand it blew up the intermediate products (``M̂``-shaped sets of
    states cut across every subsystem's block). The result is exact on ``states`` and empty outside it, so the
    windows of :func:`~.partition.w_window` (a partition of the states) give parts whose union is ``∃u.CPre(Z)``
    with nothing to join but a disjunction of sets of states; a cut along ``ŵ`` alone leaves the pairs ``(x̂, û)``
    of every part to be joined before one ``∃u`` step.
    """
    # bad_inputs conjoins its part into the chain's first operand and into M̂ ∧ outside; ``window`` there changes
    # nothing, since M̂ ∧ states → window (the w cut passes its w ranges the same way).
    care_set = states if outside is None else states & outside
    bad = bad_inputs(model, chain, M, w_bits, Z, care_set, window)
    return and_exists(admissible & states, ~bad, list(u_bits))


def compute(problem: Problem, spec: PartSpec, Z: Function, outside: Function | None,
            sym: Symmetry | None = None) -> Function:
    """The answer of the part ``spec`` (:class:`PartSpec`) of ``∃u.CPre(Z)`` on ``outside``.

    With the symmetry ``sym`` (the sets of the call invariant under it) a ``states`` or ``window`` part works on
    its representatives and closes its answer (the union of the closures is the whole: closing distributes over
    unions; the windows are invariant, since ``M̂`` is). The representatives go where the states go (the ``∃w``
    step and the admissible pairs), not into the chain's first operand: on consensus N = 6, over a Reach(Safe), the
    two windows' slower parts take 1.07x as long with them in the chain too and 1.46x without them. A ``bad`` part
    reads ``M̂`` on the representatives only (:func:`care`) and is not closed: :func:`join` reads it there.
    """
    m, start, end = problem.model, spec.start, spec.end
    reps = None if sym is None else sym.representatives
    if spec.kind == "states":
        part = lexicographic_part(m, spec.digits, start, end)
        result = predecessors_of(m, problem.chain, problem.admissible, problem.M, problem.w_bits, problem.u_bits, Z,
                                 outside, part, reps)
    elif spec.kind == "window":
        assert problem.M is not None
        digit = spec.digits[0]
        states, window = w_window(m, problem.M, digit, start[0], None if end is None else end[0],
                                  below(problem, digit))
        if reps is not None:
            states &= reps
        result = window_predecessors(m, problem.chain, problem.admissible, problem.M, problem.w_bits,
                                     problem.u_bits, Z, states, window, outside)
    elif spec.kind == "bad":
        part = lexicographic_part(m, spec.digits, start, end)
        return bad_inputs(m, problem.chain, care(problem, sym), problem.w_bits, Z, outside, part)
    else:
        raise ValueError(f"a part's kind is one of {KINDS}, not {spec.kind!r}")
    return result if sym is None else sym.close(result)


def join(problem: Problem, spec: PartSpec, bad: Iterable[Function], sym: Symmetry | None = None) -> Function:
    """The split cut's second phase: ``states ∧ ∃u.CPre(Z)`` for the states whose lowest admissible code of
    ``spec.digits[0]`` lies in the range of ``spec`` (:func:`~.partition.w_window`), from the ``bad`` parts
    (:func:`compute`) of the ranges of ``ŵ`` those states admit, read one at a time.

    Exact: a state ``x̂`` of the range admits only ``ŵ`` of its window, so the pairs bad for ``x̂`` come from the
    ranges the window meets, and ``∃u. adm ∧ states ∧ ¬(∨ bad)`` is the window cut's answer on these states
    (closed under ``sym``, if given). The good pairs of the range's states are cut down by each range's bad ones in
    turn, so every operand stays within those states: OR-ing the bad pairs first spans every state of those ranges
    (over a Reach(Safe) of consensus N = 6 on 16 workers, about 3x the CPU).
    """
    assert problem.M is not None
    digit = spec.digits[0]
    states = lowest_code_states(problem.model, problem.M, digit, spec.start[0],
                                None if spec.end is None else spec.end[0], below(problem, digit))
    if sym is not None:
        states &= sym.representatives
    good = problem.admissible & states
    for b in bad:
        good &= ~b
    result = problem.model.bdd.exist(list(problem.u_bits), good)
    return result if sym is None else sym.close(result)


def read_outside(model: SymbolicModel, Z: Function, outside: Outside) -> Function | None:
    """A part's ``outside`` as sent (:data:`Outside`), as a set of ``model`` (``Z``: the call's ``Z`` there)."""
    if outside is None:
        return None
    if isinstance(outside, bytes):
        return from_bytes(model, outside, "reading a part's outside")
    if outside != NOT_Z:
        raise ValueError(f"a part's outside is DDDMP bytes, {NOT_Z!r} or None, not {outside!r}")
    return ~Z


def solve(problem: Problem, spec: PartSpec, Z: bytes, outside: Outside,
          classes: Sequence[Sequence[int]] | None = None) -> Function:
    """:func:`compute` from the sets as a transport sent them (DDDMP bytes, :data:`NOT_Z`), with the symmetry of
    ``classes`` (if given), under CUDD's memory guard."""
    m = problem.model
    with m.guard("computing a part of CPre"):
        z = from_bytes(m, Z, "reading a part's Z")
        return compute(problem, spec, z, read_outside(m, z, outside), symmetry(problem, classes))


__all__ = ["KINDS", "NOT_Z", "Outside", "PartSpec", "Problem", "below", "care", "compute", "join", "pack",
           "read_outside", "solve", "symmetry", "unpack", "window_predecessors"]
