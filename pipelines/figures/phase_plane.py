"""The phase plane of two state coordinates: the winning domain cell by cell, the spec's regions as boxes, and
closed-loop runs on top.

Cells are drawn with their true extent, ``point ± eta/2`` from the grid's points (an image whose pixels are
the cells), so a run that touches an obstacle's cell is seen to touch it. With more than two coordinates the
domain is the slice through one cell (that of the initial state) in the others, said in the title: a
projection would need an existential over every other coordinate, which the controller answers only cell by
cell. The slice passes through the cell of the initial state when it is in the domain, else through the start
of the first run drawn (a domain state), so that the slice meets the domain. An initial state outside the domain
is marked where it lies on the slice; one off the slice is not drawn, and the title says so.

The domain is read off the domain BDD in one pass where the caller gives ``plane`` (:func:`.domain.plane_mask`),
else asked cell by cell. A plane with more than :data:`MAX_IMAGE_SIDE` cells along a side is drawn in blocks of
cells (:func:`.domain.block_levels`): a block is drawn as domain only where every cell of it is, and in a fainter
colour where only some are.
"""

from __future__ import annotations

import textwrap
from collections.abc import Callable, Sequence

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle

from pipelines.errors import SpecError
from pipelines.figures.automaton_plot import draw_atoms
from pipelines.figures.domain import MAX_PLANE_CELLS, block_factors, block_levels
from pipelines.figures.setting import CHOICES, REGION_NAMES, FigureSetting, vector
from pipelines.grid import UniformGrid
from pipelines.verification.closed_loop import Run

#: Most cells of a slice the domain is drawn for when it is asked cell by cell (no ``plane``); with ``plane``, up
#: to :data:`~.domain.MAX_PLANE_CELLS`.
MAX_SLICE_CELLS = 250_000
#: Most cells along a side drawn one pixel per cell; beyond, blocks of cells (about as many as the axes' pixels).
MAX_IMAGE_SIDE = 400

DOMAIN_COLOR = "#c6dbef"
#: Blocks of cells of which some, not all, are in the domain (drawn only for a plane drawn in blocks).
PARTLY_COLOR = "#dadaeb"
REGION_STYLE: dict[str, dict] = {
    "target": {"facecolor": (0.17, 0.63, 0.17, 0.22), "edgecolor": "darkgreen", "linewidth": 1.8, "label": "target"},
    "safe": {"fill": False, "edgecolor": "navy", "linestyle": "--", "linewidth": 1.8, "label": "safe set"},
    "avoid": {"facecolor": (0.84, 0.15, 0.16, 0.25), "edgecolor": "darkred", "hatch": "///", "linewidth": 1.2,
              "label": "obstacle (avoid)"},
}


def check_axes(axes: Sequence[int], n: int) -> tuple[int, int]:
    """Two distinct state coordinates of an ``n``-dimensional system (0-based).

    Raises
    ------
    SpecError
        Naming the coordinates there are.
    """
    if n < 2:
        raise SpecError(f"a phase plane needs two state coordinates; this system has {n}")
    if len(axes) != 2:
        raise SpecError(f"axes {list(axes)}: give two state coordinates, e.g. 0,1")
    i, j = (int(a) for a in axes)
    if not (0 <= i < n and 0 <= j < n) or i == j:
        raise SpecError(f"axes {i},{j}: give two different state coordinates from 0 to {n - 1} (0 is x1)")
    return i, j


def cell_edges(grid: UniformGrid, axis: int) -> np.ndarray:
    """The boundaries of the cells along ``axis``, shape (shape[axis] + 1,): ``point ± eta/2``."""
    p = grid.axis_points(axis)
    return np.append(p - grid.eta[axis] / 2, p[-1] + grid.eta[axis] / 2)


def base_cell(grid: UniformGrid, x0: np.ndarray | None, runs: Sequence[tuple[str, np.ndarray, Run]] = (),
              x0_in_domain: bool | None = True) -> tuple[np.ndarray, str]:
    """The cell a slice passes through, and how the caption says it: that of ``x0`` when it is on the grid and in
    the controller's domain; else that where the first drawn run starts (a state of the domain, so the slice meets
    it); else that of ``x0`` when it is on the grid; else the grid's middle cell."""

    def cell(x: np.ndarray) -> np.ndarray | None:
        idx, inside = grid.cell_of(np.asarray(x, dtype=float)[None, :])
        return idx[0] if inside[0] else None

    at_x0 = None if x0 is None else cell(x0)
    if at_x0 is not None and x0_in_domain:
        return at_x0, "the cell of x0"
    why = ("no initial state in the spec" if x0 is None
           else "x0 is not in the domain" if at_x0 is not None else "x0 is off the grid")
    for _, start, _ in runs:
        at = cell(start)
        if at is not None:
            return at, f"the cell where the first drawn run starts, {vector(start)} ({why})"
    if at_x0 is not None:
        return at_x0, "the cell of x0"
    return np.asarray(grid.shape) // 2, f"the grid's middle cell ({why})"


def slice_mask(in_domain: Callable[[np.ndarray], np.ndarray], grid: UniformGrid, i: int, j: int,
               base: np.ndarray) -> np.ndarray:
    """Whether each cell of the slice through ``base`` on coordinates ``(i, j)`` is in the domain,
    shape (shape[i], shape[j])."""
    ki, kj = grid.shape[i], grid.shape[j]
    idx = np.repeat(np.asarray(base, dtype=np.int64)[None, :], ki * kj, axis=0)
    ii, jj = np.meshgrid(np.arange(ki), np.arange(kj), indexing="ij")
    idx[:, i] = ii.ravel()
    idx[:, j] = jj.ravel()
    return np.asarray(in_domain(idx), dtype=bool).reshape(ki, kj)


def _meets_slice(lb: np.ndarray, ub: np.ndarray, grid: UniformGrid, base: np.ndarray, i: int, j: int) -> bool:
    """Whether a box meets the slice's cell in every coordinate but ``i`` and ``j``."""
    others = np.array([k for k in range(grid.dim) if k not in (i, j)], dtype=np.int64)
    if others.size == 0:
        return True
    c = grid.points(base[None, :])[0][others]
    half = grid.eta_array[others] / 2
    return bool(np.all((lb[others] <= c + half) & (ub[others] >= c - half)))


def phase_plane(
    setting: FigureSetting,
    in_domain: Callable[[np.ndarray], np.ndarray] | None,
    runs: Sequence[tuple[str, np.ndarray, Run]],
    *,
    axes: Sequence[int] = (0, 1),
    plane: Callable[[np.ndarray, int, int], np.ndarray] | None = None,
) -> Figure:
    """The phase plane of two state coordinates.

    Parameters
    ----------
    setting : FigureSetting
    in_domain : callable or None
        Composed cell indices, shape (B, n), to bool (B,) (:meth:`Controller.in_domain`); ``None``: no domain.
    runs : sequence of (origin, x0, Run)
        Closed-loop runs to draw; ``origin`` is ``"initial"`` (a spec's initial state) or ``"random"``.
    axes : (int, int)
        The coordinates, 0-based.
    plane : callable, optional
        ``plane(base, i, j)``: the domain on the plane of ``(i, j)`` through cell ``base`` in one call, shape
        (shape[i], shape[j]) (:func:`.domain.plane_mask` of the controller); used instead of ``in_domain``.

    Returns
    -------
    Figure
        Artists carry ``gid``s: ``domain`` (the image of the domain, one pixel per cell, or per block of cells:
        then its values are those of :func:`.domain.block_levels`), ``target:k``, ``safe:k``, ``avoid:k`` (the
        boxes), ``atom:NAME:k`` and ``atom_label:NAME:k`` (an ``ltl`` spec's regions, named), ``state_set``, ``run:r``, ``start:r`` and ``end:r``.
    """
    grid = setting.grid
    i, j = check_axes(axes, grid.dim)
    ei, ej = cell_edges(grid, i), cell_edges(grid, j)
    window = (ei[0], ei[-1], ej[0], ej[-1])
    fig = Figure(figsize=(7.8, 6.0))
    ax = fig.subplots()
    base, where = base_cell(grid, setting.x0, runs, setting.x0_in_domain)
    sliced = grid.dim > 2
    scope = f"slice through {where}, the other coordinates at its centre" if sliced else "whole state space"
    handles, domain_lines = _draw_domain(ax, grid, in_domain, plane, base, (i, j), window, scope)
    lines = [setting.initial_state_line(), *domain_lines]
    region_handles, region_lines = _draw_regions(ax, setting, base, (i, j), window)
    handles += region_handles
    lines += region_lines + setting.notes
    handles += _draw_runs(ax, runs, i, j)
    if setting.x0 is not None and not setting.x0_in_domain:
        x0_handles, x0_lines = _mark_x0_outside(ax, setting, base, (i, j))
        handles += x0_handles
        lines += x0_lines
    n_init = sum(1 for origin, _, _ in runs if origin == "initial")
    from_x0 = f"{n_init} from x0, " if setting.x0 is not None else ""
    projected = ", projected on this plane" if sliced else ""
    lines.append(f"runs: {from_x0}{len(runs) - n_init} from random domain states{projected}; "
                 f"inputs: {CHOICES.get(setting.choice, setting.choice)}")

    ax.set_xlim(window[0], window[1])
    ax.set_ylim(window[2], window[3])
    ri, rj = window[1] - window[0], window[3] - window[2]
    if max(ri, rj) <= 3 * min(ri, rj):  # comparable ranges: distances read the same on both axes
        ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(setting.state_names[i])
    ax.set_ylabel(setting.state_names[j])
    ax.set_title("\n".join(textwrap.fill(t, 95) for t in lines), fontsize=8, loc="left")
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)
    return fig


#: The window of a phase plane: ``(x_min, x_max, y_min, y_max)``, the outer edges of the grid's cells.
Window = tuple[float, float, float, float]


def _draw_domain(ax, grid: UniformGrid, in_domain: Callable[[np.ndarray], np.ndarray] | None,
                 plane: Callable[[np.ndarray, int, int], np.ndarray] | None, base: np.ndarray,
                 axes: tuple[int, int], window: Window, scope: str) -> tuple[list, list[str]]:
    """The winning domain on the plane of ``axes`` through cell ``base`` as an image (``gid="domain"``), one
    pixel per cell or, beyond :data:`MAX_IMAGE_SIDE` cells along a side, per block of cells; or the reason it is
    not drawn. ``scope`` says what the plane is (the whole state space or a slice).

    Returns
    -------
    handles : list
        The domain's legend entries.
    lines : list of str
        What the caption says of the domain.
    """
    i, j = axes
    cells = grid.shape[i] * grid.shape[j]
    cap = MAX_SLICE_CELLS if plane is None else MAX_PLANE_CELLS
    if in_domain is None and plane is None:
        return [], ["no controller: no domain drawn"]
    if cells > cap:
        return [], [f"domain not drawn: {cells:,} cells on this plane (at most {cap:,})"]
    if plane is not None:
        mask = np.asarray(plane(base, i, j), dtype=bool)
    else:
        assert in_domain is not None
        mask = slice_mask(in_domain, grid, i, j, base)
    label = f"winning domain ({int(mask.sum()):,} of {mask.size:,} cells)"
    factors = block_factors(mask.shape, MAX_IMAGE_SIDE)
    if factors == (1, 1):
        image = mask.astype(np.int8)
        extent = window
        colors = [(1, 1, 1, 0), DOMAIN_COLOR]
        handles = [Patch(facecolor=DOMAIN_COLOR, edgecolor="none", label=label)]
    else:
        image = block_levels(mask, factors)
        # The last block of an axis may reach past the grid; the axes' limits cut it at the grid's edge.
        extent = (window[0], window[0] + image.shape[0] * factors[0] * grid.eta[i],
                  window[2], window[2] + image.shape[1] * factors[1] * grid.eta[j])
        colors = [(1, 1, 1, 0), PARTLY_COLOR, DOMAIN_COLOR]
        handles = [Patch(facecolor=DOMAIN_COLOR, edgecolor="none",
                         label=f"{label}:\nblocks of {factors[0]} x {factors[1]} cells wholly in it"),
                   Patch(facecolor=PARTLY_COLOR, edgecolor="none", label="blocks partly in it")]
        scope += f"; drawn in blocks of {factors[0]} x {factors[1]} cells ({cells:,} cells on this plane)"
    ax.imshow(image.T, origin="lower", extent=extent, interpolation="nearest", aspect="auto",
              cmap=ListedColormap(colors), vmin=0, vmax=len(colors) - 1, gid="domain", zorder=0)
    return handles, [f"domain: {scope}"]


def _draw_regions(ax, setting: FigureSetting, base: np.ndarray, axes: tuple[int, int],
                  window: Window) -> tuple[list, list[str]]:
    """The state set and the specification's regions (target, safe set, obstacles) as boxes clipped to the
    window; on a slice, only the boxes that meet it.

    Returns
    -------
    handles : list
        One legend entry per kind of box drawn.
    lines : list of str
        For the caption: the regions of which no box meets the plane.
    """
    grid = setting.grid
    i, j = axes
    sliced = grid.dim > 2
    box = Rectangle((grid.lb[i], grid.lb[j]), grid.ub[i] - grid.lb[i], grid.ub[j] - grid.lb[j], fill=False,
                    edgecolor="grey", linestyle=":", linewidth=1.0, gid="state_set", label="state set X", zorder=1)
    ax.add_patch(box)
    handles: list = [box]
    lines = []
    for key in REGION_NAMES:
        drawn = 0
        for k, (lb, ub) in enumerate(setting.regions.get(key, [])):
            if sliced and not _meets_slice(lb, ub, grid, base, i, j):
                continue
            x_lo, x_hi = max(lb[i], window[0]), min(ub[i], window[1])
            y_lo, y_hi = max(lb[j], window[2]), min(ub[j], window[3])
            if x_lo > x_hi or y_lo > y_hi:
                continue
            style = dict(REGION_STYLE[key])
            label = style.pop("label")
            if len(setting.regions[key]) > 8:  # many boxes (a consensus region): thin, so the union reads as one
                style["linewidth"] = 0.6
            rect = Rectangle((x_lo, y_lo), x_hi - x_lo, y_hi - y_lo, gid=f"{key}:{k}", zorder=2,
                             label=label if drawn == 0 else "_nolegend_", **style)
            ax.add_patch(rect)
            if drawn == 0:
                handles.append(rect)
            drawn += 1
        if key in setting.regions and drawn == 0:
            lines.append(f"{key}: no box meets this {'slice' if sliced else 'plane'}")
    atoms = {name: [(lb, ub) for lb, ub in boxes if not sliced or _meets_slice(lb, ub, grid, base, i, j)]
             for name, boxes in setting.atoms.items()}
    handles += draw_atoms(ax, atoms, (i, j))
    return handles, lines


def _mark_x0_outside(ax, setting: FigureSetting, base: np.ndarray, axes: tuple[int, int]) -> tuple[list, list[str]]:
    """An initial state outside the domain, marked where it lies (``gid="x0_outside"``); on a slice it does not
    lie on, the caption says so instead: its projection would sit over the domain cells of another slice.

    Returns
    -------
    handles, lines : list
        Its legend entry, or the caption's line.
    """
    grid, x0 = setting.grid, setting.x0
    assert x0 is not None
    i, j = axes
    x0_cell, on_grid = grid.cell_of(np.asarray(x0, dtype=float)[None, :])
    others = [k for k in range(grid.dim) if k not in (i, j)]
    away = grid.dim > 2 and not (on_grid[0] and np.array_equal(x0_cell[0][others], np.asarray(base)[others]))
    if away:
        return [], [f"x0 = {vector(x0)} (not in the domain) lies off this slice: not drawn"]
    return ax.plot([x0[i]], [x0[j]], "x", color="crimson", markersize=10, mew=2.5, label="x0 (not in the domain)",
                   gid="x0_outside", zorder=6), []


def _draw_runs(ax, runs: Sequence[tuple[str, np.ndarray, Run]], i: int, j: int) -> list:
    """The runs' paths with their start and end marked; returns one legend handle per kind of mark."""
    handles: dict[str, object] = {}
    for r, (origin, _x0, run) in enumerate(runs):
        xs, ys = run.states[:, i], run.states[:, j]
        first = origin == "initial"
        label = "closed loop from x0" if first else "closed loop from random domain states"
        (line,) = ax.plot(xs, ys, "-", color="black" if first else "tab:orange", linewidth=2.0 if first else 1.1,
                          alpha=1.0 if first else 0.85, gid=f"run:{r}", zorder=4 if first else 3,
                          label=label if label not in handles else "_nolegend_")
        handles.setdefault(label, line)
        ax.plot([xs[0]], [ys[0]], "o", markerfacecolor="white", markeredgecolor="black", markersize=6,
                gid=f"start:{r}", zorder=5)
        bad = run.violation is not None
        ax.plot([xs[-1]], [ys[-1]], "X" if bad else "s", color="crimson" if bad else "black",
                markersize=8 if bad else 5, gid=f"end:{r}", zorder=5)
        if bad:
            handles.setdefault("end: violation", Line2D([], [], linestyle="none", marker="X", color="crimson",
                                                        markersize=8, label="end: violation"))
    if runs:
        handles["start"] = Line2D([], [], linestyle="none", marker="o", markerfacecolor="white",
                                  markeredgecolor="black", label="start")
        handles["end"] = Line2D([], [], linestyle="none", marker="s", color="black", markersize=5, label="end")
    return list(handles.values())
