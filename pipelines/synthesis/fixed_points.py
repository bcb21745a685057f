"""The fixed points of the synthesis (Algorithm 5; docs/method.md §6), as functions of a controllable predecessor.

* :func:`safe`: safety ``□S`` as ``νZ. S ∧ ∃u.CPre(Z)``;
* :func:`reach`, :func:`reach_avoid`: ``S U T`` as ``μZ. (T ∨ ∃u.CPre(Z)) ∧ S ∧ ¬A`` with a progress controller
  (``S`` everything unless a safe set is given, ``A`` empty for plain reachability);
* :func:`cobuchi`: reach-and-stay ``□S ∧ ◇□φ`` as the co-Büchi ``μX. νY. (φ ∧ S ∧ ∃u.CPre(Y)) ∨ (S ∧ ∃u.CPre(X))``;
* :func:`reach_safe`: the same as ``Reach_S(Safe(φ ∧ S))``; :func:`reach_and_stay` reports both (docs/method.md §6).

Each takes a :class:`~.cpre.ControllablePredecessor` (SCOTS's ``solve_invariance_game`` style). By the feedback
refinement relation (Theorem 4.2) and soundness of the abstraction (Theorem 4.8), the controllers refine to the
concrete network.

Each takes an optional ``progress(iteration, message)`` (:data:`IterationProgress`), called once per outer and
once per inner iteration with the size of the current iterate (CUDD's model count of one BDD, linear in its
nodes; nothing is counted without a callback).
"""

from __future__ import annotations

import functools
import logging
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Concatenate, ParamSpec, TypeVar

from pipelines.symbolic.counting import count_states
from pipelines.symbolic.symbolic_model import Function, SymbolicModel
from pipelines.synthesis import results
from pipelines.synthesis.checkpoints import Checkpoints
from pipelines.synthesis.cpre import ControllablePredecessor
from pipelines.synthesis.local_games import invariant_bound
from pipelines.synthesis.quotient import Refinement

log = logging.getLogger(__name__)
P = ParamSpec("P")
R = TypeVar("R")

#: ``progress(iteration, message)``: the fixed point's own iteration (outer, or inner for an inner fixed point,
#: counted over the whole run) and a line such as ``"reach iteration 3: 1,234 states"``.
IterationProgress = Callable[[int, str], None]


@dataclass
class SynthesisResult:
    """A winning domain and a controller, with what it cost.

    Attributes
    ----------
    kind : str
        ``safe``, ``reach``, ``reach_avoid``, ``reach_and_stay/cobuchi``, ``reach_and_stay/reach_safe``, or
        ``reach_and_stay/contracts`` and ``safe/contracts`` (:mod:`.contracts`).
    domain : Function
        Winning states (current-state bits).
    controller : Function or None
        Pairs ``(x̂, û)`` over current-state and input bits; ``None`` for a layered result (see ``layers``).
    domain_states : int
        Exact number of abstract states in ``domain``.
    iterations : int
        Iterations of the (outer) fixed point.
    inner_iterations : int
        Iterations of inner fixed points (co-Büchi ``ν``; the safety part of Reach(Safe)); 0 if none.
    seconds : float
        Wall time of the fixed point(s), controller included.
    peak_nodes : int
        CUDD's peak of live nodes in the manager (``peak_live_nodes``) when the fixed point ended: since the
        manager was made, so it includes what came before in the same manager.
    details : dict
        Per-part counts and times (JSON-ready).
    layers : tuple of Function
        A layered controller instead of ``controller``: ``layers[0] ⊆ layers[1] ⊆ ... = domain`` over
        current-state bits. At a state first in ``layers[k]`` (``k > 0``) the admissible inputs are
        ``CPre(layers[k-1])``; in ``layers[0]`` they are ``CPre(layers[0])`` if ``stay`` else every valid input
        (the target of a reachability game). This is exactly the explicit progress controller, stored as the
        sets it is made of and evaluated at one state at a time (:meth:`~.cpre.ControllablePredecessor.cpre_at`).
    stay : bool
        See ``layers``.
    """

    kind: str
    domain: Function
    controller: Function | None
    domain_states: int
    iterations: int
    inner_iterations: int
    seconds: float
    peak_nodes: int
    details: dict[str, Any] = field(default_factory=dict)
    layers: tuple[Function, ...] = ()
    stay: bool = False

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers, no BDDs (:func:`.results.summary`)."""
        return results.summary(
            self,
            peak_nodes=self.peak_nodes,
            controller_form="layered" if self.layers else "explicit",
            controller_nodes=self.controller.dag_size if self.controller is not None else None,
            layer_nodes=[f.dag_size for f in self.layers],
            domain_nodes=self.domain.dag_size,
        )


def peak_live_nodes(model: SymbolicModel) -> int:
    """CUDD's peak of live nodes since the manager was made."""
    with warnings.catch_warnings():  # dd warns that 'mem' is now in bytes
        warnings.simplefilter("ignore")
        return int(model.bdd.statistics()["peak_live_nodes"])


#: Largest iterate (BDD nodes) whose states a progress line counts; a larger one is reported by its nodes. The exact
#: count walks the BDD in Python (0.46 s for the tanks' 116 k-node iterates, against 0.1 s in CUDD).
PROGRESS_COUNT_NODES = 50_000


def _size(model: SymbolicModel, current: Function | None) -> str:
    """``": 1,234 states"`` (exact) for a progress line, ``": 123,456 BDD nodes"`` above
    :data:`PROGRESS_COUNT_NODES`, ``""`` without an iterate.

    Never CUDD's own model count (``Cudd_CountMinterm``): called once per iteration in a manager that reads the
    parts of a partitioned fixed point back from DDDMP, it aborted the process (CUDD's "cuddGarbageCollect: problem
    in constants, dead count != deleted") on consensus N = 6 and 8, in helper processes and on the cluster alike;
    without it the same runs finish. Where inside CUDD the references go wrong was not traced.
    """
    if current is None:
        return ""
    nodes = current.dag_size
    if nodes > PROGRESS_COUNT_NODES:
        return f": {nodes:,} BDD nodes"
    return f": {count_states(model, current):,} states"


class _Meter:
    """Iteration counter, timer and peak-node reader of one fixed point.

    ``len(bdd)`` (CUDD's live-node count) walks the unique table: once per iteration it was 5 % of the tanks'
    synthesis (bench/run.py profile), so the peak is CUDD's own counter, read at the end.
    """

    def __init__(self, model: SymbolicModel, kind: str, progress: IterationProgress | None = None) -> None:
        self.model = model
        self.kind = kind
        self.progress = progress
        self.t0 = time.perf_counter()
        self.iterations = 0
        self.inner = 0
        self.peak = 0

    def tick(self, inner: bool = False, current: Function | None = None) -> None:
        """Count one iteration; ``current``: the iterate after it, whose size goes to ``progress``."""
        if inner:
            self.inner += 1
        else:
            self.iterations += 1
        if log.isEnabledFor(logging.INFO):
            log.info("%s: iteration %d (inner %d), %.2f s, %d live nodes", self.kind, self.iterations, self.inner,
                     self.seconds, len(self.model.bdd))
        if self.progress is not None:
            where = f"iteration {self.iterations + 1}, inner {self.inner}" if inner else f"iteration {self.iterations}"
            self.progress(self.inner if inner else self.iterations, f"{self.kind} {where}{_size(self.model, current)}")

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.t0


def _prefixed(progress: IterationProgress, prefix: str, iteration: int, message: str) -> None:
    """``progress`` with ``prefix`` before the message (names the part of a composite fixed point)."""
    progress(iteration, prefix + message)


def _guarded(
    fn: Callable[Concatenate[ControllablePredecessor, P], R],
) -> Callable[Concatenate[ControllablePredecessor, P], R]:
    """Run a fixed point inside :meth:`SymbolicModel.guard`: CUDD running out of memory becomes a clear error."""

    @functools.wraps(fn)
    def run(cpre: ControllablePredecessor, *args: P.args, **kwargs: P.kwargs) -> R:
        with cpre.model.guard(f"computing the {fn.__name__} fixed point"):
            return fn(cpre, *args, **kwargs)

    return run


def _result(
    cpre: ControllablePredecessor, kind: str, domain: Function, controller: Function | None, meter: _Meter,
    layers: Sequence[Function] = (), stay: bool = False, **details: Any,
) -> SynthesisResult:
    meter.peak = max(meter.peak, peak_live_nodes(cpre.model))
    return SynthesisResult(
        kind=kind,
        domain=domain,
        controller=controller,
        domain_states=count_states(cpre.model, domain),
        iterations=meter.iterations,
        inner_iterations=meter.inner,
        seconds=meter.seconds,
        peak_nodes=meter.peak,
        details={"method": cpre.method, "order": cpre.model.order, **details},
        layers=tuple(layers),
        stay=stay,
    )


@_guarded
def safe(
    cpre: ControllablePredecessor, S: Function, *, layered: bool = False, progress: IterationProgress | None = None,
    local_games: bool = True, checkpoints: Checkpoints | None = None, name: str = "safe",
    refine: Refinement | None = None,
) -> SynthesisResult:
    """Safety ``□S``: ``νZ. S ∧ ∃u.CPre(Z)`` (the invariance game of Algorithm 5, SCOTS's
    ``solve_invariance_game``); the controller allows every input that keeps the state in the invariant.

    ``local_games``: start the iteration from :func:`~.local_games.invariant_bound` instead of ``S`` where it cuts
    ``S`` at least in half (the same invariant in fewer, smaller iterates; ``details["local_games"]`` says what it
    took and whether it was used). Each iterate is
    ``Z ∧ ∃u.CPre(Z)``: from ``S`` the same sets as ``S ∧ ∃u.CPre(Z)``, and from the bound a decreasing sequence
    that stays between the invariant and those sets, so it stops at the invariant.
    ``layered``: return the invariant as a one-layer controller (``stay``) instead of ``Z ∧ CPre(Z)``.
    ``progress``: see :data:`IterationProgress`.

    ``checkpoints``: a store of this problem's iterates under ``name`` (:mod:`~.checkpoints`): the loop starts
    from a stored iterate (intersected with ``S``; ``details["resumed_at_iteration"]``), the local games then
    skipped, and hands the store every iterate. Any start inside ``S`` gives a controlled invariant inside ``S``;
    an iterate of the same problem gives the same one.

    ``refine``: ``cpre`` is a quotient (:mod:`~.quotient`) and its invariant is grown on the fine game
    (:class:`~.quotient.Refinement`, ``details["refinement"]``) before the controller, which then comes from the
    fine ``CPre``.
    """
    m = cpre.model
    meter = _Meter(m, "safe", progress)
    S = S & m.x_domain
    inside = cpre.within(S)  # every iterate is inside S
    details: dict[str, Any] = {}
    Z = S
    resumed = None if checkpoints is None else checkpoints.resume(m, name)
    if resumed is not None:
        Z, meter.iterations = resumed[0] & S, resumed[1]
        details["resumed_at_iteration"] = resumed[1]
    elif local_games:
        said = None if progress is None else functools.partial(_prefixed, progress, "safe ", 0)
        bound = invariant_bound(cpre, S, progress=said)
        Z = bound.start
        details["local_games"] = bound.summary()
    while True:
        Zn = Z & cpre.predecessors(Z, within=inside)
        meter.tick(current=Zn)
        if Zn == Z:
            break
        Z = Zn
        if checkpoints is not None:
            checkpoints.iterate(m, name, Z, meter.iterations)
    if checkpoints is not None:
        checkpoints.converged(m, name, Z, meter.iterations)
    stay = cpre
    if refine is not None:
        said = None if progress is None else functools.partial(_prefixed, progress, "safe ")
        Z, details["refinement"] = refine.grow(Z, S, progress=said)
        stay, inside = refine.fine, refine.fine.within(S)
    if layered:
        return _result(cpre, "safe", Z, None, meter, layers=(Z,), stay=True, **details)
    return _result(cpre, "safe", Z, Z & stay.cpre(Z, inside), meter, **details)


@_guarded
def reach(
    cpre: ControllablePredecessor, T: Function, avoid: Function | None = None, *, kind: str = "reach",
    layered: bool = False, safe: Function | None = None, progress: IterationProgress | None = None,
) -> SynthesisResult:
    """Reachability ``◇T`` while staying in ``S``: ``μZ. (T ∨ ∃u.CPre(Z)) ∧ S ∧ ¬A`` (``S`` every state and
    ``A`` empty unless given; Algorithm 5, SCOTS's ``solve_reachability_game``) with a progress controller.

    The winning set lies in ``S ∖ A``: targets outside it do not count (a run reaching them would have left
    ``S``), and a state enters only if some input leads surely into the previous iterate.

    An input counts at ``x̂`` only in the iteration where ``x̂`` entered the attractor (SCOTS keeps it that way):
    it then leads into the previous iterate, so every closed-loop run reaches ``T`` within as many steps as
    there were iterations. Target states get every (valid) input: the specification is met on arrival.

    ``layered``: keep the iterates instead of the controller (:class:`SynthesisResult` ``layers``); each
    iteration is then one ``∃u.CPre`` without materialising ``CPre`` over states and inputs, which on the
    consensus network is most of the time and nearly all of the memory of the explicit controller.
    ``safe``: the safe set ``S``. ``progress``: see :data:`IterationProgress`.
    """
    m = cpre.model
    meter = _Meter(m, kind, progress)
    keep = m.x_domain if avoid is None else m.x_domain & ~avoid
    # Only states of S can enter, so CPre is needed on S only (exact there, empty elsewhere: cpre.within).
    inside = None
    if safe is not None:
        keep &= safe
        inside = cpre.within(keep)
    Z = T & keep
    if layered:
        layers = [Z]
        while True:
            new = cpre.predecessors(Z, outside=~Z, within=inside) & keep & ~Z
            done = new == cpre.bdd.false
            if not done:
                Z |= new
                layers.append(Z)
            meter.tick(current=Z)
            if done:
                break
        return _result(cpre, kind, Z, None, meter, layers=layers)
    controller = Z & m.u_domain
    while True:
        C = cpre.cpre(Z, inside)
        new = cpre.pre(C) & keep & ~Z
        done = new == cpre.bdd.false
        if not done:
            controller |= C & new
            Z |= new
        meter.tick(current=Z)
        if done:
            break
    return _result(cpre, kind, Z, controller, meter)


@_guarded
def reach_avoid(
    cpre: ControllablePredecessor, T: Function, A: Function, *, layered: bool = False, safe: Function | None = None,
    progress: IterationProgress | None = None,
) -> SynthesisResult:
    """Reach-avoid: ``μZ. (T ∨ ∃u.CPre(Z)) ∧ S ∧ ¬A`` (:func:`reach` with ``A``; the states of ``A`` never enter).

    ``A`` is any set of states: a union of obstacle boxes is one BDD (the union of their cells).
    """
    return reach(cpre, T, A, kind="reach_avoid", layered=layered, safe=safe, progress=progress)


@_guarded
def cobuchi(
    cpre: ControllablePredecessor, phi: Function, *, safe: Function | None = None,
    progress: IterationProgress | None = None,
) -> SynthesisResult:
    """``◇□φ`` as ``μX. νY. (φ ∧ ∃u.CPre(Y)) ∨ ∃u.CPre(X)`` (docs/method.md §6); with a safe set ``S``, ``□S ∧ ◇□φ`` as
    ``μX. νY. (φ ∧ S ∧ ∃u.CPre(Y)) ∨ (S ∧ ∃u.CPre(X))``: every iterate lies in ``S``, so no run leaves it.

    Controller: a state that enters at outer iteration ``k+1`` (``X_{k+1} \\ X_k``) gets the inputs ``û`` with
    ``(φ(x̂) ∧ CPre(X_{k+1})(x̂, û)) ∨ CPre(X_k)(x̂, û)``. Along a closed-loop run the rank ``k`` never increases,
    and while it stays constant only the first disjunct can hold, so from some time on every state is in ``φ``.
    ``progress``: see :data:`IterationProgress` (one call per inner ``ν`` iteration and per outer one).
    """
    m = cpre.model
    meter = _Meter(m, "cobuchi", progress)
    top = m.x_domain if safe is None else m.x_domain & safe
    phi = phi & top
    on_phi = cpre.within(phi)  # the ν part is needed on φ only
    inside = None if safe is None else cpre.within(top)  # CPre(X) is needed on S only
    X = cpre.bdd.false
    controller = cpre.bdd.false
    while True:
        CX = cpre.cpre(X, inside)
        preX = cpre.pre(CX)
        Y = top
        while True:
            Yn = cpre.predecessors(Y, within=on_phi) | preX
            meter.tick(inner=True, current=Yn)
            if Yn == Y:
                break
            Y = Yn
        meter.tick(current=Y)
        if Y != X:
            controller |= (Y & ~X) & (cpre.cpre(Y, on_phi) | CX)
        if Y == X:
            break
        X = Y
    return _result(cpre, "reach_and_stay/cobuchi", X, controller, meter)


@_guarded
def reach_safe(
    cpre: ControllablePredecessor, phi: Function, *, layered: bool = False, safe_set: Function | None = None,
    progress: IterationProgress | None = None, local_games: bool = True, checkpoints: Checkpoints | None = None,
    refine: Refinement | None = None,
) -> SynthesisResult:
    """``◇□φ`` as ``Reach(Safe(φ))``: inside the safe set the safety controller, outside the reach controller.

    With ``safe_set`` ``S`` (``□S ∧ ◇□φ``): ``Reach_S(Safe(φ ∧ S))``, the invariant inside ``φ ∧ S`` and the
    attractor inside ``S`` (:func:`reach` with ``safe``), so no run leaves ``S``.

    ``layered``: the reach iterates over the safe set, with ``stay`` (layer 0 is the invariant).
    ``progress``: see :data:`IterationProgress`; the safety part's calls come first (``reach_safe/safe``).
    ``local_games``, ``checkpoints``, ``refine``: for the safety part (:func:`safe`, whose iterates are stored as
    ``reach_safe/safe``); the reach runs on ``cpre`` from the (grown) invariant.
    """
    meter = _Meter(cpre.model, "reach_safe")

    named = None if progress is None else functools.partial(_prefixed, progress, "reach_safe/")
    s = safe(cpre, phi if safe_set is None else phi & safe_set, layered=layered, progress=named,
             local_games=local_games, checkpoints=checkpoints, name="reach_safe/safe", refine=refine)
    r = reach(cpre, s.domain, layered=layered, safe=safe_set, progress=named)
    meter.iterations = r.iterations
    meter.inner = s.iterations
    meter.peak = max(s.peak_nodes, r.peak_nodes)
    extra: dict[str, Any] = dict(safe_states=s.domain_states, safe_seconds=s.seconds, reach_seconds=r.seconds)
    for key in ("local_games", "resumed_at_iteration", "refinement"):
        if key in s.details:
            extra[key] = s.details[key]
    if layered:
        return _result(cpre, "reach_and_stay/reach_safe", r.domain, None, meter, layers=r.layers, stay=True, **extra)
    controller = (s.domain & s.controller) | (~s.domain & r.controller)
    return _result(cpre, "reach_and_stay/reach_safe", r.domain, controller, meter, **extra)


REACH_AND_STAY = {"cobuchi": cobuchi, "reach_safe": reach_safe}


def reach_and_stay(
    cpre: ControllablePredecessor, phi: Function, methods: Sequence[str] = ("cobuchi", "reach_safe"), *,
    layered: bool = False, safe: Function | None = None, progress: IterationProgress | None = None,
    local_games: bool = True, checkpoints: Checkpoints | None = None, refine: Refinement | None = None,
) -> dict[str, SynthesisResult]:
    """``◇□φ`` (``□S ∧ ◇□φ`` with a safe set ``safe``) by each of ``methods`` (docs/method.md §6 asks for both domains to
    be reported).

    ``layered`` applies to ``reach_safe``; the co-Büchi controller is always explicit. ``progress``: see
    :data:`IterationProgress`, the methods' calls one after the other. ``local_games``, ``checkpoints``,
    ``refine``: see :func:`safe` (Reach(Safe)'s safety part; the co-Büchi fixed point is not refined).
    """
    out: dict[str, SynthesisResult] = {}
    for name in methods:
        if name == "reach_safe":
            out[name] = reach_safe(cpre, phi, layered=layered, safe_set=safe, progress=progress,
                                   local_games=local_games, checkpoints=checkpoints, refine=refine)
        elif name == "cobuchi":
            out[name] = cobuchi(cpre, phi, safe=safe, progress=progress)
        else:
            raise ValueError(f"unknown reach-and-stay fixed point {name!r}: use {sorted(REACH_AND_STAY)}")
    return out
