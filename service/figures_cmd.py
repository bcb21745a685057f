"""``compabs figures DIR [--axes 0,1]``: redraw a finished job's figures (:func:`workers.figures.redraw_figures`).

Nothing is abstracted or synthesized again: the spec, the network and the controller are read from ``DIR`` and
the concrete system is run from the stored starts. A directory that is not a finished job, a job without a
controller or axes that are not two state coordinates end in one ``error:`` line, exit status 2 (raised as a
:class:`~pipelines.errors.CompabsError`, which :func:`service.cli.main` reports).
"""

from __future__ import annotations

import argparse
from typing import Any


def axes_pair(text: str) -> tuple[int, int]:
    """An argparse type: two comma-separated state coordinates, 0-based (``0,1`` is x1 and x2)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [int(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give two comma-separated integers, e.g. 0,1") from None
    if len(values) != 2 or min(values) < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: give two state coordinates >= 0, e.g. 0,1")
    return values[0], values[1]


def cmd_figures(args: argparse.Namespace) -> int:
    """The ``figures`` subcommand: prints the figures written; 0 (2 for a user error, raised)."""
    from workers.figures import redraw_figures  # matplotlib: only when drawing (the CLI starts in under a second)

    for path in redraw_figures(args.dir, axes=args.axes):
        print(path)
    return 0


def add_parser(sub: Any) -> None:
    """Register ``compabs figures`` on the CLI's subparsers."""
    f = sub.add_parser("figures", help="redraw a finished job's figures (phase plane, states and inputs over time)")
    f.add_argument("dir", help="output directory of 'compabs run' (or a service job's directory)")
    f.add_argument("--axes", type=axes_pair, default=(0, 1), metavar="I,J",
                   help="the phase plane's state coordinates, 0-based (default 0,1: x1 and x2)")
    f.set_defaults(func=cmd_figures)
