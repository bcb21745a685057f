"""The figures a control engineer reads (like the paper's Fig. 4-5), drawn with matplotlib's object API.

* :func:`phase_plane` — two state coordinates: the winning domain cell by cell, the target, the safe set and
  every obstacle box, and closed-loop runs on top (:mod:`.phase_plane`).
* :func:`time_plot` — states over time with the target and safe bands of each coordinate, the inputs as steps
  (:mod:`.time_plot`).

Both return a :class:`matplotlib.figure.Figure` (no pyplot state: safe in worker threads) that
:func:`save_figure` writes as PNG; what every figure states (spec kind, initial state, whether it is in the
controller's domain) is gathered once in a :class:`FigureSetting` (:mod:`.setting`).
"""

from pipelines.figures.phase_plane import MAX_SLICE_CELLS, phase_plane
from pipelines.figures.setting import FigureSetting, concrete_boxes, figure_setting, save_figure
from pipelines.figures.time_plot import time_plot

__all__ = [
    "MAX_SLICE_CELLS",
    "FigureSetting",
    "concrete_boxes",
    "figure_setting",
    "phase_plane",
    "save_figure",
    "time_plot",
]
