"""The trajectory of an ``ltl`` job (a controller with memory): the run on two state coordinates with its steps
coloured by the automaton state they lead into and the formula's regions labelled by their atoms' names, and
beside it the automaton state over time (accepting states marked).

The colour of a step from ``x_k`` to ``x_{k+1}`` is the automaton state after reading ``x_{k+1}``'s letter, so
a reader sees where on the plane the run passed each stage of the formula; a system of one coordinate draws that
coordinate over time instead of a plane.
"""

from __future__ import annotations

import textwrap
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from pipelines.figures.setting import Box, FigureSetting, vector
from pipelines.temporal.automaton import Automaton
from pipelines.verification.closed_loop import Run

#: Colours of the automaton states (cycled beyond ten states).
STATE_COLORS = ("tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan",
                "tab:red", "tab:gray", "navy")
#: Colours of the atoms' regions.
ATOM_COLORS = ("seagreen", "darkorange", "royalblue", "firebrick", "goldenrod", "teal", "purple", "sienna")


def state_color(q: int) -> str:
    return STATE_COLORS[int(q) % len(STATE_COLORS)]


def draw_atoms(ax, atoms: Mapping[str, Sequence[Box]], axes: tuple[int, int], *, label: bool = True) -> list:
    """Every atom's boxes on the plane of ``axes`` as dashed rectangles named at their centre (``gid``
    ``atom:NAME:k``); returns one legend handle per atom."""
    i, j = axes
    handles = []
    for a, (name, boxes) in enumerate(atoms.items()):
        color = ATOM_COLORS[a % len(ATOM_COLORS)]
        for k, (lb, ub) in enumerate(boxes):
            rect = Rectangle((lb[i], lb[j]), ub[i] - lb[i], ub[j] - lb[j], fill=True, facecolor=color, alpha=0.18,
                             edgecolor=color, linestyle="--", linewidth=1.4, gid=f"atom:{name}:{k}", zorder=2,
                             label=f"region {name}" if k == 0 else "_nolegend_")
            ax.add_patch(rect)
            if k == 0:
                handles.append(rect)
            if label:
                ax.text((lb[i] + ub[i]) / 2, (lb[j] + ub[j]) / 2, name, color=color, fontsize=11, weight="bold",
                        ha="center", va="center", gid=f"atom_label:{name}:{k}", zorder=6)
    return handles


def _state_handles(automaton: Automaton, seen: Sequence[int] | np.ndarray) -> list:
    return [Line2D([], [], color=state_color(q), linewidth=2.5,
                   label=f"automaton state {q}{' (accepting)' if automaton.accepting[q] else ''}")
            for q in sorted(set(int(v) for v in seen))]


def product_trajectory(setting: FigureSetting, run: Run, automaton_states: Sequence[int], automaton: Automaton,
                       atoms: Mapping[str, Sequence[Box]], *, axes: Sequence[int] = (0, 1),
                       origin: str = "initial") -> Figure:
    """The run of a controller with memory (module docstring).

    Parameters
    ----------
    setting : FigureSetting
    run : Run
        Its ``states`` (K+1, n); ``settled_at`` the step it accepted at.
    automaton_states : sequence of int
        The automaton state after each state's letter, length K+1.
    automaton : Automaton
    atoms : mapping of str to list of Box
        The formula's regions by atom name, as concrete boxes.
    axes : (int, int)
        The plane's coordinates (a system of one coordinate: ignored).
    origin : str
        ``initial`` (the spec's initial state) or ``random`` (a random domain state).

    Returns
    -------
    Figure
        Artists carry ``gid``s: ``step:k`` (the run's segments), ``atom:NAME:k`` and ``atom_label:NAME:k``
        (the regions), ``automaton_states`` (the right panel's steps).
    """
    X = np.asarray(run.states, dtype=float)
    q = np.asarray(automaton_states, dtype=np.int64)
    fig = Figure(figsize=(11.5, 5.2))
    left, right = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.25, 1]})
    if X.shape[1] >= 2:
        i, j = int(axes[0]), int(axes[1])
        xs, ys, xlabel, ylabel = X[:, i], X[:, j], setting.state_names[i], setting.state_names[j]
        handles = draw_atoms(left, atoms, (i, j))
        g = setting.grid
        left.add_patch(Rectangle((g.lb[i], g.lb[j]), g.ub[i] - g.lb[i], g.ub[j] - g.lb[j], fill=False,
                                 edgecolor="grey", linestyle=":", gid="state_set"))
        left.set_xlim(g.lb[i], g.ub[i])
        left.set_ylim(g.lb[j], g.ub[j])
        left.set_aspect("equal", adjustable="box")
    else:
        xs, ys, xlabel, ylabel = np.arange(X.shape[0], dtype=float), X[:, 0], "step", setting.state_names[0]
        handles = []
        for a, (name, boxes) in enumerate(atoms.items()):
            for lb, ub in boxes:
                left.axhspan(lb[0], ub[0], color=ATOM_COLORS[a % len(ATOM_COLORS)], alpha=0.18)
                left.text(0, (lb[0] + ub[0]) / 2, name, fontsize=11, weight="bold", va="center")
    for k in range(X.shape[0] - 1):  # one segment per step: its colour is the state it leads into
        left.plot(xs[k:k + 2], ys[k:k + 2], "-", color=state_color(q[k + 1]), linewidth=2.2, gid=f"step:{k}",
                  zorder=4)
    left.plot(xs[:1], ys[:1], "o", markerfacecolor="white", markeredgecolor="black", zorder=5, gid="start")
    left.plot(xs[-1:], ys[-1:], "X" if run.violation else "s", color="crimson" if run.violation else "black",
              zorder=5, gid="end")
    left.set_xlabel(xlabel)
    left.set_ylabel(ylabel)
    left.legend(handles=handles + _state_handles(automaton, q), fontsize=8, loc="best")

    steps = np.arange(q.size)
    right.step(steps, q, where="post", color="black", linewidth=1.0, gid="automaton_states")
    right.scatter(steps, q, c=[state_color(v) for v in q], zorder=3, s=18)
    for acc in np.flatnonzero(automaton.accepting).tolist():
        right.axhspan(acc - 0.4, acc + 0.4, color="lightgreen", alpha=0.4, zorder=0)
    right.set_yticks(range(automaton.n_states))
    right.set_yticklabels([f"{s}{' (acc.)' if automaton.accepting[s] else ''}" for s in range(automaton.n_states)])
    right.set_xlabel("step")
    right.set_ylabel("automaton state")

    formula = setting.formula or ""
    start = "x0" if origin == "initial" else "a random domain state"
    outcome = (f"violation: {run.violation}" if run.violation else
               f"formula satisfied at step {run.settled_at}" if run.settled_at is not None else
               "not yet accepted when the figure's steps ended")
    lines = [setting.initial_state_line(), f"formula: {formula}",
             f"run from {start} = {vector(X[0])} under the controller with memory; {outcome}"]
    fig.suptitle("\n".join(textwrap.fill(t, 130) for t in lines), fontsize=8, x=0.02, ha="left")
    return fig
