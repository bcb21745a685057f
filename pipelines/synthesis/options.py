"""How a game is solved: :class:`SynthesisOptions`, built in one place from a job spec's options.

:func:`~.synthesize.synthesize` takes one of these beside the abstraction and the specification. The fields
``processes``, ``parallel_after`` and ``auto_parts`` say how the fixed points' ``∃u.CPre`` is split into parts and
where those run; they change the time a synthesis takes, never its results. The others choose what is computed
(the variable order, the reach-and-stay fixed points, a quotient) or how (symmetry, local games).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.spec.model import OptionsSpec
    from pipelines.temporal.automaton import Automaton

#: The forms of a BDD controller: ``explicit`` (one BDD over states and inputs), ``layered`` (the fixed point's
#: iterates, evaluated at one state at a time) or ``auto`` (layered for the shared-``w`` CPre).
CONTROLLER_FORMS = ("auto", "explicit", "layered")

IndexBox = tuple[Sequence[int], Sequence[int]]


@dataclass(frozen=True)
class SynthesisOptions:
    """The choices of a synthesis (module docstring).

    Attributes
    ----------
    order, method, max_memory, chain_order
        The variable order (``None``: :func:`~pipelines.symbolic.order.default_order`), the CPre's method, CUDD's
        memory and the order of the relational products (:meth:`~.cpre.ControllablePredecessor.from_network`).
    controller_form : {'auto', 'explicit', 'layered'}
        :data:`CONTROLLER_FORMS`; ``layered`` where the explicit controller is the largest BDD of the job
        (consensus N = 8: 2.4 GB as DDDMP).
    reach_and_stay_methods : tuple of str
        The reach-and-stay fixed points (:func:`~.fixed_points.reach_and_stay`).
    symmetry, local_games : bool
        Use interchangeable subsystems (:mod:`~.symmetry`) and start safety fixed points from the bound of
        :mod:`~.local_games`: the same results, faster where they apply.
    quotient_level, refine_rounds : int
        Solve on the quotient of ``2^k`` cells per coordinate (:mod:`~.quotient`; ``0``: the exact game) and grow
        its safety invariant on the fine game that many rounds.
    initial_cells : tuple of (first, last)
        Per initial state of the spec, the box of cells containing it: the domain bound names those it proves
        outside the domain before the fixed points run.
    processes, parallel_after, auto_parts
        Parts of ``∃u.CPre`` (an int or ``'auto'``), how long one step must take in one process before they start,
        and what ``'auto'`` means when the parts run elsewhere (:class:`~.cpre.ControllablePredecessor`).
    automaton : Automaton, optional
        An ``ltl`` specification's automaton (``workers.automata.spec_automaton``, which runs MONA): its product
        game with the abstraction is solved (:func:`~.product.reach_symbolic`).
    """

    order: str | None = None
    method: str = "auto"
    max_memory: int | None = None
    chain_order: str = "greedy"
    controller_form: str = "auto"
    reach_and_stay_methods: tuple[str, ...] = ("cobuchi", "reach_safe")
    symmetry: bool = True
    local_games: bool = True
    quotient_level: int = 0
    refine_rounds: int = 0
    initial_cells: tuple[IndexBox, ...] = ()
    processes: int | str = 1
    parallel_after: float = 1.0
    auto_parts: int | None = None
    automaton: Automaton | None = None

    def __post_init__(self) -> None:
        if self.controller_form not in CONTROLLER_FORMS:
            raise ValueError(f"controller_form must be auto, explicit or layered, got {self.controller_form!r}")
        if self.refine_rounds and not self.quotient_level:
            raise ValueError("refine_rounds grows a quotient's invariant: it needs quotient_level > 0")

    @classmethod
    def from_spec(cls, options: OptionsSpec, initial_cells: Sequence[IndexBox] = ()) -> SynthesisOptions:
        """The options a job spec's ``options`` section asks for (the one place they are read for synthesis)."""
        return cls(reach_and_stay_methods=tuple(options.fixed_points), quotient_level=options.synthesis_quotient,
                   refine_rounds=options.synthesis_refine, initial_cells=tuple(initial_cells),
                   processes=options.synthesis_processes, parallel_after=options.synthesis_parallel_after)
