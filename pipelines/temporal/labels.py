"""The letters a cell can carry: an atom holds on a cell only if it holds on all of it.

For each atom (a named region, closed boxes of the composed state) a cell is in one of three positions:

* ``1``: wholly inside the region (the inner approximation): the atom holds at every point of the cell;
* ``0``: disjoint from it (outside the outer approximation): the atom fails at every point;
* ``2``: on the region's edge: it holds at some points of the cell and fails at others.

A cell's *class* is its positions written in base 3 (atom ``i`` the digit of ``3^i``); its *letters* are the bit
vectors that agree with every ``0`` and ``1`` of its class, both values for a ``2``. A concrete state has one
letter (:meth:`Labelling.letters_at`), always among its cell's. The product game lets the environment choose
among a cell's letters (:mod:`pipelines.synthesis.product`), so a controller is correct whatever a state on an
edge reads, and tracks the automaton on the letters its states really carry (docs/guarantees.md).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pipelines.grid import UniformGrid
from pipelines.spec.model import Region
from pipelines.spec.regions import AbstractRegion, concrete_boxes

IndexBoxes = tuple[tuple[np.ndarray, np.ndarray], ...]


@dataclass(frozen=True)
class Labelling:
    """The atoms' regions on the composed state grid.

    Attributes
    ----------
    atoms : tuple of str
        In the automaton's bit order.
    concrete : tuple of list of (lb, ub)
        Per atom, its closed boxes of the composed state.
    inside, meets : tuple of AbstractRegion
        Per atom, the cells wholly inside its region, and the cells that meet it (either may have no box).
    """

    atoms: tuple[str, ...]
    concrete: tuple[list[tuple[np.ndarray, np.ndarray]], ...]
    inside: tuple[AbstractRegion, ...]
    meets: tuple[AbstractRegion, ...]

    @classmethod
    def of(cls, atoms: Sequence[str], regions: Mapping[str, Region], grid: UniformGrid,
           where: str = "specification.regions") -> Labelling:
        """The labelling of ``atoms`` by ``regions`` on ``grid``.

        Raises
        ------
        SpecError
            A region's box of the wrong dimension or with ``lb > ub`` (:func:`~pipelines.spec.regions.concrete_boxes`).
        """
        concrete, inside, meets = [], [], []
        shape = np.asarray(grid.shape)
        for atom in atoms:
            boxes = concrete_boxes(regions[atom], grid.dim, f"{where}.{atom}")
            concrete.append(boxes)
            inner, outer = [], []
            for lb, ub in boxes:
                lo, hi = grid.inner_range(lb, ub)
                if np.all(hi >= lo):
                    inner.append((lo.astype(np.int64), hi.astype(np.int64)))
                lo, hi = grid.cells_touching(lb[None, :], ub[None, :])
                lo, hi = np.maximum(lo[0], 0), np.minimum(hi[0], shape - 1)
                if np.all(hi >= lo):
                    outer.append((lo.astype(np.int64), hi.astype(np.int64)))
            inside.append(AbstractRegion(tuple(inner)))
            meets.append(AbstractRegion(tuple(outer)))
        return cls(tuple(atoms), tuple(concrete), tuple(inside), tuple(meets))

    @property
    def n_letters(self) -> int:
        return 2 ** len(self.atoms)

    def classes(self, idx: np.ndarray) -> np.ndarray:
        """The class of each cell of ``idx`` (composed cell indices, shape (B, n)); int64 (B,)."""
        out = np.zeros(idx.shape[0], dtype=np.int64)
        for i in range(len(self.atoms)):
            position = np.where(self.inside[i].contains(idx), 1, np.where(self.meets[i].contains(idx), 2, 0))
            out += position * 3**i
        return out

    def class_letters(self, classes: np.ndarray) -> np.ndarray:
        """Which letters each class admits: bool (len(classes), 2^atoms)."""
        letters = np.arange(self.n_letters, dtype=np.int64)
        out = np.ones((classes.size, self.n_letters), dtype=bool)
        for i in range(len(self.atoms)):
            position = (np.asarray(classes, dtype=np.int64) // 3**i) % 3
            bit = (letters >> i) & 1
            out &= (position[:, None] == 2) | (position[:, None] == bit[None, :])
        return out

    def letters_at(self, x: np.ndarray) -> np.ndarray:
        """The letter of each concrete state of ``x`` (shape (B, n)): bit ``i`` set iff the state lies in atom
        ``i``'s closed region; int64 (B,)."""
        return letters_at(self.concrete, x)


def letters_at(concrete: Sequence[Sequence[tuple[np.ndarray, np.ndarray]]], x: np.ndarray) -> np.ndarray:
    """:meth:`Labelling.letters_at` of the atoms' closed boxes ``concrete`` (also what a controller with memory
    keeps of its labelling, :class:`~pipelines.product_controller.ProductController`)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    out = np.zeros(x.shape[0], dtype=np.int64)
    for i, boxes in enumerate(concrete):
        hit = np.zeros(x.shape[0], dtype=bool)
        for lb, ub in boxes:
            hit |= np.all((x >= np.asarray(lb)) & (x <= np.asarray(ub)), axis=1)
        out |= hit.astype(np.int64) << i
    return out


def successor_states(delta: np.ndarray, class_letters: np.ndarray) -> np.ndarray:
    """``D[q, c, q']``: whether the automaton can move from ``q`` to ``q'`` on a letter of class ``c`` (bool,
    shape (n_states, n_classes, n_states)); ``delta`` is :attr:`~.automaton.Automaton.delta`."""
    n_q = delta.shape[0]
    out = np.zeros((n_q, class_letters.shape[0], n_q), dtype=bool)
    for q in range(n_q):  # states: a handful; the letters and classes are bulk
        target = np.broadcast_to(delta[q][None, :], class_letters.shape)
        c, letter = np.nonzero(class_letters)
        out[q, c, target[c, letter]] = True
    return out
