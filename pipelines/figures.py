"""Figures like the paper's Fig. 4-5: states and inputs over time with and without the controller, and a
2-D slice of the controller's domain. PNG files, drawn with matplotlib's non-interactive backend.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipelines.verification.closed_loop import Run


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def trajectory_figure(controlled: Run, free: Run, path: Path, title: str, target: tuple[float, float] | None = None) -> Path:
    """States over time (solid: controlled, dashed: inputs 0) and the applied inputs, from one initial state."""
    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 7), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    n = controlled.states.shape[1]
    colors = plt.cm.tab10(np.linspace(0, 1, max(n, 2)))
    for i in range(n):
        ax1.plot(controlled.states[:, i], "-", color=colors[i % 10], lw=1.6, label=f"x{i + 1}")
        ax1.plot(free.states[:, i], "--", color=colors[i % 10], lw=1.0, alpha=0.7)
    if target is not None:
        ax1.axhspan(target[0], target[1], color="green", alpha=0.08, label="target (per coordinate)")
    ax1.set_ylabel("state")
    ax1.set_title(f"{title}\ncontrolled (solid) and u = 0 (dashed)", fontsize=9)
    ax1.legend(ncol=min(n + 1, 6), fontsize=7, loc="upper right")
    if controlled.inputs.size:
        jitter = np.linspace(-0.05, 0.05, controlled.inputs.shape[1])
        for j in range(controlled.inputs.shape[1]):
            ax2.step(np.arange(controlled.inputs.shape[0]), controlled.inputs[:, j] + jitter[j], where="post",
                     lw=1.2, label=f"u{j + 1}")
        ax2.legend(ncol=min(controlled.inputs.shape[1], 8), fontsize=7)
    ax2.set_xlabel("time step k")
    ax2.set_ylabel("input")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def domain_slice_figure(
    in_domain: Callable[[np.ndarray], np.ndarray],
    points_i: np.ndarray,
    points_j: np.ndarray,
    base_idx: np.ndarray,
    i: int,
    j: int,
    path: Path,
    title: str,
) -> Path:
    """The controller's domain on the plane of coordinates ``i`` and ``j``, the others fixed at ``base_idx``.

    ``in_domain`` maps composed cell indices, shape (B, n), to bool (B,).
    """
    plt = _pyplot()
    ki, kj = len(points_i), len(points_j)
    idx = np.repeat(base_idx[None, :], ki * kj, axis=0)
    ii, jj = np.meshgrid(np.arange(ki), np.arange(kj), indexing="ij")
    idx[:, i] = ii.ravel()
    idx[:, j] = jj.ravel()
    mask = in_domain(idx).reshape(ki, kj)
    fig, ax = plt.subplots(figsize=(5.5, 5))
    ax.imshow(mask.T, origin="lower", cmap="Greens", vmin=0, vmax=1.4, aspect="auto",
              extent=[points_i[0], points_i[-1], points_j[0], points_j[-1]])
    ax.set_xlabel(f"x{i + 1}")
    ax.set_ylabel(f"x{j + 1}")
    ax.set_title(f"{title}\n{int(mask.sum())} of {mask.size} cells in the domain")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
