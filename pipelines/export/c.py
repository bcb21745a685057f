"""The export as C99: a header and a source defining ``int compabs_control(const double *x, double *u)``.

``compabs_control`` returns 1 and writes the chosen input to ``u`` when ``x`` is in the controller's domain, 0
otherwise (``u`` untouched). It allocates nothing and needs only ``<math.h>`` and ``<stdint.h>`` (link with
``-lm``). Its quantizer is :func:`pipelines.grid.quantize` operation for operation (the same IEEE double operations in
the same order, the same relative snapping, the box's edges included), so it picks the cell the tool picks; the
constants are written as hexadecimal floating literals, exact. The controller is the export's table: the BDD
(one walk per root, at most one step per state bit) or the decision tree.

Nothing but numbers and checked identifiers is written: no text of the controller's header or spec (names,
descriptions) reaches the source, so an edited header cannot put code into it.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipelines.export.emit import Export, int_type
from pipelines.export.table import FORMS, RULES, ExportError
from pipelines.grid import SNAP_RTOL, UniformGrid

PER_LINE = 16
#: What a word from the controller's header must be to be written into a C comment.
IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}")
#: What the export's base name must be (it is written in ``#include "NAME.h"``).
FILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")


def _array(name: str, values: np.ndarray | list | tuple, ctype: str | None = None) -> str:
    a = np.asarray(values).ravel()
    if a.dtype.kind == "f":
        ctype = ctype or "double"
        body = [float(v).hex() for v in a.tolist()]
    else:
        a = a.astype(np.int64)
        if a.size == 0:
            a = np.zeros(1, dtype=np.int64)  # C has no empty arrays
        ctype = ctype or int_type(int(a.min()), int(a.max()))[0]
        body = [str(v) for v in a.tolist()]
    lines = [", ".join(body[k:k + PER_LINE]) for k in range(0, len(body), PER_LINE)]
    return f"static const {ctype} {name}[{len(body)}] = {{\n    " + ",\n    ".join(lines) + "\n};\n"


QUANTIZE = """
/* The cell of x (compabs's quantizer, pipelines.grid.quantize): 1 and idx, or 0 outside the box. */
static int quantize(const double *x, int64_t *idx)
{
    for (int i = 0; i < NX; ++i) {
        if (!(x[i] >= LB[i] && x[i] <= UB[i]))
            return 0;
    }
    for (int i = 0; i < NX; ++i) {
        double r = (x[i] - ORIGIN[i]) / ETA[i] + 0.5;
        double nearest = nearbyint(r);
        if (fabs(r - nearest) <= SNAP_RTOL * fmax(1.0, fabs(r)))
            r = nearest;
        int64_t upper = (int64_t)floor(r) - K_LO[i];
        int64_t lower = (int64_t)ceil(r) - 1 - K_LO[i];
        int64_t k = (upper >= 0 && upper < SHAPE[i]) ? upper : lower;
        if (k < 0 || k >= SHAPE[i])
            return 0;
        idx[i] = k;
    }
    return 1;
}
"""

BDD_WALK = """
/* Value of the BDD edge e at the cell idx: edge = node << 1 | complemented, node 0 the constant TRUE. */
static int evaluate(uint32_t e, const int64_t *idx)
{
    while (e >> 1) {
        uint32_t n = e >> 1;
        uint32_t v = NODE_VAR[n];
        int64_t bit = (idx[BIT_COORD[v]] >> BIT_SHIFT[v]) & 1;
        e = (uint32_t)(bit ? NODE_HIGH[n] : NODE_LOW[n]) ^ (e & 1u);
    }
    return !(e & 1u);
}
"""

BDD_EVAL = BDD_WALK + """
static int choose(const int64_t *idx, int64_t *code)
{
    if (!evaluate(ROOT_DOMAIN, idx))
        return 0;
    int c = 0;
    for (int s = 0; s < NS; ++s) {
        code[s] = 0;
        for (int k = 0; k < WIDTH[s]; ++k)
            code[s] = (code[s] << 1) | evaluate(OUTPUT[c++], idx);
    }
    return 1;
}
"""

TREE_EVAL = """
static int choose(const int64_t *idx, int64_t *code)
{
    uint32_t n = 0;
    while (FEATURE[n] >= 0)
        n = idx[FEATURE[n]] < THRESHOLD[n] ? (uint32_t)LEFT[n] : (uint32_t)RIGHT[n];
    if (LEAF[n] < 0)
        return 0;
    for (int s = 0; s < NS; ++s)
        code[s] = CHOICES[(int64_t)LEAF[n] * NS + s];
    return 1;
}
"""

#: The end of a control function: each subsystem's input point of its code written to ``u``.
WRITE_INPUT = """    for (int s = 0; s < NS; ++s) {
        for (int d = 0; d < U_DIM[s]; ++d)
            u[U_OUT[s] + d] = U_POINTS[U_OFFSET[s] + code[s] * U_DIM[s] + d];
    }
    return 1;
}
"""

CONTROL = """
int compabs_control(const double *x, double *u)
{
    int64_t idx[NX];
    int64_t code[NS];
    if (!quantize(x, idx) || !choose(idx, code))
        return 0;
    for (int s = 0; s < NS; ++s) {
        if (code[s] < 0 || code[s] >= N_INPUTS[s])
            return 0;
    }
""" + WRITE_INPUT


def _identifier(value: object) -> str:
    """``value`` if it is a C identifier (what a controller's kind and fixed point are), else ``unnamed``: text
    from a controller header never reaches the C source unchecked (a comment's ``*/`` would end it)."""
    return value if isinstance(value, str) and IDENTIFIER.fullmatch(value) else "unnamed"


def c_sources(export: Export, name: str = "compabs_controller") -> tuple[str, str]:
    """The header and the source of the C export (``name.h``, ``name.c``).

    Written from numbers and identifiers only: the grids and tables as numeric literals, the controller's kind
    and fixed point when they are identifiers, ``name`` (a file name, in ``#include``) only as letters, digits,
    ``_``, ``-`` and ``.``.
    """
    if not FILE_NAME.fullmatch(name):
        raise ExportError(f"the C export's base name {name[:80]!r} is not letters, digits, '_', '-' and '.' (it is "
                          "written in an #include line): give another --out")
    if export.rule not in RULES or export.form not in FORMS:
        raise ExportError(f"unknown rule {export.rule!r} or form {export.form!r}")
    g = export.state_grid
    n, m = g.dim, sum(ig.dim for ig in export.input_grids)
    guard = "".join(ch if ch.isalnum() else "_" for ch in name).upper() + "_H"
    s = {k: None if v is None else int(v) for k, v in export.sizes.items() if k != "form"}
    tree = ("no tree (not built: the grid is above the exact tree's cell limit, --form bdd was asked, or it "
            "could not beat the BDD)" if s["tree_nodes"] is None
            else f"tree {s['tree_nodes']} nodes ({s['tree_bytes']} bytes)")
    about = (f"compabs controller export: {_identifier(export.meta.get('kind'))} "
             f"({_identifier(export.meta.get('fixed_point'))}), rule {export.rule}, form {export.form}; "
             f"{s['domain_states']} domain cells, BDD {s['bdd_nodes']} nodes ({s['bdd_bytes']} bytes), {tree}.")
    header = (f"/* {about} */\n#ifndef {guard}\n#define {guard}\n\n#define COMPABS_STATE_DIM {n}\n"
              f"#define COMPABS_INPUT_DIM {m}\n\n"
              "/* Writes the chosen input u[0 .. COMPABS_INPUT_DIM-1] and returns 1 when x[0 .. COMPABS_STATE_DIM-1]\n"
              "   is in the controller's domain; returns 0 (u untouched) otherwise. No allocation, reentrant. */\n"
              "int compabs_control(const double *x, double *u);\n\n#endif\n")
    parts = [f"/* {about} */\n#include <math.h>\n#include <stdint.h>\n\n#include \"{name}.h\"\n\n",
             *grid_parts(g, export.input_grids)]
    if export.form == "bdd":
        t = export.bdd
        parts += [f"static const uint32_t ROOT_DOMAIN = {int(t.domain)}u;\n", _array("OUTPUT", t.outputs, "uint32_t"),
                  _array("WIDTH", export.widths, "int"), _array("BIT_COORD", t.bits[:, 0]),
                  _array("BIT_SHIFT", t.bits[:, 1]), _array("NODE_VAR", t.var), _array("NODE_LOW", t.low),
                  _array("NODE_HIGH", t.high), BDD_EVAL]
    else:
        tr = export.tree
        assert tr is not None
        parts += [_array("FEATURE", tr.feature), _array("THRESHOLD", tr.threshold), _array("LEFT", tr.left),
                  _array("RIGHT", tr.right), _array("LEAF", tr.leaf), _array("CHOICES", export.choices), TREE_EVAL]
    parts.append(CONTROL)
    return header, "".join(parts)


def grid_parts(g: UniformGrid, input_grids: list[UniformGrid]) -> list[str]:
    """The C of the state grid and the quantizer (``NX``, ``quantize``), and of the input grids (``NS``, the
    inputs' points and where each subsystem's input goes): what every C export starts with."""
    points, offset, out, dims = [], [], [], []
    at = pos = 0
    for ig in input_grids:
        offset.append(at)
        out.append(pos)
        dims.append(ig.dim)
        p = ig.all_points()
        points.append(p.ravel())
        at += p.size
        pos += ig.dim
    return [f"#define NX {g.dim}\n#define NS {len(input_grids)}\n",
            f"static const double SNAP_RTOL = {float(SNAP_RTOL).hex()};\n",
            _array("ORIGIN", np.asarray(g.origin, dtype=float)), _array("ETA", np.asarray(g.eta, dtype=float)),
            _array("LB", np.asarray(g.lb, dtype=float)), _array("UB", np.asarray(g.ub, dtype=float)),
            _array("K_LO", g.k_lo, "int64_t"), _array("SHAPE", g.shape, "int64_t"),
            _array("N_INPUTS", [ig.size for ig in input_grids], "int64_t"),
            _array("U_DIM", dims, "int"), _array("U_OUT", out, "int"), _array("U_OFFSET", offset, "int64_t"),
            _array("U_POINTS", np.concatenate(points).astype(float)), QUANTIZE]


def write_c(export: Export, out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``<out>.h`` and ``<out>.c`` (``out`` without suffix; a ``.c`` or ``.h`` suffix is dropped)."""
    return write_sources(out, lambda name: c_sources(export, name))


def write_sources(out: str | os.PathLike[str], sources: Callable[[str], tuple[str, str]]) -> tuple[Path, Path]:
    """Write the header and source ``sources(name)`` gives as ``<out>.h`` and ``<out>.c`` (a ``.c`` or ``.h``
    suffix of ``out`` is dropped; ``name`` is the base name, which the header's guard and include use)."""
    base = Path(out)
    if base.suffix in (".c", ".h"):
        base = base.with_suffix("")
    header, source = sources(base.name)
    h, c = base.with_name(base.name + ".h"), base.with_name(base.name + ".c")
    h.write_text(header)
    c.write_text(source)
    return h, c
