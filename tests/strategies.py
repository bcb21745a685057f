"""Random systems, relations and networks the tests share: hypothesis strategies for subsystem specs with
Lipschitz constants in closed form, and numpy builders of relations and interconnection nodes."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import strategies as st

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.grid import UniformGrid
from pipelines.interconnection import NodeRelation


# ============================================================================ relations and nodes
def grid(k: int) -> UniformGrid:
    """A 1-D grid with ``k`` cells (only its size matters to the symbolic layer)."""
    return UniformGrid(origin=(0.0,), eta=(1.0,), k_lo=(0,), k_hi=(k - 1,), lb=(0.0,), ub=(float(k - 1),))


def random_relation(rng, state_shape, n_u, n_w, p_block=0.2) -> SubsystemRelation:
    n_x, n = math.prod(state_shape), len(state_shape)
    size = np.asarray(state_shape)
    lo = rng.integers(0, size, size=(n_x, n_u, n_w, n))
    hi = np.minimum(lo + rng.integers(0, 3, size=lo.shape), size - 1)
    blocking = rng.random((n_x, n_u, n_w)) < p_block
    lo[blocking], hi[blocking] = 0, -1
    return SubsystemRelation("test", lo.astype(np.int32), hi.astype(np.int32), blocking, 1.0, 1.0)


def drifting_relation(rng: np.random.Generator, n_x: int, n_u: int, n_w: int, p_block: float) -> SubsystemRelation:
    """A 1-D subsystem relation whose successors lie near the state (drift of -1..1 cells, width 1-2: safe sets are
    then often non-empty), each triple blocking with probability ``p_block``."""
    here = np.arange(n_x).reshape(-1, 1, 1, 1)
    lo = np.clip(here + rng.integers(-1, 2, size=(n_x, n_u, n_w, 1)), 0, n_x - 1)
    hi = np.minimum(lo + rng.integers(0, 2, size=lo.shape), n_x - 1)
    blocking = rng.random((n_x, n_u, n_w)) < p_block
    lo[blocking], hi[blocking] = 0, -1
    return SubsystemRelation("test", lo.astype(np.int32), hi.astype(np.int32), blocking, 1, 1)


def random_node(rng, output, out_size, inputs, in_sizes, p_empty=0.1) -> NodeRelation:
    """A node relation over the given input grids: per input cell an output range of one or two cells, empty
    (``lo > hi``) with probability ``p_empty``."""
    shape = tuple(in_sizes)
    lo = rng.integers(0, out_size, size=shape)
    hi = np.minimum(lo + rng.integers(0, 2, size=shape), out_size - 1)
    empty = rng.random(shape) < p_empty
    lo, hi = np.where(empty, 1, lo), np.where(empty, 0, hi)
    return NodeRelation(output, grid(out_size), tuple(inputs), tuple(grid(k) for k in in_sizes), None,
                        lo.astype(np.int32), hi.astype(np.int32), 0.0)


# ============================================================================ subsystem specs (hypothesis)
def _expr(n, m, p, centre, A, Bm, Cm, nl, s):
    rows = []
    for i in range(n):
        terms = [str(centre[i])] + [f"{A[i][j]} * (x[{j}] - {centre[j]})" for j in range(n)]
        pert = [f"{Bm[i][j]} * u[{j}]" for j in range(m)] + [f"{Cm[i][j]} * w[{j}]" for j in range(p)]
        a, c, k = nl[i]
        pert.append(f"{a} * sin({c} * x[{(i + 1) % n}])")
        if p:
            pert.append(f"{k} * tanh(w[{i % p}])")
        rows.append(" + ".join(terms) + f" + {s} * (" + " + ".join(pert) + ")")
    return "[" + ", ".join(rows) + "]"


@st.composite
def systems(draw, n):
    """``x' = c + A (x - c) + s (B u + C w + a sin(c' x) + k tanh(w))`` on a box around ``c`` with ``||A|| <= 0.6``
    and perturbations scaled to the cells (``s``), so that most triples are not blocking; constants in closed
    form (infinity norm: row sums of the Jacobian's bounds)."""
    m = draw(st.integers(1, 2))
    p = draw(st.integers(0, 2))
    small = st.floats(-1.0, 1.0, allow_nan=False).map(lambda v: round(v, 3))
    A = [[round(draw(small) * 0.6 / n, 3) for _ in range(n)] for _ in range(n)]
    Bm = [[draw(small) for _ in range(m)] for _ in range(n)]
    Cm = [[draw(small) for _ in range(p)] for _ in range(n)]
    nonlinear = draw(st.booleans())
    nl = [(draw(small) if nonlinear else 0.0, draw(st.floats(0.2, 2.5).map(lambda v: round(v, 3))),
           draw(small) if nonlinear else 0.0) for _ in range(n)]
    per = draw(st.lists(st.integers(2, 5), min_size=n, max_size=n))  # cells per dimension (about)
    eta = [round(draw(st.floats(0.2, 1.5)), 3) for _ in range(n)]
    centre = [round(draw(st.floats(-3, 3)), 2) for _ in range(n)]
    half = [round(eta[i] * per[i] * draw(st.floats(0.3, 0.5)), 3) for i in range(n)]
    s = round(0.1 * min(eta), 4)
    L_x = max(sum(abs(v) for v in A[i]) + s * abs(nl[i][0] * nl[i][1]) for i in range(n))
    L_w = max(s * (sum(abs(v) for v in Cm[i]) + abs(nl[i][2])) for i in range(n)) if p else 0.0
    spec = {
        "name": "s", "state": {"lb": [centre[i] - half[i] for i in range(n)],
                               "ub": [centre[i] + half[i] for i in range(n)], "eta": eta},
        "input": {"lb": [-0.5] * m, "ub": [0.5] * m, "eta": [draw(st.sampled_from([0.5, 1.0]))] * m},
        "dynamics": _expr(n, m, p, centre, A, Bm, Cm, nl, s),
        # a margin on the closed-form constants, as a spec would give them
        "lipschitz": {"x": round(L_x * 1.01 + 1e-3, 6), "w": round(L_w * 1.01 + 1e-3, 6)},
        "samples": draw(st.sampled_from([4, 9, 16, 25, 36] if n == 2 else [8, 12, 27])),
    }
    internal = [{"lb": -1.0, "ub": round(draw(st.floats(-0.5, 1.5)), 2),
                 "eta": round(draw(st.floats(0.3, 1.0)), 2)} for _ in range(max(p, 1))]
    if p:
        spec["reads"] = list(range(p))
    return spec, internal


r3 = st.floats(-1.0, 1.0, allow_nan=False).map(lambda v: round(v, 3))


def _fmt(v: float) -> str:
    return repr(round(float(v), 6))


@st.composite
def anisotropic(draw, n: int):
    """``(subsystem spec, internal grids, entries of L_x, entries of L_w)`` of an anisotropic n-D map.

    kinds: ``rotation`` (a rotation by a state-dependent angle, scaled), ``shear`` (``x_i += k x_j`` with a large
    ``k``), ``heading`` (the last coordinate is a heading that moves every other coordinate by ``a cos``/``a sin``
    and is moved by nothing but the input)."""
    kind = draw(st.sampled_from(["rotation", "shear", "heading"]))
    p = draw(st.integers(0, 1))
    eta = [round(draw(st.floats(0.2, 0.6)), 3) for _ in range(n)]
    per = [draw(st.integers(3, 5 if n <= 3 else 3)) for _ in range(n)]
    half = [round(eta[i] * per[i] / 2, 4) for i in range(n)]
    rows: list[str] = []
    Lx = np.zeros((n, n))
    if kind == "rotation":
        s = round(draw(st.floats(0.3, 0.9)), 3)
        t = round(draw(st.floats(0.1, 1.4)), 3)  # angle of the rotation of the first two coordinates
        c, si = np.cos(t), np.sin(t)
        rows.append(f"{s} * ({_fmt(c)} * x[0] - {_fmt(si)} * x[1])")
        rows.append(f"{s} * ({_fmt(si)} * x[0] + {_fmt(c)} * x[1])")
        Lx[0, :2] = s * abs(c), s * abs(si)
        Lx[1, :2] = s * abs(si), s * abs(c)
        for i in range(2, n):
            rows.append(f"0.5 * x[{i}] + 0.2 * sin(x[{i - 1}])")
            Lx[i, i], Lx[i, i - 1] = 0.5, 0.2
    elif kind == "shear":
        k = round(draw(st.floats(1.5, 4.0)), 3) * draw(st.sampled_from([-1, 1]))
        j = draw(st.integers(1, n - 1))
        for i in range(n):
            if i == 0:
                rows.append(f"x[0] + {k} * x[{j}]")
                Lx[0, 0], Lx[0, j] = 1.0, abs(k)
            else:
                rows.append(f"x[{i}]")
                Lx[i, i] = 1.0
    else:
        a = round(draw(st.floats(0.5, 3.0)), 3)
        h = n - 1
        for i in range(h):
            trig = "cos" if i % 2 == 0 else "sin"
            rows.append(f"x[{i}] + {a} * {trig}(x[{h}])")
            Lx[i, i], Lx[i, h] = 1.0, a
        rows.append(f"x[{h}]")
        Lx[h, h] = 1.0
    Lw = np.zeros((n, p))
    if p:
        q = round(draw(st.floats(0.1, 1.0)), 3)
        i = draw(st.integers(0, n - 1))
        rows[i] += f" + {q} * tanh(w[0])"
        Lw[i, 0] = q
    m = draw(st.integers(1, 2))
    bu = [draw(r3) for _ in range(m)]
    for i in range(n):
        rows[i] += f" + {round(0.2 * min(eta), 4)} * u[{i % m}] * {bu[i % m]}"
    spec = {
        "name": "s", "replicate": 1,
        "state": {"lb": [-v for v in half], "ub": half, "eta": eta},
        "input": {"lb": [-1] * m, "ub": [1] * m, "eta": [1] * m},
        "dynamics": "[" + ", ".join(rows) + "]",
        # a margin on the closed-form entries, as a spec would give them
        "lipschitz": {"x": np.round(Lx * 1.01 + 1e-3, 6).tolist(), "w": np.round(Lw * 1.01 + 1e-3, 6).tolist()},
        "samples": draw(st.sampled_from([2**n, 3**n] if n <= 3 else [16])),
    }
    if p:
        spec["reads"] = [0]
    internal = {"lb": -1.0, "ub": 1.0, "eta": round(draw(st.floats(0.4, 1.0)), 2)}
    return spec, internal, kind


coef = st.floats(-1.5, 1.5, allow_nan=False).map(lambda v: round(v, 3))


@st.composite
def scalar_systems(draw):
    """f(x, u, w) = a x + b sin(c x) + d w + k tanh(w) + u on random grids; L_x = |a| + |b c|, L_w = |d| + |k|."""
    a, b, d, k = draw(coef), draw(coef), draw(coef), draw(coef)
    c = draw(st.floats(0.1, 3.0).map(lambda v: round(v, 3)))
    lb = round(draw(st.floats(-5, 5)), 2)
    width = round(draw(st.floats(0.5, 12)), 2)
    eta = round(draw(st.floats(0.2, 3.0)), 3)
    wlb = round(draw(st.floats(-3, 3)), 2)
    wwidth = round(draw(st.floats(0.0, 6)), 2)
    weta = round(draw(st.floats(0.2, 3.0)), 3)
    uub = round(draw(st.floats(0.0, 2.0)), 2)
    return {
        "dynamics": f"{a} * x[0] + {b} * sin({c} * x[0]) + {d} * w[0] + {k} * tanh(w[0]) + u[0]",
        "L_x": abs(a) + abs(b * c),
        "L_w": abs(d) + abs(k),
        "state": {"lb": lb, "ub": lb + width, "eta": eta},
        "internal": {"lb": wlb, "ub": wlb + wwidth, "eta": weta},
        "input": {"lb": -uub, "ub": uub, "eta": max(uub, 0.5)},
        "samples": draw(st.integers(1, 60)),
        "method": draw(st.sampled_from(["lipschitz", "scp", "hull"])),
        "objective": draw(st.sampled_from(["paper", "radius"])),
    }
