"""What every figure of a job states, gathered once: the spec's kind and regions, the names of the coordinates
and inputs, the initial state and whether it is in the controller's domain.

Regions are drawn as the spec gives them (concrete boxes), not as their cell approximations: a reader checks
the figure against the spec, and the domain drawn cell by cell beside them shows what the abstraction made of
them (targets and safe sets from inside, obstacles from outside, docs/method.md §1).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipelines.grid import UniformGrid
from pipelines.network import Network
from pipelines.spec.model import Region

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from matplotlib.figure import Figure

#: A concrete box over the composed state: ``(lb, ub)``, each shape (n,).
Box = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class Consensus:
    """A consensus region ``OR_k AND_i |x_i - phi_k| <= radius``, ``phi_k = first + k * step``, ``k < count``
    (the centres :func:`pipelines.spec.regions.abstract_region` abstracts)."""

    first: float
    step: float
    count: int
    radius: float

    def centres(self, states: np.ndarray) -> np.ndarray:
        """Per state, shape (B, n), a centre ``phi`` whose box ``[phi - r, phi + r]^n`` holds it (the one nearest
        the middle of its coordinates' range), NaN where none does; shape (B,)."""
        X = np.atleast_2d(np.asarray(states, dtype=float))
        lo, hi = X.max(axis=1) - self.radius, X.min(axis=1) + self.radius  # phi must lie in [lo, hi]
        tol = 1e-9 * max(1.0, abs(self.first) + abs(self.step) * self.count)
        with np.errstate(invalid="ignore"):
            k_lo = np.maximum(np.ceil((lo - self.first - tol) / self.step), 0)
            k_hi = np.minimum(np.floor((hi - self.first + tol) / self.step), self.count - 1)
            mid = np.rint(((lo + hi) / 2 - self.first) / self.step)
        k = np.clip(mid, k_lo, k_hi)
        phi = self.first + k * self.step
        ok = (k_lo <= k_hi) & np.all(np.abs(X - phi[:, None]) <= self.radius + tol, axis=1)
        return np.where(ok, phi, np.nan)

    def describe(self) -> str:
        last = self.first + (self.count - 1) * self.step
        centres = f"{self.first:g}, {self.first + self.step:g}, ..., {last:g}"
        return f"|x_i - phi| <= {self.radius:g} for every i, phi = {centres}"

#: Most boxes one region may have to be drawn (a consensus region of many centres is described, not drawn).
MAX_DRAWN_BOXES = 500

#: The regions figures draw, in legend order.
REGION_NAMES = ("target", "safe", "avoid")

#: How the figures' closed-loop runs choose among the admissible inputs (:meth:`Controller.choose`).
CHOICES = {"first": "the first admissible input at each step (deterministic)",
           "steady": "the previous input while it stays admissible, else the first admissible one (deterministic)",
           "random": "an admissible input drawn at random at each step"}


def concrete_boxes(region: Region, n: int) -> tuple[list[Box], str | None]:
    """The boxes of a spec region over a composed state of dimension ``n`` (scalars broadcast, a consensus
    region as its boxes ``[phi - r, phi + r]^n``).

    Returns
    -------
    boxes : list of (lb, ub)
    note : str or None
        Why some boxes are not returned (a consensus region of more than :data:`MAX_DRAWN_BOXES` centres).
    """
    boxes: list[Box] = []
    for b in region.boxes:
        lb = np.broadcast_to(np.atleast_1d(np.asarray(b.lb, dtype=float)), (n,)).copy()
        ub = np.broadcast_to(np.atleast_1d(np.asarray(b.ub, dtype=float)), (n,)).copy()
        boxes.append((lb, ub))
    note = None
    if region.consensus is not None:
        c = consensus_of(region)
        if c.count > MAX_DRAWN_BOXES:
            note = f"consensus region of {c.count} boxes |x_i - phi| <= {c.radius:g}: not drawn"
        else:
            phi = c.first + c.step * np.arange(c.count)
            boxes += [(np.full(n, p - c.radius), np.full(n, p + c.radius)) for p in phi]
    return boxes, note


def consensus_of(region: Region) -> Consensus:
    """The :class:`Consensus` of a region with a ``consensus`` part."""
    assert region.consensus is not None
    first, last, step = region.consensus.centers
    # The count of pipelines.spec.regions.abstract_region, so the drawn boxes are the abstracted ones.
    count = int(math.floor((last - first) / step * (1 + 1e-12))) + 1
    return Consensus(float(first), float(step), count, float(region.consensus.radius))


def _names(network: Network) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``x3 (tank3)`` per state coordinate and ``u1 (tank1)`` per input, numbered over the composed system."""
    states, inputs = [], []
    col = 0
    for s in network.subsystems:
        for k in range(s.n):
            g = s.state_offset + k
            states.append(f"x{g + 1} ({s.name})" if s.n == 1 else f"x{g + 1} ({s.name}, x{k + 1})")
        for k in range(s.m):
            inputs.append(f"u{col + 1} ({s.name})" if s.m == 1 else f"u{col + 1} ({s.name}, u{k + 1})")
            col += 1
    return tuple(states), tuple(inputs)


def vector(x: Sequence[float] | np.ndarray, most: int = 10) -> str:
    """A state as ``[1.5, 2, 65]`` (4 significant digits), the middle elided beyond ``most`` components."""
    v = [f"{float(c):.4g}" for c in np.asarray(x, dtype=float).ravel()]
    if len(v) > most:
        v = [*v[: most // 2], "...", *v[-(most // 2):]]
    return "[" + ", ".join(v) + "]"


_NUMBER_LIST = re.compile(r"\[(?:\s*-?[0-9.eE+-]+(?:inf|nan)?\s*,)*\s*-?[0-9.eE+-]+\s*\]")


def short_message(text: str) -> str:
    """A run's violation message with its states written as :func:`vector` does (4 digits, long ones elided)."""

    def shorten(m: re.Match[str]) -> str:
        try:
            return vector([float(v) for v in m.group()[1:-1].split(",")])
        except ValueError:
            return m.group()

    return _NUMBER_LIST.sub(shorten, text)


@dataclass(frozen=True)
class FigureSetting:
    """What the figures of one job say about it.

    Attributes
    ----------
    name, kind : str
        The spec's name and specification kind (``safe``, ``reach``, ``reach_avoid``, ``reach_and_stay``).
    grid : UniformGrid
        The composed state grid (cells are ``point ± eta/2``).
    state_names, input_names : tuple of str
        ``x1 (subsystem)`` per state coordinate, ``u1 (subsystem)`` per input of the composed system.
    regions : dict of str to list of Box
        The spec's ``target``, ``safe`` and ``avoid`` regions as concrete boxes (those it has).
    bands : dict of str to list of Box
        The boxes the spec lists for each region (without a consensus region's): what the time plot draws as
        each coordinate's band.
    consensus : dict of str to Consensus
        The consensus part of each region that has one: the time plot draws, at each step, the box of it that
        holds the state.
    notes : list of str
        What is not drawn, and why.
    x0 : ndarray or None
        The spec's first initial state (``options.initial_states``), if any.
    x0_in_domain : bool or None
        Whether its cell is in the controller's domain.
    choice : str
        How the drawn runs choose their inputs (a key of :data:`CHOICES`).
    atoms : dict of str to list of Box
        An ``ltl`` spec's named regions (its formula's atoms) as concrete boxes.
    formula : str or None
        An ``ltl`` spec's formula.
    """

    name: str
    kind: str
    grid: UniformGrid
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    regions: dict[str, list[Box]]
    bands: dict[str, list[Box]] = field(default_factory=dict)
    consensus: dict[str, Consensus] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    x0: np.ndarray | None = None
    x0_in_domain: bool | None = None
    choice: str = "first"
    atoms: dict[str, list[Box]] = field(default_factory=dict)
    formula: str | None = None

    def initial_state_line(self) -> str:
        """The caption line every figure carries: the spec kind, the initial state and whether it is in the domain."""
        head = f"{self.name}: {self.kind.replace('_', '-')} specification"
        if self.x0 is None:
            return f"{head}; no initial state in the spec (runs from random states of the domain)"
        where = "in" if self.x0_in_domain else "NOT in"
        return f"{head}; initial state x0 = {vector(self.x0)} is {where} the controller's domain"


def figure_setting(network: Network, initial_states: Sequence[dict], choice: str = "first") -> FigureSetting:
    """The :class:`FigureSetting` of a job.

    Parameters
    ----------
    network : Network
        Its ``spec`` gives the name, kind and regions.
    initial_states : sequence of dict
        Per initial state of the spec, ``x0`` and ``in_domain`` (:attr:`ClosedLoop.initial_states`).
    choice : str
        How the drawn runs choose their inputs (a key of :data:`CHOICES`).
    """
    spec = network.spec
    n = network.state_dim
    regions: dict[str, list[Box]] = {}
    bands: dict[str, list[Box]] = {}
    consensus: dict[str, Consensus] = {}
    notes: list[str] = []
    for key in REGION_NAMES:
        region = getattr(spec.specification, key)
        if region is not None:
            boxes, note = concrete_boxes(region, n)
            regions[key] = boxes
            bands[key] = boxes[: len(region.boxes)]  # concrete_boxes lists the spec's own boxes first
            if region.consensus is not None:
                consensus[key] = consensus_of(region)
            if note:
                notes.append(f"{key}: {note}")
    atoms = {name: concrete_boxes(region, n)[0] for name, region in (spec.specification.regions or {}).items()}
    states, inputs = _names(network)
    first = initial_states[0] if initial_states else None
    return FigureSetting(
        name=spec.name, kind=spec.specification.kind, grid=network.composed_state_grid(), state_names=states,
        input_names=inputs, regions=regions, bands=bands, consensus=consensus, notes=notes,
        x0=None if first is None else np.asarray(first["x0"], dtype=float),
        x0_in_domain=None if first is None else bool(first["in_domain"]), choice=choice, atoms=atoms,
        formula=spec.specification.formula,
    )


def save_figure(fig: Figure, path: str | os.PathLike[str], dpi: int = 110) -> Path:
    """Write ``fig`` as PNG; the bounding box is tight, so legends and captions outside the axes are kept."""
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    return Path(path)
