"""Small random networks and an explicit-state game solver: the reference the symbolic synthesis is tested against.

Each random network has 2-3 subsystems with 3-6 states and 2 inputs, and either one internal variable shared
by all subsystems (a random node relation x -> w, sometimes through an intermediate z) or one internal variable
per subsystem (the tanks' structure). :class:`Explicit` enumerates composed states, joint inputs and every
``ŵ ∈ M̂(x̂)``; it shares no code with the symbolic solver beyond the input arrays. The test modules of the
controllable predecessor, its partitioned forms, the quotient, the local games and the fixed points all use it.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.interconnection import NodeRelation
from pipelines.symbolic.counting import enumerate_cells
from pipelines.symbolic.order import SubsystemLayout, tree_owners
from pipelines.symbolic.relations import interconnection_parts, state_set, subsystem_relations
from pipelines.symbolic.symbolic_model import SymbolicModel
from pipelines.synthesis.cpre import ControllablePredecessor

from .strategies import drifting_relation, grid, random_node


@dataclass
class Net:
    layouts: list[SubsystemLayout]
    relations: dict[str, SubsystemRelation]
    w_sizes: list[int]
    nodes: list[NodeRelation]
    shape: tuple[int, ...]  # states per subsystem (all 1-D)
    n_u: tuple[int, ...]


def random_net(rng: np.random.Generator, shared: bool) -> Net:
    N = int(rng.integers(2, 4))
    shape = tuple(int(k) for k in rng.integers(3, 7, size=N))
    n_u = (2,) * N
    nodes: list[NodeRelation] = []
    p_empty = 0.05 if rng.random() < 0.5 else 0.0
    if shared:
        Kw = int(rng.integers(2, 5))
        w_sizes = [Kw]
        reads = [(0,)] * N
        if rng.random() < 0.5:  # through an intermediate variable, as MDec makes them
            Kz = int(rng.integers(2, 4))
            nodes.append(random_node(rng, "z0", Kz, ["x0", "x1"], [shape[0], shape[1]], p_empty))
            nodes.append(random_node(rng, "w0", Kw, ["z0", f"x{N - 1}"], [Kz, shape[N - 1]], p_empty))
        else:
            sup = sorted(rng.choice(N, size=min(N, 2), replace=False).tolist())
            nodes.append(random_node(rng, "w0", Kw, [f"x{i}" for i in sup], [shape[i] for i in sup], p_empty))
    else:
        w_sizes, reads = [], []
        for _ in range(N):
            if rng.random() < 0.15:  # a subsystem that reads nothing
                reads.append(())
                continue
            j = len(w_sizes)
            Kw = int(rng.integers(2, 4))
            w_sizes.append(Kw)
            reads.append((j,))
            sup = sorted(rng.choice(N, size=int(rng.integers(1, 3)), replace=False).tolist())
            nodes.append(random_node(rng, f"w{j}", Kw, [f"x{k}" for k in sup], [shape[k] for k in sup], p_empty))
        if rng.random() < 0.3:  # an internal variable nobody reads: only M̂(x) ≠ ∅ depends on it
            j = len(w_sizes)
            w_sizes.append(2)
            nodes.append(random_node(rng, f"w{j}", 2, ["x0"], [shape[0]], 0.2))
    layouts, relations = [], {}
    for i in range(N):
        # Identical neighbours share a key and one relation (exercises renaming).
        same = i > 0 and shape[i] == shape[i - 1] and reads[i] == reads[i - 1] and rng.random() < 0.4
        key = layouts[-1].key if same else f"k{i}"
        layouts.append(SubsystemLayout(i, (shape[i],), n_u[i], reads[i], key, i))
        if not same:
            n_w = math.prod(w_sizes[j] for j in reads[i]) if reads[i] else 1
            relations[key] = drifting_relation(rng, shape[i], n_u[i], n_w, 0.1)
    return Net(layouts, relations, w_sizes, nodes, shape, n_u)


def ring_net(rng: np.random.Generator) -> Net:
    """A ring of 3 subsystems, each reading the internal variables of both neighbours (the rooms' structure): every
    ``w_j`` a random node of ``x_j`` (sometimes of ``x_j`` and the next state too) read by two subsystems."""
    N = 3
    shape = tuple(int(k) for k in rng.integers(3, 5, size=N))
    n_u = (2,) * N
    p_empty = 0.05 if rng.random() < 0.5 else 0.0
    w_sizes = [int(k) for k in rng.integers(2, 4, size=N)]
    nodes = []
    for j in range(N):
        sup = [j] if rng.random() < 0.7 else sorted({j, (j + 1) % N})
        nodes.append(random_node(rng, f"w{j}", w_sizes[j], [f"x{k}" for k in sup], [shape[k] for k in sup], p_empty))
    reads = [((i - 1) % N, (i + 1) % N) for i in range(N)]
    layouts = [SubsystemLayout(i, (shape[i],), n_u[i], reads[i], f"k{i}", i) for i in range(N)]
    relations = {f"k{i}": drifting_relation(rng, shape[i], n_u[i], w_sizes[reads[i][0]] * w_sizes[reads[i][1]], 0.1)
                 for i in range(N)}
    return Net(layouts, relations, w_sizes, nodes, shape, n_u)


# ============================================================================ the explicit solver
class Explicit:
    """Explicit-state game: every (x̂, û, ŵ ∈ M̂(x̂)) row with its successor box, CPre by box sums."""

    def __init__(self, net: Net) -> None:
        self.net = net
        self.shape = net.shape
        self.nX = math.prod(net.shape)
        self.nU = math.prod(net.n_u)
        self.N = len(net.shape)
        self.states = list(itertools.product(*(range(k) for k in net.shape)))
        self.inputs = list(itertools.product(*(range(k) for k in net.n_u)))
        rows = []  # (x, u, blocked, lo[N], hi[N])
        self.has_w = np.zeros(self.nX, dtype=bool)
        for xf, x in enumerate(self.states):
            W = self._allowed_w(x)
            self.has_w[xf] = len(W) > 0
            for uf, u in enumerate(self.inputs):
                for w in W:
                    blocked, lo, hi = False, [], []
                    for s, lay in enumerate(net.layouts):
                        rel = net.relations[lay.key]
                        wi = np.ravel_multi_index([w[j] for j in lay.reads], [net.w_sizes[j] for j in lay.reads]) \
                            if lay.reads else 0
                        blocked |= bool(rel.blocking[x[s], u[s], wi])
                        lo.append(int(rel.lo[x[s], u[s], wi, 0]))
                        hi.append(int(rel.hi[x[s], u[s], wi, 0]))
                    rows.append((xf, uf, blocked, lo, hi))
        self.rx = np.array([r[0] for r in rows], dtype=np.int64)
        self.ru = np.array([r[1] for r in rows], dtype=np.int64)
        self.blocked = np.array([r[2] for r in rows], dtype=bool)
        self.lo = np.array([r[3] for r in rows], dtype=np.int64).reshape(-1, self.N)
        self.hi = np.array([r[4] for r in rows], dtype=np.int64).reshape(-1, self.N)

    def _allowed_w(self, x: tuple[int, ...]) -> list[tuple[int, ...]]:
        """``M̂(x̂)``: ∃z computed bottom-up over the forest of nodes, then the product over outputs."""
        env: dict[str, set[int]] = {f"x{i}": {v} for i, v in enumerate(x)}
        for node in self.net.nodes:
            cells: set[int] = set()
            for combo in itertools.product(*(sorted(env[n]) for n in node.inputs)):
                cells.update(range(int(node.lo[combo]), int(node.hi[combo]) + 1))
            env[node.output] = cells
        sets = [sorted(env[f"w{j}"]) for j in range(len(self.net.w_sizes))]
        return list(itertools.product(*sets))

    def cpre(self, Z: np.ndarray) -> np.ndarray:
        """bool (nX, nU): M̂(x̂) ≠ ∅ and every row of (x̂, û) is non-blocking with all successors in Z."""
        Zn = Z.reshape(self.shape).astype(np.int64)
        S = np.zeros(tuple(k + 1 for k in self.shape), dtype=np.int64)  # summed-volume table
        S[tuple(slice(1, None) for _ in self.shape)] = Zn
        for a in range(self.N):
            S = np.cumsum(S, axis=a)
        inside = np.zeros(self.rx.size, dtype=np.int64)
        for corner in itertools.product((0, 1), repeat=self.N):
            idx = tuple(np.where(c, self.hi[:, a] + 1, self.lo[:, a]) for a, c in enumerate(corner))
            inside += (-1) ** (self.N - sum(corner)) * S[idx]
        volume = np.prod(self.hi - self.lo + 1, axis=1)
        ok = ~self.blocked & (inside == volume)
        bad = np.zeros((self.nX, self.nU), dtype=bool)
        np.logical_or.at(bad, (self.rx, self.ru), ~ok)
        return ~bad & self.has_w[:, None]

    def pre(self, Z: np.ndarray) -> np.ndarray:
        return self.cpre(Z).any(axis=1)

    # fixed points, written from their definitions
    def safe(self, S):
        Z = S.copy()
        while True:
            Zn = S & self.pre(Z)
            if np.array_equal(Zn, Z):
                return Z
            Z = Zn

    def reach(self, T, A=None):
        keep = np.ones(self.nX, bool) if A is None else ~A
        Z = T & keep
        while True:
            Zn = (T | self.pre(Z)) & keep
            if np.array_equal(Zn, Z):
                return Z
            Z = Zn

    def cobuchi(self, phi, S=None):
        """``μX. νY. (φ ∧ S ∧ Pre(Y)) ∨ (S ∧ Pre(X))`` (``S``: every state unless given)."""
        S = np.ones(self.nX, bool) if S is None else S
        X = np.zeros(self.nX, bool)
        while True:
            preX = self.pre(X) & S
            Y = S.copy()
            while True:
                Yn = (phi & S & self.pre(Y)) | preX
                if np.array_equal(Yn, Y):
                    break
                Y = Yn
            if np.array_equal(Y, X):
                return X
            X = Y

    # closed loops
    def successors(self, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closed-loop graph under a controller C (nX, nU): adjacency (nX, nX) and whether some allowed row
        blocks."""
        adj = np.zeros((self.nX, self.nX), dtype=bool)
        blocks = np.zeros(self.nX, dtype=bool)
        for r in np.flatnonzero(C[self.rx, self.ru]):
            x = self.rx[r]
            if self.blocked[r]:
                blocks[x] = True
                continue
            for succ in itertools.product(*(range(a, b + 1) for a, b in zip(self.lo[r], self.hi[r]))):
                adj[x, np.ravel_multi_index(succ, self.shape)] = True
        return adj, blocks


def controller_matrix(model: SymbolicModel, C, ex: Explicit) -> np.ndarray:
    rows = enumerate_cells(model, C, model.x_digits() + model.u_digits())
    out = np.zeros((ex.nX, ex.nU), dtype=bool)
    if rows.size:
        xf = np.ravel_multi_index(tuple(rows[:, : ex.N].T), ex.shape)
        uf = np.ravel_multi_index(tuple(rows[:, ex.N :].T), ex.net.n_u)
        out[xf, uf] = True
    return out


def states_vector(model: SymbolicModel, f, ex: Explicit) -> np.ndarray:
    rows = enumerate_cells(model, f, model.x_digits())
    out = np.zeros(ex.nX, dtype=bool)
    if rows.size:
        out[np.ravel_multi_index(tuple(rows.T), ex.shape)] = True
    return out


def build(net: Net, order: str, method: str = "auto", chain_order: str = "greedy") -> ControllablePredecessor:
    z_sizes = {n.output: n.output_grid.size for n in net.nodes if n.output.startswith("z")}
    m = SymbolicModel(net.layouts, net.w_sizes, z_sizes, z_owner=tree_owners(net.nodes), order=order)
    T, NB = subsystem_relations(m, net.relations)
    return ControllablePredecessor(m, T, NB, interconnection_parts(m, net.nodes), method, chain_order)


def random_set(rng, ex: Explicit, p: float) -> np.ndarray:
    return rng.random(ex.nX) < p


# ============================================================================ checks
def check_progress(ex: Explicit, C: np.ndarray, domain: np.ndarray, T: np.ndarray) -> None:
    """From every domain state, every run under the controller reaches T within |domain| steps."""
    assert np.all(C.any(axis=1)[domain & ~T]), "a domain state without input"
    assert not np.any(C[~domain]), "controller outside the domain"
    adj, blocks = ex.successors(C & ~T[:, None])
    assert not np.any(blocks[domain & ~T]), "an allowed input blocks"
    done = T & domain
    for _ in range(int(domain.sum()) + 1):
        ready = domain & ~done & ~np.any(adj & ~done[None, :], axis=1)
        if not ready.any():
            break
        done |= ready
    assert np.array_equal(done, domain), "some run does not reach the target"


def check_stay(ex: Explicit, C: np.ndarray, domain: np.ndarray, phi: np.ndarray) -> None:
    """Reach-and-stay controller: the domain is closed, nothing blocks, no state outside φ is on a cycle."""
    assert np.all(C.any(axis=1)[domain])
    adj, blocks = ex.successors(C)
    assert not np.any(blocks[domain])
    assert not np.any(adj[domain][:, ~domain]), "a successor leaves the domain"
    reach = adj.copy()  # transitive closure (Warshall), small graphs only
    for k in range(ex.nX):
        reach |= reach[:, [k]] & reach[[k], :]
    on_cycle = np.diag(reach)
    assert not np.any(on_cycle & domain & ~phi), "a run can visit a state outside φ forever"


def layered_matrix(ctrl, ex: Explicit) -> np.ndarray:
    """Inputs a (layered) controller allows at every cell, through ``input_indices`` one cell at a time."""
    out = np.zeros((ex.nX, ex.nU), dtype=bool)
    for xf, x in enumerate(ex.states):
        rows = ctrl.input_indices(np.array(x))
        if rows.size:
            out[xf, np.ravel_multi_index(tuple(rows.T), ex.net.n_u)] = True
    return out


def coupled_net(rng: np.random.Generator, shared: bool) -> Net:
    """4-6 subsystems, each coupled to one or two others through an internal variable (a chain, a tree, a ring):
    groups of at most half the network exist. ``shared``: some internal variables are read by two subsystems."""
    N = int(rng.integers(4, 7))
    shape = tuple(int(k) for k in rng.integers(3, 5, size=N))
    n_u = tuple(2 if i in rng.choice(N, size=2, replace=False) else 1 for i in range(N))  # keeps Explicit small
    nodes, w_sizes, reads = [], [], []
    for i in range(N):
        if i == 0 and rng.random() < 0.5:  # a source that reads nothing
            reads.append(())
            continue
        if shared and i > 0 and reads[i - 1] and rng.random() < 0.4:  # read the same variable as the previous one
            reads.append(reads[i - 1])
            continue
        j = len(w_sizes)
        Kw = int(rng.integers(2, 4))
        w_sizes.append(Kw)
        reads.append((j,))
        others = [k for k in range(N) if k != i]
        sup = sorted(rng.choice(others, size=int(rng.integers(1, 3)), replace=False).tolist())
        nodes.append(random_node(rng, f"w{j}", Kw, [f"x{k}" for k in sup], [shape[k] for k in sup], 0.0))
    layouts, relations = [], {}
    for i in range(N):
        key = f"k{i}"
        layouts.append(SubsystemLayout(i, (shape[i],), n_u[i], reads[i], key, i))
        n_w = math.prod(w_sizes[j] for j in reads[i]) if reads[i] else 1
        relations[key] = drifting_relation(rng, shape[i], n_u[i], n_w, 0.03)
    return Net(layouts, relations, w_sizes, nodes, shape, n_u)


# ============================================================================ hand-made integrators
def integrator(K: int, steps: tuple[int, ...]) -> tuple[SubsystemRelation, int]:
    """``x' = x + u`` on cells ``0..K-1``, input ``j`` moving by ``steps[j]`` cells; leaving the grid blocks."""
    x = np.arange(K)[:, None] + np.asarray(steps)[None, :]
    blocking = (x < 0) | (x >= K)
    lo = np.where(blocking, 0, x)[:, :, None, None].astype(np.int32)
    hi = np.where(blocking, -1, x)[:, :, None, None].astype(np.int32)
    return SubsystemRelation("test", lo, hi, blocking[:, :, None], 1.0, 0.0), len(steps)


def integrators(shape: tuple[int, ...], steps: tuple[int, ...] = (-1, 0, 1)) -> Net:
    """Independent integrators, one per coordinate; one internal variable nobody reads (the interconnection
    of a network without coupling: ``M̂(x̂)`` is never empty)."""
    layouts, relations = [], {}
    for i, K in enumerate(shape):
        rel, n_u = integrator(K, steps)
        relations[f"k{i}"] = rel
        layouts.append(SubsystemLayout(i, (K,), n_u, (), f"k{i}", i))
    node = NodeRelation("w0", grid(1), ("x0",), (grid(shape[0]),), None, np.zeros(shape[0], np.int32),
                        np.zeros(shape[0], np.int32), 0.0)
    return Net(layouts, relations, [1], [node], shape, (len(steps),) * len(shape))


def ring_integrators(N: int = 3, K: int = 9) -> Net:
    """A ring of ``N`` integrators ``x' = x + u`` (``u`` in -2..2) on cells ``0..K-1``, each reading both
    neighbours' cells (``w_j = x_j``): a neighbour below ``K // 3`` may pull it one cell down, one above
    ``2K // 3`` one cell up; leaving the grid blocks. Holding two cells needs calm neighbours, holding three does
    not: the contracts' chain has two levels (the rooms' structure, small enough for :class:`Explicit`)."""
    cold, hot = K // 3, 2 * K // 3
    steps = np.arange(-2, 3)
    w = np.arange(K)
    wl, wr = np.meshgrid(w, w, indexing="ij")
    down = ((wl < cold) | (wr < cold)).reshape(-1).astype(int)
    up = ((wl > hot) | (wr > hot)).reshape(-1).astype(int)
    x = np.arange(K)[:, None, None] + steps[None, :, None]
    lo, hi = x - down[None, None, :], x + up[None, None, :]
    blocking = (lo < 0) | (hi >= K)
    lo, hi = np.where(blocking, 0, lo), np.where(blocking, -1, hi)
    rel = SubsystemRelation("test", lo[..., None].astype(np.int32), hi[..., None].astype(np.int32), blocking, 1, 1)
    nodes = [NodeRelation(f"w{j}", grid(K), (f"x{j}",), (grid(K),), None, np.arange(K, dtype=np.int32),
                          np.arange(K, dtype=np.int32), 0.0) for j in range(N)]
    layouts = [SubsystemLayout(i, (K,), len(steps), ((i - 1) % N, (i + 1) % N), "room", i) for i in range(N)]
    return Net(layouts, {"room": rel}, [K] * N, nodes, (K,) * N, (len(steps),) * N)


def cells(game, *xs: int):
    return state_set(game.model, np.array(xs).reshape(-1, 1))


def integrator_spec(specification: dict, **options) -> dict:
    """Two concrete integrators ``x' = x + u`` on [0, 9] (cells of width 1), inputs -2..2, no coupling (the map's
    output is read by nobody). The abstraction moves ``u`` cells with one cell of slack either way."""
    sub = {"name": "cart", "replicate": 2, "state": {"lb": 0, "ub": 9, "eta": 1},
           "input": {"lb": -2, "ub": 2, "eta": 1}, "dynamics": "x[0] + u[0]", "lipschitz": {"x": 1.0},
           "samples": 4, "growth_bound": "hull"}
    return {"name": "carts", "subsystems": [sub],
            "interconnection": {"map": "[x[0]]", "internal": {"lb": 0, "ub": 9, "eta": 1}, "error": "linear"},
            "specification": specification,
            "options": {"audit_transitions": 0, "closed_loop_runs": 30, "synthesis_processes": 1, **options}}
