"""Controllers as arrays: the controllers of explicit games (:mod:`.synthesis.explicit`), refined by the feedback
refinement relation (Theorem 4.2).

An :class:`ArrayController` holds, per cell of the state grid, whether it is in the domain, the admissible inputs
as a boolean row over the input grid's flat indices, and for progress controllers the layer (the iteration at
which the cell entered the attractor). It answers every query of :class:`~.controller.Controller` (``inputs``,
``choose``, ``in_domain``, ``sample_cells``, ...) with array indexing, for many states at once. ``compabs export``
turns it into the same controller as a BDD (:func:`~.export.emit.as_bdd`) and determinizes that.

On disk (docs/storage.md): ``NAME.json``, the header (``format`` :data:`ARRAY_FORMAT`, the grids, the job's
meta, its integrity record: the SHA-256 of the arrays' file and the job's spec hash,
:mod:`.controller_integrity`), and ``NAME.npz``, the arrays (``admissible`` bit-packed, ``layer``), read without
pickles. A file whose checksum, spec hash or shapes disagree with its header is refused.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.controller_integrity import (
    ControllerIntegrityError,
    read_arrays_header,
    seal,
)
from pipelines.errors import CompabsError
from pipelines.grid_controller import GridController

#: ``format`` of an array controller's header.
ARRAY_FORMAT = "compabs-array-controller/1"


class ArrayController(GridController):
    """A controller ``C(x̂) ⊆ Û`` of a single system stored as arrays (module docstring).

    Parameters
    ----------
    admissible : ndarray of bool, shape (n_x, n_u)
        Inputs allowed at each flat cell of ``state_grid`` (a row of ``False`` outside the domain).
    layer : ndarray of int, shape (n_x,), or None
        A progress controller's layers (``-1`` outside the domain).
    meta : dict
        ``state_grid`` and ``input_grids`` (one grid: a single system) as grid descriptions, ``kind``, and what
        the job recorded.
    """

    def __init__(self, admissible: np.ndarray, layer: np.ndarray | None, meta: dict[str, Any]) -> None:
        super().__init__(meta, {**meta, "form": "array"})
        if len(self._input_grids) != 1:
            raise CompabsError(f"an array controller has one input grid, got {len(self._input_grids)}")
        admissible = np.asarray(admissible, dtype=bool)
        shape = (self._state_grid.size, self._input_grids[0].size)
        if admissible.shape != shape:
            raise CompabsError(f"an array controller's inputs have shape {admissible.shape}, expected {shape}")
        self._admissible = admissible
        self._domain: np.ndarray = np.asarray(admissible.any(axis=1))
        self._layer = None if layer is None else np.asarray(layer, dtype=np.int32).reshape(-1)
        if self._layer is not None and (self._layer.size != shape[0] or
                                        not np.array_equal(self._layer >= 0, self._domain)):
            raise CompabsError("an array controller's layers do not match its domain")

    # ------------------------------------------------------------------ what the controller is
    @property
    def admissible(self) -> np.ndarray:
        """The inputs allowed at each flat cell, shape (n_x, n_u) (read-only view)."""
        view = self._admissible.view()
        view.flags.writeable = False
        return view

    @property
    def domain_mask(self) -> np.ndarray:
        """Whether each flat cell is in the domain, shape (n_x,)."""
        return self._domain.copy()

    @property
    def layers(self) -> np.ndarray | None:
        """Per flat cell, the layer of a progress controller (``-1`` outside the domain), else ``None``."""
        return None if self._layer is None else self._layer.copy()

    @property
    def nodes(self) -> int:
        """Bytes of the arrays (an array controller has no BDD nodes; reports compare sizes by this)."""
        return int(self._admissible.size // 8 + (0 if self._layer is None else self._layer.nbytes))

    # ------------------------------------------------------------------ queries
    def _flat(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, self._state_grid.dim)
        ok = self._state_grid.on_grid(idx)
        flat = np.zeros(idx.shape[0], dtype=np.int64)
        flat[ok] = self._state_grid.ravel(idx[ok])
        return flat, ok

    def in_domain(self, idx: np.ndarray) -> np.ndarray:
        """Whether composed cells, shape (B, n), are in the domain; bool (B,) (off the grid: not)."""
        flat, ok = self._flat(idx)
        return ok & self._domain[flat]

    def layer_of(self, idx: np.ndarray) -> int | None:
        """The cell's layer (progress controllers; ``0`` for any domain cell otherwise), ``None`` outside."""
        flat, ok = self._flat(idx)
        if not ok[0] or not self._domain[flat[0]]:
            return None
        return 0 if self._layer is None else int(self._layer[flat[0]])

    def input_indices(self, idx: np.ndarray) -> np.ndarray:
        """Flat input indices allowed at a cell, shape (k, 1)."""
        flat, ok = self._flat(idx)
        if not ok[0]:
            return np.zeros((0, 1), dtype=np.int64)
        return np.flatnonzero(self._admissible[flat[0]]).reshape(-1, 1)

    def inputs(self, x: np.ndarray) -> np.ndarray:
        """Admissible concrete inputs at the concrete state ``x``, shape (k, m); (0, m) outside the domain."""
        idx = self.cell(x)
        if idx is None:
            return np.zeros((0, self.input_dim))
        g = self._input_grids[0]
        return g.points(g.unravel(self.input_indices(idx)[:, 0]))

    def choose_many(self, X: np.ndarray, rng: np.random.Generator, how: str = "random") -> list[np.ndarray | None]:
        """One admissible concrete input per row of ``X``, shape (B, n): uniform over the admissible inputs
        (``"random"``) or the smallest input index (``"first"``); ``None`` outside the domain. All rows at once."""
        idx, ok = self.cells(X)
        flat, on = self._flat(idx)
        ok &= on
        ok[ok] = self._domain[flat[ok]]
        rows = self._admissible[flat[ok]]
        if how == "random":
            k = rows.sum(axis=1)
            pick = np.floor(rng.random(k.size) * k).astype(np.int64)
            code = np.argmax(np.cumsum(rows, axis=1) > pick[:, None], axis=1)
        else:
            code = np.argmax(rows, axis=1)
        g = self._input_grids[0]
        points = g.points(g.unravel(code))
        out: list[np.ndarray | None] = [None] * len(ok)
        for j, r in enumerate(np.flatnonzero(ok)):
            out[r] = points[j]
        return out

    def choose(self, x: np.ndarray, rng: np.random.Generator, how: str = "random") -> np.ndarray | None:
        return self.choose_many(np.asarray(x, dtype=float).reshape(1, -1), rng, how)[0]

    def sample_cells(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Cells drawn uniformly (with replacement) from the domain, shape (count, n); empty if the domain is."""
        cells = np.flatnonzero(self._domain)
        if cells.size == 0 or count <= 0:
            return np.zeros((0, self._state_grid.dim), dtype=np.int64)
        return self._state_grid.unravel(cells[rng.integers(cells.size, size=count)])

    def plane_mask(self, base: np.ndarray, i: int, j: int) -> np.ndarray:
        """The domain on the plane of coordinates ``(i, j)`` through cell ``base``, shape (shape[i], shape[j])
        (:func:`~.figures.domain.plane_mask` of a BDD controller)."""
        shape = self._state_grid.shape
        at: list[Any] = [int(v) for v in np.asarray(base).reshape(-1)]
        at[i], at[j] = slice(None), slice(None)
        plane = self._domain.reshape(shape)[tuple(at)]
        return plane if i < j else plane.T

    # ------------------------------------------------------------------ files
    def save(self, directory: str | os.PathLike[str], name: str) -> tuple[Path, ...]:
        """Write ``NAME.npz`` and its header ``NAME.json`` (with its integrity record,
        :func:`~.controller_integrity.seal`); returns the paths (arrays first)."""
        base = Path(directory) / name
        arrays, head = base.with_name(base.name + ".npz"), base.with_name(base.name + ".json")
        parts: dict[str, np.ndarray] = {"admissible": np.packbits(self._admissible, axis=1)}
        if self._layer is not None:
            parts["layer"] = self._layer
        with open(arrays, "wb") as f:
            np.savez_compressed(f, **parts)  # type: ignore[arg-type]
        header = {
            "format": ARRAY_FORMAT,
            "meta": self._meta,
            "roots": [arrays.name],
            "shape": list(self._admissible.shape),
            "layered": self._layer is not None,
        }
        head.write_text(json.dumps(seal(header, head.parent, [arrays.name]), indent=1))
        return arrays, head

    @classmethod
    def load(cls, directory: str | os.PathLike[str], name: str, job_hash: str | None = None) -> ArrayController:
        """Read a controller written by :meth:`save`, its header's integrity record verified first (with
        ``job_hash``, the job's spec hash too: :func:`~.controller_integrity.verify_header`)."""
        base = Path(directory) / name
        head_path = base.with_name(base.name + ".json")
        header, arrays, shape, meta = read_arrays_header(head_path, "array controller", ARRAY_FORMAT, job_hash)
        try:
            with np.load(arrays, allow_pickle=False) as data:
                admissible = np.unpackbits(data["admissible"], axis=1, count=shape[1]).astype(bool)
                layer = data["layer"] if header.get("layered") else None
        except (OSError, ValueError, KeyError, IndexError) as exc:
            raise ControllerIntegrityError(f"{arrays}: not readable as an array controller ({exc})") from None
        if admissible.shape != shape:
            raise ControllerIntegrityError(f"{arrays}: arrays of shape {admissible.shape}, the header says {shape}")
        try:
            return cls(admissible, layer, meta)
        except (KeyError, TypeError, ValueError, CompabsError) as exc:
            raise ControllerIntegrityError(f"{head_path}: not a readable array controller header "
                                           f"({type(exc).__name__}: {exc})") from None


def is_array_controller(header_path: str | os.PathLike[str]) -> bool:
    """Whether a controller header (``NAME.json``) is an array controller's (its first bytes are enough)."""
    with open(header_path, "rb") as f:
        head = f.read(4096)
    return ARRAY_FORMAT.encode() in head
