"""States and inputs over time for one closed-loop run (the paper's Fig. 4-5), with the run under ``u = 0``
from the same state for comparison.

Each state coordinate carries the band of every box of the target and of the safe set on that coordinate (for
every specification kind that has one); a consensus region (``|x_i - phi| <= r`` for every ``i``, for one of its
centres ``phi``) has no fixed band, so at each step the box of it that holds the state is drawn, and none where
no box does: the run is in the region exactly at the steps where every coordinate lies in a band. Inputs are
drawn as the zero-order hold they are (``steps-post``), exactly as applied, and inputs that are 0 throughout the
run are named in a note above their panel rather than drawn. Time steps are integers on the axis.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import MaxNLocator

from pipelines.figures.setting import CHOICES, Consensus, FigureSetting, short_message, vector
from pipelines.verification.closed_loop import Run

#: Up to this many state coordinates, each gets its own panel (and its own bands); beyond, one panel for all.
MAX_STATE_PANELS = 4

#: Line styles of the inputs, in turn (equal inputs coincide; the styles keep each visible).
INPUT_STYLES = ("-", "--", ":", "-.")

BAND_STYLE = {"target": ("tab:green", 0.16, "target"), "safe": ("tab:blue", 0.10, "safe set")}


def _intervals(boxes: Sequence[tuple[np.ndarray, np.ndarray]], c: int) -> list[tuple[float, float]]:
    """The distinct intervals the boxes span on coordinate ``c``, in order."""
    return sorted({(float(lb[c]), float(ub[c])) for lb, ub in boxes})


def _outcome(kind: str, run: Run) -> str:
    if run.violation is not None:
        return f"violation: {short_message(run.violation)}"
    k = run.inputs.shape[0]
    if kind in ("reach", "reach_avoid"):
        return f"target reached at k = {k}" + (" (x0 is in it)" if k == 0 else "")
    if kind == "reach_and_stay":
        return f"in the target from k = {run.settled_at} to the end (k = {k})"
    return f"in the safe set for all {k} steps"


def _free_line(free: Run, steps: int) -> str:
    k = free.inputs.shape[0]
    if k < steps:
        why = short_message(free.violation or "stopped")
        return f"dashed: from the same start with u = 0; it ends at k = {k}: {why}"
    return f"dashed: from the same start with u = 0, over {k} step{'' if k == 1 else 's'}"


def time_plot(
    setting: FigureSetting,
    run: Run,
    *,
    origin: str = "initial",
    free: Run | None = None,
    steps: int | None = None,
) -> Figure:
    """States over time with the target and safe bands, and the inputs as steps.

    Parameters
    ----------
    setting : FigureSetting
    run : Run
        The closed-loop run drawn.
    origin : str
        ``"initial"`` (it starts at the spec's initial state) or ``"random"`` (a random state of the domain).
    free : Run, optional
        The run from the same state with all inputs 0, drawn dashed; where it ends early the title says why.
    steps : int, optional
        The horizon the runs were given (default: the controlled run's length).

    Returns
    -------
    Figure
        Artists carry ``gid``s: ``state:c`` and ``free:c`` (lines), ``target_band:c:k`` and ``safe_band:c:k``
        (spans; ``c`` is ``all`` where one band holds for every coordinate), ``target_band:c:consensus:m`` and
        ``safe_band:c:consensus:m`` (rectangles: the ``m``-th stretch of steps in one box of a consensus region),
        ``input:j`` (step lines).
    """
    n = setting.grid.dim
    K = run.inputs.shape[0]
    steps = K if steps is None else steps
    panels = n if n <= MAX_STATE_PANELS else 1
    fig = Figure(figsize=(10.0, 1.9 * panels + 2.3 if panels > 1 else 6.5))
    axs = fig.subplots(panels + 1, 1, sharex=True, squeeze=False,
                       gridspec_kw={"height_ratios": [2.0] * panels + [1.4]})[:, 0]
    colors = [f"C{c % 10}" for c in range(n)]
    k_states = np.arange(run.states.shape[0])
    for c in range(n):
        ax = axs[c if panels > 1 else 0]
        ax.plot(k_states, run.states[:, c], "-", color=colors[c], linewidth=1.6, gid=f"state:{c}",
                label=f"{setting.state_names[c]}")
        if free is not None:
            ax.plot(np.arange(free.states.shape[0]), free.states[:, c], "--", color=colors[c], linewidth=1.0,
                    alpha=0.7, gid=f"free:{c}", label="u = 0" if panels > 1 or c == 0 else "_nolegend_")
            if free.inputs.shape[0] < steps:
                ax.plot([free.states.shape[0] - 1], [free.states[-1, c]], "x", color=colors[c], markersize=7)
    notes = _bands(setting, list(axs[:panels]), colors, run.states)

    ax_u = axs[-1]
    k_inputs = np.arange(K + 1)
    zero = [name for j, name in enumerate(setting.input_names) if not np.any(run.inputs[:, j])] if K else []
    drawn = [j for j, name in enumerate(setting.input_names) if K and name not in zero]
    for rank, j in enumerate(drawn):
        u = run.inputs[:, j]
        # Inputs are drawn as applied, so equal ones coincide: each later one thinner and dashed, on top.
        width = 2.8 - 1.8 * rank / max(len(drawn) - 1, 1)
        # The last input holds until k = K: repeat it so steps-post draws its whole step.
        ax_u.plot(k_inputs, np.append(u, u[-1]), drawstyle="steps-post", linewidth=width,
                  linestyle=INPUT_STYLES[rank % len(INPUT_STYLES)], gid=f"input:{j}",
                  label=setting.input_names[j], zorder=2 + rank)
    if K == 0:
        ax_u.text(0.01, 0.5, "no input applied (the run took no step)", transform=ax_u.transAxes, fontsize=8)
    elif zero:
        which = ", ".join(z.split(" ")[0] for z in zero) if len(zero) > 1 else zero[0]
        # Above the panel, not over the inputs drawn at 0.
        ax_u.text(0.0, 1.03, textwrap.fill(f"{which}: 0 at every step", 110), transform=ax_u.transAxes,
                  fontsize=7.5, color="dimgray", va="bottom")
    ax_u.set_ylabel("input")
    ax_u.set_xlabel("time step k")
    ax_u.xaxis.set_major_locator(MaxNLocator(integer=True, steps=[1, 2, 5, 10]))  # shared by every panel
    for ax in axs:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7.5, frameon=False)
    if panels == 1:
        axs[0].set_ylabel("state")

    start = "x0" if origin == "initial" else f"a random state of the domain, {vector(run.states[0])}"
    lines = [setting.initial_state_line(),
             f"drawn: the closed loop from {start}; {_outcome(setting.kind, run)}",
             f"inputs: {CHOICES.get(setting.choice, setting.choice)}"]
    if free is not None:
        lines.append(_free_line(free, steps))
    lines += notes
    axs[0].set_title("\n".join(textwrap.fill(t, 110) for t in lines), fontsize=8, loc="left")
    return fig


def _bands(setting: FigureSetting, axs: Sequence, colors: list[str], states: np.ndarray) -> list[str]:
    """Draw each region's band per coordinate; returns notes for regions without one."""
    n = setting.grid.dim
    notes = []
    for key, (color, alpha, name) in BAND_STYLE.items():
        if key not in setting.regions:
            continue
        boxes = setting.bands.get(key, [])
        consensus = setting.consensus.get(key)
        if consensus is not None:
            _consensus_band(axs, states, consensus, key, color, alpha, name, per_coordinate=len(axs) == n)
            notes.append(f"{name} band: at each step, the box of the consensus region ({consensus.describe()}) "
                         "that holds the state; none where no box does")
        if not boxes:
            if consensus is None:
                notes.append(f"{name}: no box region, no band drawn")
            continue
        per = [_intervals(boxes, c) for c in range(n)]
        if len(axs) == n:  # one panel per coordinate
            for c, ax in enumerate(axs):
                for k, (lo, hi) in enumerate(per[c]):
                    ax.axhspan(lo, hi, color=color, alpha=alpha, gid=f"{key}_band:{c}:{k}",
                               label=f"{name} ({setting.state_names[c].split(' ')[0]})" if k == 0 else "_nolegend_")
        elif all(p == per[0] for p in per):  # one panel, and every coordinate has the same band
            for k, (lo, hi) in enumerate(per[0]):
                axs[0].axhspan(lo, hi, color=color, alpha=alpha, gid=f"{key}_band:all:{k}",
                               label=f"{name} (every coordinate)" if k == 0 else "_nolegend_")
        else:  # one panel, bands that differ: each in its coordinate's colour
            for c in range(n):
                for k, (lo, hi) in enumerate(per[c]):
                    axs[0].axhspan(lo, hi, color=colors[c], alpha=0.06, gid=f"{key}_band:{c}:{k}",
                                   label=f"{name} of each coordinate (its colour)" if c == k == 0 else "_nolegend_")
    return notes


def consensus_stretches(states: np.ndarray, consensus: Consensus) -> list[tuple[int, int, float]]:
    """The steps of a run grouped by the consensus box that holds the state: ``(first step, last step, phi)``
    per stretch, in order; a box is kept while it holds the state (no flicker between overlapping boxes)."""
    choice = consensus.centres(states)
    out: list[tuple[int, int, float]] = []
    phi = np.nan
    for k, x in enumerate(np.atleast_2d(states)):
        keep = not np.isnan(phi) and bool(np.all(np.abs(x - phi) <= consensus.radius))
        if not keep:
            phi = choice[k]
            if np.isnan(phi):
                continue
        if out and out[-1][2] == phi and out[-1][1] == k - 1:
            out[-1] = (out[-1][0], k, phi)
        else:
            out.append((k, k, float(phi)))
    return out


def _consensus_band(axs: Sequence, states: np.ndarray, consensus: Consensus, key: str, color: str, alpha: float,
                    name: str, *, per_coordinate: bool) -> None:
    """At each step, the band ``[phi - r, phi + r]`` of the consensus box holding the state (every panel)."""
    r = consensus.radius
    for c, ax in enumerate(axs):
        where = c if per_coordinate else "all"
        for m, (k0, k1, phi) in enumerate(consensus_stretches(states, consensus)):
            ax.add_patch(Rectangle((k0 - 0.5, phi - r), k1 - k0 + 1, 2 * r, color=color, alpha=alpha, linewidth=0,
                                   gid=f"{key}_band:{where}:consensus:{m}", zorder=0,
                                   label=f"{name}: consensus box holding the state" if m == 0 else "_nolegend_"))
