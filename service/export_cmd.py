"""``compabs export``, ``compabs import`` and ``compabs control``: controllers that leave the tool (docs/export.md).

* ``export DIR --format {json,csv,c}``: the job's controller determinized and minimised (:mod:`pipelines.export`);
* ``import FILE.json``: a JSON export read back (its summary, or its input at ``--x``);
* ``control DIR --x 1,2``: the admissible inputs at a concrete state, and the determinized one. Outside the
  controller's domain (or the state box) it says so and exits 1.

Every failure is one ``error:`` line and exit status 2 (:func:`service.cli.main`); a controller file that fails
its checksums or belongs to another spec is refused before it is read
(:class:`~pipelines.controller_integrity.ControllerIntegrityError`).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.errors import CompabsError, SpecError
from service.arguments import count
from workers import jobdir

#: Exit status of ``compabs control`` / ``compabs import --x`` at a state without an input.
NO_INPUT = 1


def parse_state(text: str, dim: int, flag: str = "--x") -> np.ndarray:
    """A comma-separated concrete state with ``dim`` finite components."""
    try:
        x = np.array([float(v) for v in text.split(",")], dtype=float)
    except ValueError:
        raise SpecError(f"{flag} expects comma-separated numbers, got {text!r}") from None
    if x.size != dim:
        raise SpecError(f"{flag} has {x.size} components; the controller's states have {dim}")
    if not all(math.isfinite(v) for v in x):
        raise SpecError(f"{flag} {text!r} has a component that is not a finite number")
    return x


def _name(args: argparse.Namespace) -> str:
    return jobdir.CONTROLLER if not args.controller else f"{jobdir.CONTROLLER}_{args.controller}"


def cmd_export(args: argparse.Namespace) -> int:
    """Write the export; print its sizes (JSON) and the files written."""
    from pipelines.array_controller import ArrayController
    from pipelines.controller import Controller
    from pipelines.controller_loading import load_controller
    from pipelines.export.c import write_c
    from pipelines.export.emit import export_controller, write_csv, write_json
    from pipelines.product_controller import ProductController

    ctrl = load_controller(args.dir, _name(args))
    if isinstance(ctrl, ProductController):
        return _export_product(ctrl, args)
    if not isinstance(ctrl, Controller | ArrayController):
        raise CompabsError(f"{args.dir} is an exported controller; export reads a job's --out directory")
    form = args.form if args.format != "csv" else "bdd"  # a CSV lists cells: no need for a tree
    export = export_controller(ctrl, form=form, rule=args.rule)
    default = Path(args.dir) / f"{_name(args)}_export"
    out = Path(args.out) if args.out else default
    out.parent.mkdir(parents=True, exist_ok=True)  # --out into a directory that does not exist yet
    if args.format == "json":
        files = [write_json(export, out if args.out else out.with_suffix(".json"))]
    elif args.format == "csv":
        files = [write_csv(export, out if args.out else out.with_suffix(".csv"), args.max_rows)]
    else:
        files = list(write_c(export, out))
    summary = {"rule": export.rule, **export.sizes, "files": [str(f) for f in files]}
    if args.format == "c":
        summary["c_bytes"] = sum(f.stat().st_size for f in files)
    print(json.dumps(summary, indent=1))
    return 0


def _export_product(ctrl: Any, args: argparse.Namespace) -> int:
    """``compabs export`` of an ``ltl`` job's controller with memory (:mod:`pipelines.export.memory`)."""
    from pipelines.export.memory import export_product, write_product_csv, write_product_json
    from pipelines.export.memory_c import write_product_c

    export = export_product(ctrl, form=args.form, rule=args.rule)
    out = Path(args.out) if args.out else Path(args.dir) / f"{_name(args)}_export"
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.format == "json":
        files = [write_product_json(export, out if args.out else out.with_suffix(".json"))]
    elif args.format == "csv":
        files = write_product_csv(export, out if args.out else out.with_suffix(".csv"), args.max_rows)
    else:
        files = list(write_product_c(export, out))
    summary: dict[str, Any] = {"rule": export.rule, **export.sizes, "files": [str(f) for f in files]}
    if args.format == "c":
        summary["c_bytes"] = sum(f.stat().st_size for f in files)
    print(json.dumps(summary, indent=1))
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    """Read a JSON export back; print its summary, or its input at ``--x`` (exit 1 outside its domain)."""
    from pipelines.controller_loading import is_export
    from pipelines.export.table import PRODUCT_EXPORT_FORMAT, load_export

    if Path(args.file).is_file() and is_export(Path(args.file), PRODUCT_EXPORT_FORMAT):
        raise CompabsError(f"{args.file} is the export of an 'ltl' controller (a controller with memory), which "
                           "'compabs import' does not query: ask the job with 'compabs control DIR --x ... --q Q', or "
                           "read it with pipelines.load_controller")
    ctrl = load_export(args.file)
    if args.x is None:
        print(json.dumps({**ctrl.meta, "state_dim": ctrl.state_grid.dim, "input_dim": ctrl.input_dim}, indent=1))
        return 0
    x = parse_state(args.x, ctrl.state_grid.dim)
    u = ctrl.input(x)
    if u is None:
        print(f"x = {x.tolist()} is outside the exported controller's domain: no input")
        return NO_INPUT
    print(",".join(repr(float(v)) for v in u))
    return 0


def control_at(directory: str, x_text: str, rule: str = "auto", name: str = jobdir.CONTROLLER,
               q: int | None = None) -> dict[str, Any]:
    """What ``compabs control`` reports at a state: its cell, the admissible inputs, the determinized one; for a
    controller with memory also the letter and the automaton state ``q`` (default ``δ(q₀, σ(x))``: the run
    starts at ``x``)."""
    from pipelines.array_controller import ArrayController
    from pipelines.controller import Controller, LayeredController
    from pipelines.controller_loading import load_controller
    from pipelines.export.determinize import determinized_at, resolve_rule
    from pipelines.export.table import RULES, ExportError
    from pipelines.product_controller import ProductController

    ctrl = load_controller(directory, name)
    if isinstance(ctrl, ProductController):
        return _product_control_at(ctrl, x_text, rule, q)
    if q is not None:
        raise CompabsError("--q is the automaton state of an 'ltl' job's controller (a controller with memory); "
                           f"{directory}'s controller has none")
    if not isinstance(ctrl, Controller | ArrayController):
        raise CompabsError(f"{directory} is an exported controller; for its input at a state use 'compabs import "
                           f"{directory} --x ...'")
    x = parse_state(x_text, ctrl.state_grid.dim)
    if isinstance(ctrl, ArrayController):
        # An array controller's inputs are its determinization's candidates; a progress controller's all lead
        # into the layer before the cell's, so both rules choose its smallest admissible input.
        if rule not in RULES:
            raise ExportError(f"unknown rule {rule!r}; expected one of {', '.join(RULES)}")
        if rule == "auto":
            layered = ctrl.layers is not None and ctrl.meta.get("kind") != "safe"
            rule = "earliest_layer" if layered else "smallest_index"
    else:
        rule = resolve_rule(ctrl, rule)
    idx = ctrl.cell(x)
    out: dict[str, Any] = {"x": x.tolist(), "cell": None, "cell_centre": None, "in_domain": False, "inputs": [],
                           "determinized": None, "rule": rule, "fixed_point": ctrl.meta.get("fixed_point")}
    if idx is None:
        out["reason"] = "outside the state box"
        return out
    out["cell"] = [int(v) for v in idx]
    out["cell_centre"] = ctrl.state_grid.points(idx[None, :])[0].tolist()
    if isinstance(ctrl, LayeredController) or (isinstance(ctrl, ArrayController) and ctrl.layers is not None):
        out["layer"] = ctrl.layer_of(idx)
    inputs = ctrl.inputs(x)
    out["inputs"] = inputs.tolist()
    out["in_domain"] = bool(inputs.shape[0])
    if not out["in_domain"]:
        out["reason"] = "outside the controller's domain"
        return out
    if isinstance(ctrl, ArrayController):
        out["determinized"] = inputs[0].tolist()
        return out
    codes = determinized_at(ctrl, idx, rule)
    assert codes is not None
    parts = [g.points(g.unravel(codes[s:s + 1])) for s, g in enumerate(ctrl.input_grids)]
    out["determinized"] = np.concatenate(parts, axis=1)[0].tolist()
    return out


def _product_control_at(ctrl: Any, x_text: str, rule: str, q: int | None) -> dict[str, Any]:
    """:func:`control_at` for a :class:`~pipelines.product_controller.ProductController`: ``C_q`` at ``x``'s cell.
    Its determinized input is the smallest admissible input index (what ``compabs export`` writes): every input
    of ``C_q`` makes progress in the product, so the rule is ``smallest_index`` whatever ``rule`` asks."""
    from pipelines.controller import Controller
    from pipelines.export.determinize import determinized_at
    from pipelines.export.table import RULES, ExportError

    if rule not in ("auto", "smallest_index"):
        raise ExportError(f"an 'ltl' controller is determinized by the smallest admissible input index (every input "
                          f"makes progress in the product); rule {rule!r} is not for it (one of {', '.join(RULES)})")
    automaton = ctrl.automaton
    x = parse_state(x_text, ctrl.state_grid.dim)
    letter = int(ctrl.letters_at(x[None, :])[0])
    if q is None:
        q = int(ctrl.initial_state(x[None, :])[0])
    elif not 0 <= q < automaton.n_states:
        raise SpecError(f"--q {q}: the automaton has states 0 .. {automaton.n_states - 1}")
    out: dict[str, Any] = {"x": x.tolist(), "letter": letter,
                           "atoms": [a for i, a in enumerate(automaton.atoms) if (letter >> i) & 1],
                           "q": q, "accepting": bool(automaton.accepting[q]), "cell": None, "cell_centre": None,
                           "in_domain": False, "inputs": [], "determinized": None, "rule": "smallest_index",
                           "fixed_point": ctrl.meta.get("fixed_point")}
    idx = ctrl.cell(x)
    if idx is None:
        out["reason"] = "outside the state box"
        return out
    out["cell"] = [int(v) for v in idx]
    out["cell_centre"] = ctrl.state_grid.points(idx[None, :])[0].tolist()
    out["layer"] = ctrl.layer_of(idx, q)
    inputs = ctrl.inputs(x, q)
    out["inputs"] = inputs.tolist()
    out["in_domain"] = bool(inputs.shape[0])
    if not out["in_domain"]:
        out["reason"] = f"outside the controller's winning set in automaton state {q}"
        return out
    per_state = ctrl.per_state[q]
    if not isinstance(per_state, Controller):  # an array controller lists its inputs by index
        out["determinized"] = inputs[0].tolist()
        return out
    codes = determinized_at(per_state, idx, "smallest_index")
    assert codes is not None
    parts = [g.points(g.unravel(codes[s:s + 1])) for s, g in enumerate(ctrl.input_grids)]
    out["determinized"] = np.concatenate(parts, axis=1)[0].tolist()
    return out


def format_control(r: dict[str, Any], limit: int) -> str:
    """The report of :func:`control_at` as a short table."""
    lines = [f"x = {r['x']}"]
    if "q" in r:
        atoms = ", ".join(r["atoms"]) or "none"
        lines.append(f"automaton state {r['q']}{' (accepting)' if r['accepting'] else ''}; atoms holding at x: "
                     f"{atoms}")
    if r["cell"] is None:
        return "\n".join(lines + [f"no input: x is {r['reason']}"])
    layer = f", layer {r['layer']}" if r.get("layer") is not None else ""
    lines.append(f"cell {r['cell']} (centre {r['cell_centre']}){layer}")
    if not r["in_domain"]:
        return "\n".join(lines + [f"no input: x is {r['reason']}"])
    m = len(r["inputs"][0])
    rows = [[f"u{j + 1}" for j in range(m)]] + [[f"{v:g}" for v in u] for u in r["inputs"][:limit]]
    width = max(len(c) for row in rows for c in row)
    lines.append(f"admissible inputs ({len(r['inputs'])}):")
    lines += ["  " + "  ".join(c.rjust(width) for c in row) for row in rows]
    if len(r["inputs"]) > limit:
        lines.append(f"  ... and {len(r['inputs']) - limit} more (--limit, --json)")
    lines.append(f"determinized ({r['rule']} rule): " + ", ".join(f"{v:g}" for v in r["determinized"]))
    return "\n".join(lines)


def cmd_control(args: argparse.Namespace) -> int:
    """Print the inputs at ``--x``: 0 if there is one, 1 outside the domain or the box (2 for a user error)."""
    r = control_at(args.dir, args.x, args.rule, _name(args), args.q)
    print(json.dumps(r) if args.json else format_control(r, args.limit))
    return 0 if r["in_domain"] else NO_INPUT


def add_parser(sub: Any) -> None:
    """Register ``compabs export``, ``compabs import`` and ``compabs control`` on the CLI's subparsers."""
    from pipelines.export.table import CSV_MAX_ROWS, FORMS, RULES  # light: the CLI starts in under a second

    e = sub.add_parser("export", help="write a job's controller determinized and minimised as JSON, CSV or C")
    e.add_argument("dir", help="output directory of 'compabs run'")
    e.add_argument("--format", choices=["json", "csv", "c"], required=True)
    e.add_argument("--out", default=None, help="file (json, csv) or base name of NAME.h/NAME.c (c); default "
                   "DIR/controller_export.*")
    e.add_argument("--rule", choices=RULES, default="auto", help="determinization rule (docs/export.md)")
    e.add_argument("--form", choices=FORMS, default="auto", help="bdd, tree or the smaller (auto)")
    e.add_argument("--controller", default=None, metavar="FIXED_POINT",
                   help="another stored fixed point's controller (controller_<FIXED_POINT>.json)")
    e.add_argument("--max-rows", type=count(1), default=CSV_MAX_ROWS, help="largest CSV (domain cells)")
    e.set_defaults(func=cmd_export)
    i = sub.add_parser("import", help="read a JSON controller export back: its summary, or its input at --x")
    i.add_argument("file", help="a file written by 'compabs export --format json'")
    i.add_argument("--x", default=None, help="a state, comma-separated: print the exported controller's input")
    i.set_defaults(func=cmd_import)
    c = sub.add_parser("control", help="the admissible inputs of a job's controller at a state (exit 1 outside "
                       "its domain)")
    c.add_argument("dir", help="output directory of 'compabs run'")
    c.add_argument("--x", required=True, help="the state, comma-separated")
    c.add_argument("--rule", choices=RULES, default="auto", help="rule of the determinized input")
    c.add_argument("--controller", default=None, metavar="FIXED_POINT", help="as for export")
    c.add_argument("--q", type=count(0), default=None, help="an 'ltl' controller's automaton state at x (default: "
                   "the one a run starting at x is in)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--limit", type=count(1), default=20, help="admissible inputs listed in the table")
    c.set_defaults(func=cmd_control)
