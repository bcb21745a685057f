"""What every form of controller shares: the grids it is over and the quantizer that refines it (Theorem 4.2).

A controller ``C(x̂) ⊆ Û`` answers at a concrete state through the feedback refinement relation: the state is
related to its cell (:func:`~pipelines.grid.quantize`), and the cell's inputs are grid points of the input grids.
:class:`GridController` holds the state grid and the input grids (read from their descriptions, as every
controller file and export records them) and answers ``cell`` / ``cells``; the BDD controller
(:class:`~pipelines.controller.Controller`), the array controller (:class:`~pipelines.array_controller.ArrayController`)
and the exported one (:class:`~pipelines.export.table.ExportedController`) add how they store ``C``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from pipelines.grid import UniformGrid, quantize


class GridController:
    """The grids of a controller and its quantizer (module docstring).

    Parameters
    ----------
    grids : mapping
        ``state_grid`` (the composed state grid) and ``input_grids`` (one per subsystem, in order) as grid
        descriptions (:meth:`~pipelines.grid.UniformGrid.describe`).
    meta : mapping
        What the controller's file records about it (kind, spec, ...); :attr:`meta` gives a copy.
    """

    def __init__(self, grids: Mapping[str, Any], meta: Mapping[str, Any]) -> None:
        self._meta = dict(meta)
        self._state_grid = UniformGrid.from_description(grids["state_grid"])
        self._input_grids = [UniformGrid.from_description(g) for g in grids["input_grids"]]

    @property
    def meta(self) -> dict[str, Any]:
        return dict(self._meta)

    @property
    def state_grid(self) -> UniformGrid:
        return self._state_grid

    @property
    def input_grids(self) -> list[UniformGrid]:
        return list(self._input_grids)

    @property
    def input_dim(self) -> int:
        """Components of a joint concrete input (all subsystems')."""
        return sum(g.dim for g in self._input_grids)

    def cells(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices of concrete states, shape (B, n) -> (B, n), and whether each is in the box, shape (B,)
        (indices of the others are meaningless).

        A state on a cell boundary gets the upper cell, per coordinate the lower one where the upper is off the
        grid, so a state on the upper edge of the box has a cell (:func:`~pipelines.grid.quantize`, which the C
        export reproduces)."""
        return quantize(self._state_grid, X)

    def cell(self, x: np.ndarray) -> np.ndarray | None:
        """The cell indices of a concrete state, shape (n,), or ``None`` off the grid or outside the box."""
        idx, ok = self.cells(np.asarray(x, dtype=float).reshape(1, -1))
        return idx[0] if ok[0] else None
