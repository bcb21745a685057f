"""Controllers with memory: the controller of an ``ltl`` specification's product game (docs/spec.md,
"Temporal-logic tasks"; :mod:`pipelines.synthesis.product`).

A product controller reads the automaton state ``q`` as well as the cell. At run time it tracks ``q`` on the
letters the concrete states really carry (:func:`~pipelines.temporal.labels.letters_at`, the atoms' closed boxes):
``q₀' = δ(q₀, σ(x₀))`` at the start, ``q' = δ(q, σ(x'))`` after each step, and applies an input of
``C_q(x̂)``, the product game's progress controller at ``(q, x̂)``. Each step lowers the product layer, so a run
from a domain state reaches an accepting ``q`` (the trace so far satisfies the formula) within the layer of its
first product state (:meth:`ProductController.layer_of`).

Two forms, after the back end that solved the game:

* arrays (explicit games): per automaton state an :class:`~.array_controller.ArrayController` over the cells, the
  layers, the domain; on disk ``NAME.json`` (``format`` :data:`PRODUCT_FORMAT`) and ``NAME.npz``;
* BDDs (any network): per automaton state a :class:`~.controller.Controller` (the pairs ``(x̂, û)`` of ``C_q``)
  and the domain, in one manager; on disk a symbolic dump (:func:`~.symbolic.files.dump`) whose ``meta`` says
  ``form: product``. Its layers are saved as the binary digits of each winning product state's layer, per
  automaton state ``meta["layer_bits"]`` BDDs after the domain (:func:`layer_digits`), so a loaded controller
  bounds each run as the job's own does.

Both headers record the automaton (:meth:`~pipelines.temporal.automaton.Automaton.to_json`) and the atoms'
closed boxes in ``meta``, and carry the integrity record every controller has (:mod:`.controller_integrity`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipelines.array_controller import ArrayController
from pipelines.controller import Controller
from pipelines.controller_integrity import (
    ControllerIntegrityError,
    read_arrays_header,
    seal,
)
from pipelines.errors import CompabsError
from pipelines.grid_controller import GridController
from pipelines.temporal.automaton import Automaton
from pipelines.temporal.labels import letters_at

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.symbolic.symbolic_model import Function, SymbolicModel
    from pipelines.synthesis.product import ProductResult, SymbolicProductResult
    from pipelines.temporal.labels import Labelling

#: ``format`` of the arrays form's header.
PRODUCT_FORMAT = "compabs-product-controller/1"
#: ``meta["form"]`` of both forms.
FORM = "product"

Boxes = list[tuple[np.ndarray, np.ndarray]]


class ProductController(GridController):
    """A controller with memory ``C_q(x̂) ⊆ Û`` (module docstring).

    Parameters
    ----------
    automaton : Automaton
    regions : sequence of list of (lb, ub)
        Per atom (in the automaton's bit order) its closed boxes of the composed state.
    per_state : sequence of ArrayController or Controller
        Per automaton state ``q``, the controller ``C_q`` over the cells (its domain: the cells ``x̂`` with
        ``(q, x̂)`` winning).
    domain : ndarray of bool (n_x,) or Function
        The cells from which every run starts in the winning set, whatever letter its first state carries.
    meta : dict
        ``state_grid``, ``input_grids``, ``kind``, ``automaton``, ``regions`` and what the job recorded.
    layers : ndarray (n_q, n_x), or per state a list of Function, or None
        The product layers (arrays), or per state the winning sets after each iteration (BDDs); ``None``: a
        loaded BDD form, whose ``digits`` give the layers.
    digits : per state a list of Function, optional
        A loaded BDD form's layers as binary digits (:func:`layer_digits`); without them (and without
        ``layers``) :meth:`layer_of` answers the game's iterations.
    """

    def __init__(self, automaton: Automaton, regions: Sequence[Boxes], per_state: Sequence[ArrayController | Controller],
                 domain: np.ndarray | Function, meta: Mapping[str, Any], layers: Any = None,
                 digits: Sequence[Sequence[Function]] | None = None) -> None:
        super().__init__(meta, {**meta, "form": FORM})
        if len(per_state) != automaton.n_states or len(regions) != len(automaton.atoms):
            raise CompabsError(f"a product controller has one controller per automaton state ({automaton.n_states}) "
                               f"and one region per atom ({len(automaton.atoms)}); got {len(per_state)} and "
                               f"{len(regions)}")
        self._automaton = automaton
        self._regions = tuple([(np.asarray(lb, float), np.asarray(ub, float)) for lb, ub in boxes] for boxes in regions)
        self._per_state = list(per_state)
        self._domain = domain
        self._layers = layers
        self._digits = None if digits is None else [list(d) for d in digits]
        self._domain_table: Any = None

    # ------------------------------------------------------------------ built from a product game
    @classmethod
    def from_explicit(cls, result: ProductResult, labelling: Labelling, meta: Mapping[str, Any]) -> ProductController:
        """The controller of :func:`~.synthesis.product.reach_explicit`'s result."""
        meta = _product_meta(meta, result.automaton, labelling.concrete)
        per_state = [ArrayController(result.admissible[q], result.layer[q], meta)
                     for q in range(result.automaton.n_states)]
        return cls(result.automaton, labelling.concrete, per_state, np.asarray(result.domain, dtype=bool), meta,
                   np.asarray(result.layer, dtype=np.int32))

    @classmethod
    def from_symbolic(cls, model: SymbolicModel, result: SymbolicProductResult, labelling: Labelling,
                      meta: Mapping[str, Any]) -> ProductController:
        """The controller of :func:`~.synthesis.product.reach_symbolic`'s result (BDDs of ``model``)."""
        meta = {**_product_meta(meta, result.automaton, labelling.concrete), "iterations": result.iterations}
        per_state = [Controller(model, c, meta) for c in result.controller]
        return cls(result.automaton, labelling.concrete, per_state, result.domain, meta, result.layers)

    # ------------------------------------------------------------------ what it is
    @property
    def automaton(self) -> Automaton:
        return self._automaton

    @property
    def per_state(self) -> list[ArrayController | Controller]:
        """``C_q`` for each automaton state ``q``."""
        return list(self._per_state)

    @property
    def is_symbolic(self) -> bool:
        return not isinstance(self._domain, np.ndarray)

    @property
    def nodes(self) -> int:
        """BDD nodes (BDD form) or bytes of the arrays (arrays form) of what :meth:`save` writes."""
        if self.is_symbolic:
            return sum(c.nodes for c in self._per_state) + int(self._domain.dag_size)  # type: ignore[union-attr]
        return sum(c.nodes for c in self._per_state) + int(np.asarray(self._domain).size // 8)

    # ------------------------------------------------------------------ the memory
    def letters_at(self, X: np.ndarray) -> np.ndarray:
        """The letter each concrete state of ``X`` (shape (B, n)) carries; int64 (B,)."""
        return letters_at(self._regions, X)

    def initial_state(self, X: np.ndarray) -> np.ndarray:
        """The automaton state after the first letter of runs starting at ``X``: ``δ(q₀, σ(x₀))``; int (B,)."""
        return self._automaton.delta[self._automaton.initial, self.letters_at(X)].astype(np.int64)

    def automaton_state_after(self, q: np.ndarray | int, X: np.ndarray) -> np.ndarray:
        """The automaton states after runs in states ``q`` move to the concrete states ``X``: ``δ(q, σ(x))``."""
        q = np.broadcast_to(np.asarray(q, dtype=np.int64), (np.atleast_2d(X).shape[0],))
        return self._automaton.delta[q, self.letters_at(X)].astype(np.int64)

    def accepting(self, q: np.ndarray | int) -> np.ndarray:
        """Whether the automaton states ``q`` accept (the trace so far satisfies the formula)."""
        return self._automaton.accepting[np.asarray(q, dtype=np.int64)]

    # ------------------------------------------------------------------ queries
    def in_domain(self, idx: np.ndarray) -> np.ndarray:
        """Whether composed cells, shape (B, n), are in the controller's domain (every first letter wins); bool
        (B,), off the grid: not."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, self._state_grid.dim)
        on = self._state_grid.on_grid(idx)
        out = np.zeros(idx.shape[0], dtype=bool)
        if not self.is_symbolic:
            out[on] = np.asarray(self._domain)[self._state_grid.ravel(idx[on])]
            return out
        if self._domain_table is None:
            from pipelines.symbolic.node_table import node_table

            self._domain_table = node_table(self._per_state[0].model, self._domain)  # type: ignore[union-attr]
        out[on] = self._domain_table.evaluate(idx[on])[:, 0]
        return out

    def winning(self, idx: np.ndarray, q: np.ndarray | int) -> np.ndarray:
        """Whether the product states ``(q, x̂)`` (cells shape (B, n), states (B,) or one) are winning; bool (B,)."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, self._state_grid.dim)
        q = np.broadcast_to(np.asarray(q, dtype=np.int64), (idx.shape[0],))
        out = np.zeros(idx.shape[0], dtype=bool)
        for state in np.unique(q).tolist():  # automaton states: a handful; the cells are bulk
            rows = np.flatnonzero(q == state)
            out[rows] = self._per_state[state].in_domain(idx[rows])
        return out

    def layer_of(self, idx: np.ndarray, q: int) -> int | None:
        """The product layer of ``(q, x̂)``: a run from it accepts within that many steps; ``None`` if losing. A
        loaded BDD form reads it from its saved digits (one without them answers the game's iterations)."""
        idx = np.asarray(idx, dtype=np.int64).reshape(1, -1)
        if not self.winning(idx, q)[0]:
            return None
        if self._layers is None and self._digits is None:
            return int(self._meta.get("iterations", 0))
        if not self.is_symbolic:
            return int(self._layers[q, self._state_grid.ravel(idx)[0]])
        model = self._per_state[0].model  # type: ignore[union-attr]
        state = model.state_assignment([int(v) for v in idx[0]])
        if self._layers is None:
            assert self._digits is not None
            return sum(1 << b for b, f in enumerate(self._digits[int(q)]) if model.bdd.let(state, f) == model.bdd.true)
        for k, layer in enumerate(self._layers[q]):
            if model.bdd.let(state, layer) == model.bdd.true:
                return k
        return None  # pragma: no cover - the last layer is the winning set

    def inputs(self, x: np.ndarray, q: int) -> np.ndarray:
        """Admissible concrete inputs at the concrete state ``x`` in automaton state ``q``, shape (k, m)."""
        return self._per_state[int(q)].inputs(x)

    def choose_many(self, X: np.ndarray, q: np.ndarray, rng: np.random.Generator, how: str = "random"
                    ) -> list[np.ndarray | None]:
        """One admissible concrete input per row of ``X`` (shape (B, n)) in automaton states ``q`` (B,), ``None``
        where ``(q, x̂)`` is losing; rows grouped by their automaton state, each group drawn by ``C_q``."""
        X = np.asarray(X, dtype=float).reshape(-1, self._state_grid.dim)
        q = np.asarray(q, dtype=np.int64).reshape(-1)
        out: list[np.ndarray | None] = [None] * X.shape[0]
        for state in np.unique(q).tolist():
            rows = np.flatnonzero(q == state)
            for r, u in zip(rows.tolist(), self._per_state[state].choose_many(X[rows], rng, how)):
                out[r] = u
        return out

    def choose(self, x: np.ndarray, q: int, rng: np.random.Generator, how: str = "random") -> np.ndarray | None:
        return self.choose_many(np.asarray(x, dtype=float).reshape(1, -1), np.array([q]), rng, how)[0]

    def sample_cells(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Cells drawn uniformly (with replacement) from the domain, shape (count, n)."""
        if not self.is_symbolic:
            cells = np.flatnonzero(np.asarray(self._domain))
            if cells.size == 0 or count <= 0:
                return np.zeros((0, self._state_grid.dim), dtype=np.int64)
            return self._state_grid.unravel(cells[rng.integers(cells.size, size=count)])
        from pipelines.symbolic.counting import sample

        model = self._per_state[0].model  # type: ignore[union-attr]
        return sample(model, self._domain, model.x_digits(), rng, size=count)

    # ------------------------------------------------------------------ files
    def save(self, directory: str | os.PathLike[str], name: str) -> tuple[Path, ...]:
        """Write the controller (module docstring); returns the paths, payload first, header last."""
        meta = {**self._meta, "form": FORM, "states": self._automaton.n_states}
        if self.is_symbolic:
            from pipelines.symbolic.files import dump

            model = self._per_state[0].model  # type: ignore[union-attr]
            digits = self._digits if self._layers is None else layer_digits(model, self._layers)
            roots = [c.relation for c in self._per_state] + [self._domain]  # type: ignore[union-attr]
            if digits is not None:
                meta["layer_bits"] = len(digits[0]) if digits else 0
                roots += [f for per_q in digits for f in per_q]
            return dump(model, Path(directory) / name, roots, meta)
        base = Path(directory) / name
        arrays, head = base.with_name(base.name + ".npz"), base.with_name(base.name + ".json")
        admissible = np.stack([c.admissible for c in self._per_state])  # type: ignore[union-attr]
        with open(arrays, "wb") as f:
            np.savez_compressed(f, admissible=np.packbits(admissible, axis=2), layer=self._layers,
                                domain=np.asarray(self._domain, dtype=bool))
        header = {"format": PRODUCT_FORMAT, "meta": meta, "roots": [arrays.name], "shape": list(admissible.shape)}
        head.write_text(json.dumps(seal(header, head.parent, [arrays.name]), indent=1))
        return arrays, head

    @classmethod
    def load(cls, directory: str | os.PathLike[str], name: str, job_hash: str | None = None) -> ProductController:
        """Read the arrays form written by :meth:`save`, its integrity record verified first
        (:func:`~.controller_integrity.verify_header`)."""
        head_path = Path(directory) / f"{name}.json"
        _, arrays, shape, meta = read_arrays_header(head_path, "product controller", PRODUCT_FORMAT, job_hash)
        try:
            with np.load(arrays, allow_pickle=False) as data:
                admissible = np.unpackbits(data["admissible"], axis=2, count=shape[2]).astype(bool)
                layer, domain = data["layer"], data["domain"].astype(bool)
        except (OSError, ValueError, KeyError, IndexError) as exc:
            raise ControllerIntegrityError(f"{arrays}: not readable as a product controller ({exc})") from None
        if admissible.shape != shape or layer.shape != shape[:2] or domain.shape != shape[1:2]:
            raise ControllerIntegrityError(f"{arrays}: arrays of shape {admissible.shape}, the header says {shape}")
        automaton, regions = _read_meta(meta, head_path)
        try:
            per_state = [ArrayController(admissible[q], layer[q], meta) for q in range(shape[0])]
            return cls(automaton, regions, per_state, domain, meta, layer.astype(np.int32))
        except (KeyError, TypeError, ValueError, CompabsError) as exc:
            raise ControllerIntegrityError(f"{head_path}: not a readable product controller ({type(exc).__name__}: "
                                           f"{exc})") from None

    @classmethod
    def from_roots(cls, model: SymbolicModel, roots: Sequence[Function], meta: Mapping[str, Any],
                   where: str | os.PathLike[str]) -> ProductController:
        """The BDD form from the roots of its (verified) symbolic dump: one per automaton state, the domain, then
        per automaton state ``meta["layer_bits"]`` digits of the layers (:func:`layer_digits`)."""
        automaton, regions = _read_meta(meta, where)
        n_q = automaton.n_states
        bits = meta.get("layer_bits")
        if bits is not None and (not isinstance(bits, int) or isinstance(bits, bool) or not 0 <= bits <= 64):
            raise ControllerIntegrityError(f"{where}: its layer_bits {bits!r} is not a count of digits")
        if len(roots) != n_q + 1 + n_q * (bits or 0):
            raise ControllerIntegrityError(f"{where}: {len(roots)} BDD files for an automaton of {n_q} states (one "
                                           f"per state, the domain and {bits or 0} layer digits per state)")
        try:
            per_state = [Controller(model, c, dict(meta)) for c in roots[:n_q]]
            digits = None if bits is None else [list(roots[n_q + 1 + q * bits:n_q + 1 + (q + 1) * bits])
                                                for q in range(n_q)]
            return cls(automaton, regions, per_state, roots[n_q], meta, digits=digits)
        except (KeyError, TypeError, ValueError, CompabsError) as exc:
            raise ControllerIntegrityError(f"{where}: not a readable product controller ({type(exc).__name__}: "
                                           f"{exc})") from None


def layer_digits(model: SymbolicModel, layers: Sequence[Sequence[Function]]) -> list[list[Function]]:
    """Per automaton state, the binary digits of its winning cells' layers: digit ``b`` holds on the cells whose
    layer has bit ``b`` set (``layers[q][k]``: the winning set after ``k`` iterations, nested). As many digits
    per state as the largest layer needs; the winning sets themselves say which cells have a layer."""
    width = max(len(per_q) for per_q in layers) - 1 if layers else 0
    bits = max(1, int(width).bit_length())
    false = model.bdd.false
    out = []
    with model.guard("writing the product controller's layers"):
        for per_q in layers:
            digits = [false] * bits
            for k in range(1, len(per_q)):  # the layers of one automaton state: as many as the game's iterations
                new = per_q[k] & ~per_q[k - 1]
                if new == false:
                    continue
                digits = [d | new if (k >> b) & 1 else d for b, d in enumerate(digits)]
            out.append(digits)
    return out


def _product_meta(meta: Mapping[str, Any], automaton: Automaton, regions: Sequence[Boxes]) -> dict[str, Any]:
    """``meta`` with the automaton and the atoms' closed boxes (what the controller reads at run time)."""
    return {**meta, "form": FORM, "automaton": automaton.to_json(),
            "regions": {atom: [[np.asarray(lb).tolist(), np.asarray(ub).tolist()] for lb, ub in boxes]
                        for atom, boxes in zip(automaton.atoms, regions)}}


def _read_meta(meta: Mapping[str, Any], where: str | os.PathLike[str]) -> tuple[Automaton, list[Boxes]]:
    """The automaton and the atoms' boxes a header's ``meta`` records (:func:`_product_meta`)."""
    try:
        automaton = Automaton.from_json(meta["automaton"])
        regions = [[(np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)) for lb, ub in meta["regions"][atom]]
                   for atom in automaton.atoms]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise ControllerIntegrityError(f"{where}: its automaton or regions cannot be read ({type(exc).__name__}: "
                                       f"{exc}); run the job again") from None
    return automaton, regions


def is_product_arrays(header_path: str | os.PathLike[str]) -> bool:
    """Whether a controller header (``NAME.json``) is a product controller's arrays form (its first bytes)."""
    with open(header_path, "rb") as f:
        head = f.read(4096)
    return PRODUCT_FORMAT.encode() in head
