"""A controller with memory's export (:mod:`.memory`) as C99: a header and a source defining

* ``int compabs_step(const double *x, int q, double *u, int *q_next)``: reads the letter of ``x`` (bit ``i`` set
  iff ``x`` lies in one of atom ``i``'s closed boxes), moves the automaton from ``q`` on it and writes the new
  state to ``q_next``; then returns 1 and writes the input of that state's controller at ``x`` to ``u`` when
  ``x``'s cell is in its domain, 0 otherwise (``u`` untouched). A run starts with ``q =
  COMPABS_INITIAL_STATE`` and passes each ``q_next`` to the next call; it has met the formula once
  ``compabs_accepting(q)``. A ``q`` that is no automaton state returns 0 and writes nothing.
* ``int compabs_letter(const double *x)``, ``int compabs_accepting(int q)``.

The quantizer and the BDD walk are the C export's (:mod:`.c`), the state boxes' tests compare as
:func:`~pipelines.temporal.labels.letters_at` does (a NaN lies in no box). Written from numbers and identifiers
only: atom names reach a comment only when they are identifiers, nothing else of the header or spec is written.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipelines.export.c import BDD_WALK, FILE_NAME, WRITE_INPUT, _array, _identifier, grid_parts, write_sources
from pipelines.export.memory import ProductExport
from pipelines.export.table import ExportError

STEP = """
int compabs_letter(const double *x)
{
    int letter = 0;
    for (int b = 0; b < N_BOXES; ++b) {
        int inside = 1;
        for (int i = 0; i < NX; ++i) {
            if (!(x[i] >= BOX_LB[b * NX + i] && x[i] <= BOX_UB[b * NX + i])) {
                inside = 0;
                break;
            }
        }
        if (inside)
            letter |= 1 << BOX_ATOM[b];
    }
    return letter;
}

int compabs_accepting(int q)
{
    return q >= 0 && q < NQ && ACCEPTING[q];
}

int compabs_step(const double *x, int q, double *u, int *q_next)
{
    int64_t idx[NX];
    int64_t code[NS];
    if (q < 0 || q >= NQ)
        return 0;
    int next = (int)DELTA[q * N_LETTERS + compabs_letter(x)];
    *q_next = next;
    if (!quantize(x, idx) || !evaluate(ROOT_DOMAIN[next], idx))
        return 0;
    int c = 0;
    for (int s = 0; s < NS; ++s) {
        code[s] = 0;
        for (int k = 0; k < WIDTH[s]; ++k)
            code[s] = (code[s] << 1) | evaluate(OUTPUT[next * N_OUTPUTS + c++], idx);
        if (code[s] < 0 || code[s] >= N_INPUTS[s])
            return 0;
    }
""" + WRITE_INPUT


def product_c_sources(export: ProductExport, name: str = "compabs_controller") -> tuple[str, str]:
    """The header and the source of a controller with memory's C export (``name.h``, ``name.c``)."""
    if not FILE_NAME.fullmatch(name):
        raise ExportError(f"the C export's base name {name[:80]!r} is not letters, digits, '_', '-' and '.' (it is "
                          "written in an #include line): give another --out")
    g, a, t = export.state_grid, export.automaton, export.table
    n, m = g.dim, sum(ig.dim for ig in export.input_grids)
    guard = "".join(ch if ch.isalnum() else "_" for ch in name).upper() + "_H"
    atoms = ", ".join(f"bit {i}: {_identifier(atom)}" for i, atom in enumerate(a.atoms))
    about = (f"compabs controller export with memory: {_identifier(export.meta.get('kind'))}, rule {export.rule}, "
             f"form bdd; automaton {a.n_states} states ({int(a.accepting.sum())} accepting) over {len(a.atoms)} "
             f"atoms ({atoms}); BDD {t.nodes} nodes.")
    header = (f"/* {about} */\n#ifndef {guard}\n#define {guard}\n\n#define COMPABS_STATE_DIM {n}\n"
              f"#define COMPABS_INPUT_DIM {m}\n#define COMPABS_AUTOMATON_STATES {a.n_states}\n"
              f"#define COMPABS_INITIAL_STATE {a.initial}\n#define COMPABS_ATOMS {len(a.atoms)}\n\n"
              "/* Moves the automaton from state q on the letter of x[0 .. COMPABS_STATE_DIM-1] and writes the new\n"
              "   state to *q_next; returns 1 and writes the input of that state's controller to\n"
              "   u[0 .. COMPABS_INPUT_DIM-1] when x is in its domain, 0 (u untouched) otherwise. Start a run with\n"
              "   q = COMPABS_INITIAL_STATE and pass *q_next to the next call; the formula holds on the run so far\n"
              "   once compabs_accepting(q). A q outside 0 .. COMPABS_AUTOMATON_STATES-1 returns 0, writing\n"
              "   nothing. No allocation, reentrant. */\n"
              "int compabs_step(const double *x, int q, double *u, int *q_next);\n\n"
              "/* The letter of x: bit i set iff x lies in one of atom i's closed boxes. */\n"
              "int compabs_letter(const double *x);\n\n"
              "/* 1 if q is an accepting automaton state. */\nint compabs_accepting(int q);\n\n#endif\n")
    boxes = [(i, lb, ub) for i, per_atom in enumerate(export.regions) for lb, ub in per_atom]
    lbs = np.asarray([lb for _, lb, _ in boxes], dtype=float).reshape(-1) if boxes else np.zeros(n)
    ubs = np.asarray([ub for _, _, ub in boxes], dtype=float).reshape(-1) if boxes else np.zeros(n)
    parts = [f"/* {about} */\n#include <math.h>\n#include <stdint.h>\n\n#include \"{name}.h\"\n\n",
             *grid_parts(g, export.input_grids),
             f"#define NQ {a.n_states}\n#define N_LETTERS {a.n_letters}\n#define N_BOXES {len(boxes)}\n"
             f"#define N_OUTPUTS {export.outputs.shape[1]}\n",
             _array("BOX_LB", lbs), _array("BOX_UB", ubs), _array("BOX_ATOM", [i for i, _, _ in boxes], "int"),
             _array("DELTA", a.delta), _array("ACCEPTING", a.accepting.astype(np.int64), "uint8_t"),
             _array("ROOT_DOMAIN", export.domains, "uint32_t"), _array("OUTPUT", export.outputs, "uint32_t"),
             _array("WIDTH", export.widths, "int"), _array("BIT_COORD", t.bits[:, 0]),
             _array("BIT_SHIFT", t.bits[:, 1]), _array("NODE_VAR", t.var), _array("NODE_LOW", t.low),
             _array("NODE_HIGH", t.high), BDD_WALK, STEP]
    return header, "".join(parts)


def write_product_c(export: ProductExport, out: str | os.PathLike[str]) -> tuple[Path, Path]:
    """Write ``<out>.h`` and ``<out>.c`` (a ``.c`` or ``.h`` suffix of ``out`` is dropped)."""
    return write_sources(out, lambda name: product_c_sources(export, name))
