"""Controllers as files, and their refinement to the concrete system (Theorem 4.2).

A controller is a BDD over current-state and input bits, written in DDDMP with a JSON header (variable order,
bit widths, the grids, the spec). :func:`load_controller` reads one without the job store; its
:meth:`Controller.inputs` quantizes a concrete state and returns the admissible concrete inputs there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import CompabsError
from .grid import UniformGrid

CONTROLLER_FILE = "controller"


class Controller:
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
        self._model = model
        self._bdd = bdd
        self._meta = dict(meta)
        self._state_grid = UniformGrid.from_description(meta["state_grid"])
        self._input_grids = [UniformGrid.from_description(g) for g in meta["input_grids"]]
        self._domain = model.bdd.exist(model.u_bits, bdd)

    @property
    def meta(self) -> dict:
        return dict(self._meta)

    @property
    def input_dim(self) -> int:
        return sum(g.dim for g in self._input_grids)

    @property
    def state_grid(self) -> UniformGrid:
        return self._state_grid

    def cell(self, x: np.ndarray) -> np.ndarray | None:
        """The cell indices of a concrete state, shape (n,), or ``None`` off the grid or outside the box."""
        x = np.asarray(x, dtype=float).reshape(1, -1)
        if x.shape[1] != self._state_grid.dim:
            raise CompabsError(f"a state has {self._state_grid.dim} components, got {x.shape[1]}")
        if np.any(x < np.asarray(self._state_grid.lb)) or np.any(x > np.asarray(self._state_grid.ub)):
            return None
        idx, inside = self._state_grid.cell_of(x)
        return idx[0] if inside[0] else None

    def input_indices(self, idx: np.ndarray) -> np.ndarray:
        """Per-subsystem flat input indices allowed at a cell, shape (k, N)."""
        return self._model.inputs_at(self._bdd, [int(v) for v in idx])

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
        """Whether composed cells, shape (B, n), are in the controller's domain; bool (B,)."""
        m = self._model
        out = np.zeros(idx.shape[0], dtype=bool)
        for r, row in enumerate(np.asarray(idx)):
            out[r] = m.bdd.let(m.state_assignment(row), self._domain) == m.bdd.true
        return out

    def sample_cells(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Cells drawn uniformly from the controller's domain, shape (count, n) (empty if the domain is).

        Bits are fixed one at a time, each with the probability of its share of the remaining domain (CUDD's
        floating-point count is enough for probabilities), so a domain of 1e-5 of the state space costs no
        more than a large one, where rejection sampling would fail.
        """
        m = self._model
        bdd = m.bdd
        n = self._state_grid.dim
        bits = list(m.x_bits)
        if self._domain == bdd.false:
            return np.zeros((0, n), dtype=np.int64)
        rows = []
        for _ in range(count):
            f = self._domain
            assign: dict[str, bool] = {}
            for k, b in enumerate(bits):
                rest = len(bits) - k - 1
                f1 = bdd.let({b: True}, f)
                f0 = bdd.let({b: False}, f)
                c1 = bdd.count(f1, nvars=rest) if f1 != bdd.false else 0.0
                c0 = bdd.count(f0, nvars=rest) if f0 != bdd.false else 0.0
                value = bool(rng.random() * (c0 + c1) < c1)
                assign[b] = value
                f = f1 if value else f0
            rows.append([sum(int(assign[b]) << (len(m.bits[f"x{i}"]) - 1 - j) for j, b in enumerate(m.bits[f"x{i}"]))
                         for i in range(n)])
        return np.array(rows, dtype=np.int64)

    def save(self, directory: str | Path, name: str = CONTROLLER_FILE) -> tuple[Path, Path]:
        return self._model.dump(Path(directory) / name, self._bdd, self._meta)


def load_controller(directory: str | Path, name: str = CONTROLLER_FILE) -> Controller:
    """Load a controller written by ``compabs run`` (``DIR/controller.dddmp`` and ``DIR/controller.json``)."""
    from .symbolic import SymbolicModel

    base = Path(directory) / name
    if not base.with_name(base.name + ".json").exists():
        raise CompabsError(f"no controller in {directory} (expected {base.name}.json and {base.name}.dddmp)")
    model, bdd, meta = SymbolicModel.load(base)
    return Controller(model, bdd, meta)
