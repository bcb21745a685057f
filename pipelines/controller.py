"""Controllers as files, and their refinement to the concrete system (Theorem 4.2).

A controller is a BDD over current-state and input bits, written in DDDMP with a JSON header (variable order,
bit widths, the grids, the spec). :func:`~pipelines.controller_loading.load_controller` reads one without the job
store; its :meth:`Controller.inputs` quantizes a concrete state and returns the admissible concrete inputs there.

A :class:`LayeredController` is the same controller stored as what it is made of (the fixed point's iterates
and the controllable predecessor's ingredients) and evaluated at one state at a time
(:func:`~.synthesis.at_state.cpre_at_state`); where the explicit BDD is huge (consensus) it is the form that fits on
disk and answers in milliseconds.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipelines.errors import CompabsError
from pipelines.grid_controller import GridController
from pipelines.symbolic.counting import Sampler, enumerate_cells, sample, sampler
from pipelines.symbolic.files import dump
from pipelines.symbolic.joint_table import JointTable, contains, draw, joint_table
from pipelines.symbolic.node_table import BDDTable, node_table
from pipelines.symbolic.symbolic_model import Function
from pipelines.synthesis.at_state import ChainAtStates, cpre_at_state

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.synthesis.cpre import ControllablePredecessor
    from pipelines.synthesis.fixed_points import SynthesisResult

CONTROLLER_FILE = "controller"


class Controller(GridController):
    """A synthesized controller ``C(x̂) ⊆ Û``, refined by the feedback refinement relation.

    Parameters
    ----------
    model : SymbolicModel
        The manager the controller BDD lives in (its header gives the encoding).
    bdd : Function
        The controller over current-state and input bits.
    meta : dict
        ``state_grid`` (the composed state grid), ``input_grids`` (one per subsystem, in order), ``kind``,
        and what the job recorded.
    """

    def __init__(self, model, bdd, meta: dict) -> None:
        super().__init__(meta, meta)
        self._model = model
        self._bdd = bdd
        self._domain = model.bdd.exist(model.u_bits, bdd)
        self._domain_table: BDDTable | None = None  # built on the first in_domain
        self._samplers: dict[tuple[int, ...], Sampler] = {}
        self._joint_table: JointTable | None = None

    @property
    def model(self):
        """The :class:`~.symbolic.symbolic_model.SymbolicModel` the controller's BDDs live in."""
        return self._model

    @property
    def relation(self) -> Function:
        """The controller ``C(x̂, û)`` over current-state and input bits."""
        return self._bdd

    @property
    def domain(self) -> Function:
        """The controller's domain ``∃û.C`` over current-state bits."""
        return self._domain

    def input_set(self, idx: np.ndarray):
        """The inputs allowed at a cell as a BDD over the input bits."""
        return self._model.bdd.let(self._model.state_assignment([int(v) for v in idx]), self._bdd)

    def input_indices(self, idx: np.ndarray) -> np.ndarray:
        """Per-subsystem flat input indices allowed at a cell, shape (k, N)."""
        m = self._model
        return enumerate_cells(m, self.input_set(idx), m.u_digits())

    def choose(self, x: np.ndarray, rng: np.random.Generator, how: str = "random") -> np.ndarray | None:
        """One admissible concrete input at ``x``, shape (m_total,): uniform over the admissible joint inputs
        (``how="random"``) or the first in the BDD's variable order (``"first"``, deterministic; the same as
        ``inputs(x)[0]`` when the subsystems' blocks are in network order); ``None`` outside the domain.

        Costs a few BDD operations per input bit, where :meth:`inputs` lists every admissible joint input (tens
        of thousands at a consensus state).
        """
        return self.choose_many(np.asarray(x, dtype=float).reshape(1, -1), rng, how)[0]

    def choose_many(self, X: np.ndarray, rng: np.random.Generator, how: str = "random") -> list[np.ndarray | None]:
        """:meth:`choose` at each row of ``X``, shape (B, n), drawing from ``rng`` in row order (so the draws
        are those of :meth:`choose` row by row). Cells and input points are computed for all rows at once, the
        inputs drawn from the controller's node table (:mod:`~.symbolic.joint_table`, compiled, about a cell's
        cofactor per cell); a :class:`LayeredController`, which has no one BDD to tabulate, keeps the model counts
        of a cell's input set per cell (at most ``INPUT_CACHE`` cells).
        """
        idx, ok = self.cells(X)
        codes = np.zeros((len(ok), len(self._input_grids)), dtype=np.int64)
        table = self._joint()
        if table is not None:
            rows = np.flatnonzero(ok)
            codes[rows], ok[rows] = draw(table, idx[rows], rng if how == "random" else None)
            return self._points(codes, ok)
        for r in np.flatnonzero(ok):
            code = self._sampler(idx[r]).draw(rng if how == "random" else None)
            if code is None:
                ok[r] = False
            else:
                codes[r] = code
        return self._points(codes, ok)

    def _points(self, codes: np.ndarray, ok: np.ndarray) -> list[np.ndarray | None]:
        points = np.concatenate([g.points(g.unravel(codes[:, s])) for s, g in enumerate(self._input_grids)], axis=1)
        return [points[r] if ok[r] else None for r in range(len(ok))]

    def _joint(self) -> JointTable | None:
        """The controller's :class:`~.symbolic.joint_table.JointTable`, built on the first draw (``None``: each
        cell's inputs are counted on their own, as a :class:`LayeredController`'s)."""
        if self._joint_table is None:
            self._joint_table = joint_table(self._model, self._bdd & self._model.u_domain)
        return self._joint_table

    def allows(self, idx: np.ndarray, codes: np.ndarray) -> np.ndarray | None:
        """Whether the joint input ``codes`` (per subsystem, shape (B, N)) is allowed at each cell ``idx`` (B, n);
        ``None`` where the controller keeps no :class:`~.symbolic.joint_table.JointTable`."""
        table = self._joint()
        return None if table is None else contains(table, idx, codes)

    def _sampler(self, idx: np.ndarray) -> Sampler:
        key = tuple(int(v) for v in idx)
        hit = self._samplers.get(key)
        if hit is None:
            m = self._model
            hit = sampler(m, self.input_set(idx), m.u_digits())
            if len(self._samplers) >= INPUT_CACHE:
                self._samplers.clear()
            self._samplers[key] = hit
        return hit

    def inputs(self, x: np.ndarray) -> np.ndarray:
        """Admissible concrete inputs at the concrete state ``x``, shape (k, m_total); (0, m_total) outside."""
        idx = self.cell(x)
        if idx is None:
            return np.zeros((0, self.input_dim))
        flat = self.input_indices(idx)
        if flat.shape[0] == 0:
            return np.zeros((0, self.input_dim))
        parts = [g.points(g.unravel(flat[:, s])) for s, g in enumerate(self._input_grids)]
        return np.concatenate(parts, axis=1)

    def in_domain(self, idx: np.ndarray) -> np.ndarray:
        """Whether composed cells, shape (B, n), are in the controller's domain; bool (B,).

        One vectorised walk of the domain's node table (built once, :func:`~.symbolic.node_table.node_table`) for all
        cells: 0.2 s for 2·10^5 cells of the tanks' controller, where a ``let`` per cell takes about 8.5 s. A cell off the grid is in
        no domain (its bits could spell another cell's code)."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, self._state_grid.dim)
        on_grid = self._state_grid.on_grid(idx)
        if self._domain_table is None:
            self._domain_table = node_table(self._model, self._domain)
        out = np.zeros(idx.shape[0], dtype=bool)
        out[on_grid] = self._domain_table.evaluate(idx[on_grid])[:, 0]
        return out

    def sample_cells(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Cells drawn uniformly from the controller's domain, shape (count, n) (empty if the domain is).

        Exact model counts guide a walk down the domain BDD (:func:`~.symbolic.counting.sample`), so a domain of
        1e-5 of the state space costs no more than a large one, where rejection sampling would fail.
        """
        m = self._model
        return sample(m, self._domain, m.x_digits(), rng, size=count)

    def save(self, directory: str | os.PathLike[str], name: str = CONTROLLER_FILE) -> tuple[Path, ...]:
        return dump(self._model, Path(directory) / name, self._bdd, {**self._meta, "form": "explicit"})

    @property
    def nodes(self) -> int:
        """BDD nodes of what :meth:`save` writes."""
        return self._bdd.dag_size


INPUT_CACHE = 100_000
"""Cells whose input sets a :class:`LayeredController` keeps (each a BDD over the input bits only)."""


class LayeredController(Controller):
    """A progress controller kept as layers and evaluated on line (:class:`~.synthesis.fixed_points.SynthesisResult`).

    At a cell first in ``layers[k]`` the admissible inputs are ``CPre(layers[k-1])`` at that cell (Algorithm 5's
    reachability controller), in ``layers[0]`` ``CPre(layers[0])`` if ``stay`` (the invariant of Reach(Safe)) or
    every valid input (a reach target). The answer equals the explicit controller's, cell for cell (tested).

    Parameters
    ----------
    model : SymbolicModel
    admissible : Function
        States and inputs where every admissible internal input lets every subsystem move
        (:attr:`~.synthesis.cpre.ControllablePredecessor.admissible`).
    chain : sequence of (Function, list of str)
        The partitioned relations and the next-state bits each lets quantify
        (:attr:`~.synthesis.cpre.ControllablePredecessor.chain`).
    M : Function or None
        The interconnection over states and internal inputs for the shared-``w`` CPre, else ``None``.
    layers : sequence of Function
        Increasing sets over current-state bits; the last one is the domain.
    stay : bool
    meta : dict
        As for :class:`Controller`.
    """

    def __init__(self, model, admissible, chain, M, layers, stay: bool, meta: dict) -> None:  # noqa: PLR0913
        if not layers:
            raise CompabsError("a layered controller needs at least one layer")
        self._layers = tuple(layers)
        self._stay = bool(stay)
        self._chain = [(rel, list(bits)) for rel, bits in chain]
        self._M = M
        self._admissible = admissible
        self._next: dict[int, Function] = {}
        self._inputs: dict[tuple[int, ...], object] = {}
        self._at = ChainAtStates(model, self._chain)
        super().__init__(model, self._layers[-1], meta)
        self._domain = self._layers[-1]

    @classmethod
    def from_result(cls, cpre: ControllablePredecessor, result: SynthesisResult, meta: dict) -> LayeredController:
        """The controller of a layered :class:`~.synthesis.fixed_points.SynthesisResult` of ``cpre``."""
        return cls(cpre.model, cpre.admissible, cpre.chain, cpre.M, result.layers, result.stay, meta)

    @property
    def layers(self) -> tuple[Function, ...]:
        return self._layers

    @property
    def stay(self) -> bool:
        return self._stay

    @property
    def ingredients(self) -> tuple[list[tuple[Function, list[str]]], Function, Function | None]:
        """``(chain, admissible, M)``: the CPre ingredients (:func:`~.synthesis.cpre.bad_inputs`)."""
        return self._chain, self._admissible, self._M

    @property
    def chain_at_states(self) -> ChainAtStates:
        """The chain's cofactors at the cells met so far (:class:`~.synthesis.at_state.ChainAtStates`), for
        :func:`~.synthesis.at_state.cpre_at_state` at more cells."""
        return self._at

    @property
    def relation(self) -> Function:
        raise CompabsError("a layered controller is not stored as one BDD over states and inputs; evaluate it per "
                           "cell (input_set) or determinize it (pipelines.export)")

    @property
    def nodes(self) -> int:
        roots = [self._admissible, *(r for r, _ in self._chain), *self._layers] + ([self._M] if self._M is not None else [])
        return sum(f.dag_size for f in roots)

    def layer_of(self, idx: np.ndarray) -> int | None:
        """Index of the first layer holding the cell, or ``None`` outside the domain."""
        m = self._model
        state = m.state_assignment([int(v) for v in idx])
        if m.bdd.let(state, self._layers[-1]) != m.bdd.true:
            return None
        for k, layer in enumerate(self._layers):
            if m.bdd.let(state, layer) == m.bdd.true:
                return k
        return None  # pragma: no cover - the last layer holds it

    def _joint(self) -> None:
        return None  # no one BDD over states and inputs: each cell's inputs come from its layer's CPre

    def input_set(self, idx: np.ndarray):
        """As :meth:`Controller.input_set`; answers are kept per cell (at most ``INPUT_CACHE`` cells), since
        closed-loop runs that have reached the invariant revisit the same cells."""
        key = tuple(int(v) for v in idx)
        hit = self._inputs.get(key)
        if hit is not None:
            return hit
        m = self._model
        k = self.layer_of(idx)
        if k is None:
            out = m.bdd.false
        elif k == 0 and not self._stay:
            out = m.u_domain
        else:
            src = 0 if k == 0 else k - 1
            if src not in self._next:
                self._next[src] = m.to_next(self._layers[src])
            out = cpre_at_state(m, self._chain, self._admissible, self._M, m.state_assignment(list(key)),
                                self._next[src], self._at)
        if len(self._inputs) >= INPUT_CACHE:
            self._inputs.clear()
        self._inputs[key] = out
        return out

    def save(self, directory: str | os.PathLike[str], name: str = CONTROLLER_FILE) -> tuple[Path, ...]:
        roots = [self._admissible, *(r for r, _ in self._chain), *self._layers]
        if self._M is not None:
            roots.append(self._M)
        meta = {
            **self._meta,
            "form": "layered",
            "stay": self._stay,
            "chain_next_bits": [bits for _, bits in self._chain],
            "layers": len(self._layers),
            "shared": self._M is not None,
        }
        return dump(self._model, Path(directory) / name, roots, meta)


def controller_of(cpre: ControllablePredecessor, result: SynthesisResult, meta: dict) -> Controller:
    """The controller of a :class:`~.synthesis.fixed_points.SynthesisResult` of ``cpre``, explicit or layered."""
    if result.layers:
        return LayeredController.from_result(cpre, result, meta)
    return Controller(cpre.model, result.controller, meta)
