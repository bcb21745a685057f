"""oxidd beside CUDD: a second BDD engine, for the synthesis's heaviest step on several threads (issue 49).

``oxidd`` (Rust, PyPI) builds BDDs with complement edges as CUDD does, and runs its apply, its relational product
(``apply_exists``) and its substitution on several threads. :class:`OxiddManager` is an oxidd manager with named
variables declared in a given level order, never reordered, and the few operations a controllable predecessor is
made of. :class:`OxiddMirror` is one over the variables of a :class:`~.symbolic_model.SymbolicModel`, in the
model's level order, with functions crossing between the two managers (:meth:`OxiddMirror.put`,
:meth:`OxiddMirror.get`): the fixed points stay in CUDD, and only their ``∃u.CPre`` runs in oxidd
(:mod:`pipelines.synthesis.engine_cpre`).

Functions cross as DDDMP text, which both libraries write and read natively. oxidd reads CUDD's files as they are;
CUDD's reader trusts its input and crashes on oxidd's (``.varinfo 4``, node lines without names, a ``.rootnames``
line), so :func:`cudd_dddmp` rewrites them into the form CUDD writes (:func:`~.files.check_dddmp` accepts it):
the same nodes, ids and complemented edges, each node line naming its variable.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numba
import numpy as np

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.symbolic.symbolic_model import Function, SymbolicModel

__all__ = ["OXIDD_CACHE", "OXIDD_NODES", "OxiddManager", "OxiddMirror", "cudd_dddmp", "oxidd_available"]

#: Largest node count an oxidd manager may reach (its index-based manager's limit for complement edges is 2^31).
#: Reserved, not allocated: the pages are touched as nodes are made.
OXIDD_NODES = 1 << 28
#: Entries of oxidd's apply cache, allocated at once (about 20 bytes each). CUDD grows its cache up to 2^25 entries
#: (:data:`~.symbolic_model.MAX_CACHE_ENTRIES`) while its hit rate is high; oxidd's is fixed. On consensus N = 8
#: (two threads) 2^20 entries cost the fixed point 1.2x the time of 2^22 and 2^24 0.92x: its last step, on an
#: iterate a little larger than the one before, finds the earlier step's products there (1.4 s against 4.3 s).
OXIDD_CACHE = 1 << 24


def oxidd_available() -> bool:
    """Whether ``oxidd`` can be imported (a dependency; without it every call runs in CUDD)."""
    try:
        import oxidd  # noqa: F401
    except ImportError:
        return False
    return True


class OxiddManager:
    """An oxidd manager over ``variables`` (declared in this level order), plain BDDs (``kind='bdd'``) or with
    complement edges (``'bcdd'``, as CUDD's), its apply on ``threads`` threads; ``x_bits`` and ``xn_bits`` pair the
    current- and next-state bits for :meth:`to_next`."""

    def __init__(self, variables: Sequence[str], x_bits: Sequence[str], xn_bits: Sequence[str], kind: str = "bcdd",
                 threads: int = 1, nodes: int = OXIDD_NODES, cache: int = OXIDD_CACHE) -> None:
        factory: Any  # the two kinds share their interface, not a base class
        if kind == "bdd":
            from oxidd.bdd import BDDManager

            factory = BDDManager
        elif kind == "bcdd":
            from oxidd.bcdd import BCDDManager

            factory = BCDDManager
        else:
            raise ValueError(f"oxidd kind must be 'bdd' or 'bcdd', got {kind!r}")
        self.kind, self.threads = kind, int(threads)
        self.variables = list(variables)
        self.manager = factory(int(nodes), int(cache), int(threads))
        self.manager.add_named_vars(self.variables)
        self.false, self.true = self.manager.false(), self.manager.true()
        self._cubes: dict[tuple[str, ...], Any] = {}
        self._next = self.renaming(zip(x_bits, xn_bits), both_ways=False)

    def _index(self, name: str) -> int:
        """The manager's number of the variable ``name``."""
        v = self.manager.name_to_var(name)
        if v is None:
            raise ValueError(f"no variable {name!r} in this manager")
        return int(v)

    def cube(self, bits: Sequence[str]) -> Any:
        """The conjunction of ``bits``' variables (how oxidd names a set of variables to quantify), made once."""
        key = tuple(bits)
        c = self._cubes.get(key)
        if c is None:
            c = self.true
            for b in reversed(key):
                c &= self.manager.var(b)
            self._cubes[key] = c
        return c

    def and_exists(self, f: Any, g: Any, bits: Sequence[str]) -> Any:
        """``∃bits. f ∧ g`` in one call (oxidd's ``apply_exists``, CUDD's ``Cudd_bddAndAbstract``)."""
        from oxidd.util import BooleanOperator

        return f.apply_exists(BooleanOperator.AND, g, self.cube(bits))

    def renaming(self, pairs: Iterable[tuple[str, str]], both_ways: bool = True) -> Any:
        """The simultaneous substitution of each pair's second variable for its first (and, ``both_ways``, the first
        for the second: an exchange), for :meth:`substitute`."""
        subs = []
        for a, b in pairs:
            subs.append((self._index(a), self.manager.var(b)))
            if both_ways:
                subs.append((self._index(b), self.manager.var(a)))
        return self.true.make_substitution(subs)

    @staticmethod
    def substitute(f: Any, renaming: Any) -> Any:
        return f.substitute(renaming)

    def to_next(self, f: Any) -> Any:
        """``f(x) -> f(x')`` (``f`` reads no next-state bit)."""
        return f.substitute(self._next)

    def nodes(self, f: Any) -> int:
        return int(f.node_count())

    def write(self, f: Any, path: str | Path) -> None:
        """``f`` as oxidd's DDDMP text (:func:`cudd_dddmp` turns it into CUDD's)."""
        self.manager.export_dddmp_with_names(str(path), [(f, "root")], ascii=True)

    def read(self, path: str | Path) -> Any:
        """The one root of a DDDMP file over these variables (by name; CUDD's files, complement edges included)."""
        from oxidd.util import DDDMPFile

        with DDDMPFile(str(path)) as file:
            names = file.var_names
            if names is None:
                raise ValueError(f"{path}: the DDDMP file names no variables")
            support = [self._index(names[i]) for i in file.support_vars]
            (root,) = self.manager.import_dddmp(file, support)
        return root


class OxiddMirror(OxiddManager):
    """An :class:`OxiddManager` over ``model``'s variables in its level order, BDDs with complement edges, and the
    crossing of functions between the two (module docstring)."""

    def __init__(self, model: SymbolicModel, threads: int = 1, nodes: int = OXIDD_NODES,
                 cache: int = OXIDD_CACHE) -> None:
        super().__init__(model.variables, model.x_bits, model.xn_bits, "bcdd", threads, nodes, cache)
        self.model = model
        self._dir = tempfile.TemporaryDirectory(prefix="compabs-oxidd-")
        self._path = os.path.join(self._dir.name, "f.dddmp")

    def put(self, f: Function) -> Any:
        """``f`` of the CUDD model, in oxidd."""
        from pipelines.symbolic.files import write_root

        bdd = self.model.bdd
        if f == bdd.false:
            return self.false
        if f == bdd.true:
            return self.true
        write_root(self.model, self._path, f, "handing a BDD to oxidd")
        return self.read(self._path)

    def get(self, g: Any) -> Function:
        """``g`` of oxidd, in the CUDD model."""
        from pipelines.symbolic.files import read_root

        if g == self.false:
            return self.model.bdd.false
        if g == self.true:
            return self.model.bdd.true
        self.write(g, self._path)
        with open(self._path, "rb") as fh:
            text = cudd_dddmp(fh.read())
        with open(self._path, "wb") as fh:
            fh.write(text)
        return read_root(self.model, self._path, "reading a BDD from oxidd")

    def close(self) -> None:
        """Remove the transfer directory (the manager goes with the last reference to it)."""
        self._dir.cleanup()


def cudd_dddmp(data: bytes) -> bytes:
    """oxidd's one-root DDDMP text (``.varinfo 4``, node lines ``id index then else``, a ``.rootnames`` line) as CUDD
    writes it (``.varinfo 3``, node lines ``id name index then else``, the terminal ``1 T 1 0 0``): the nodes,
    ids and edges unchanged.

    Raises
    ------
    ValueError
        ``data`` is not such a file.
    """
    head, sep, rest = data.partition(b"\n.nodes\n")
    body, end, _ = rest.rpartition(b".end")
    if not sep or not end:
        raise ValueError("not a DDDMP text file: no .nodes ... .end section")
    lines, names = [], None
    for line in head.split(b"\n"):
        if line.startswith(b".rootnames"):
            continue
        if line.startswith(b".varinfo"):
            line = b".varinfo 3"
        elif line.startswith(b".suppvarnames "):
            names = line.split()[1:]
        lines.append(line)
    if not names:
        raise ValueError("not a DDDMP text file of named variables: no .suppvarnames")
    lengths = np.array([len(n) for n in names], dtype=np.int64)
    offsets = np.concatenate(([0], np.cumsum(lengths)))
    nodes = _named_node_lines(np.frombuffer(body, dtype=np.uint8), np.frombuffer(b"".join(names), dtype=np.uint8),
                              offsets)
    if nodes is None:
        raise ValueError("the node lines are not 'id index then else' over the support's variables")
    return b"\n".join(lines) + b"\n.nodes\n" + nodes.tobytes() + b".end\n"


@numba.njit(cache=True)
def _named_node_lines(body: np.ndarray, names: np.ndarray, offsets: np.ndarray) -> np.ndarray | None:
    """Each line ``id index then else`` of ``body`` as ``id name index then else`` (``names[offsets[i]:offsets[i+1]]``
    the name of support index ``i``), ``id T ...`` as ``id T 1 0 0``; ``None`` where a line is neither."""
    n, longest = body.size, 0
    for i in range(offsets.size - 1):
        longest = max(longest, offsets[i + 1] - offsets[i])
    lines = 0
    for i in range(n):
        lines += body[i] == 10
    out = np.empty(n + (lines + 1) * (longest + 8), dtype=np.uint8)
    k, s = 0, 0
    while s < n:
        e = s
        while e < n and body[e] != 10:
            e += 1
        if e == s:  # an empty line
            s = e + 1
            continue
        p = s
        while p < e and body[p] != 32:
            p += 1
        if p == s or p + 1 >= e:
            return None
        out[k:k + p - s] = body[s:p]
        k += p - s
        if body[p + 1] == 84:  # "T": the terminal
            for c in b" T 1 0 0\n":
                out[k] = c
                k += 1
            s = e + 1
            continue
        idx, q = 0, p + 1
        while q < e and body[q] != 32:
            if body[q] < 48 or body[q] > 57:
                return None
            idx = 10 * idx + body[q] - 48
            q += 1
        if q == p + 1 or q >= e or idx >= offsets.size - 1:
            return None
        out[k] = 32
        k += 1
        a, b = offsets[idx], offsets[idx + 1]
        out[k:k + b - a] = names[a:b]
        k += b - a
        out[k:k + e - p] = body[p:e]  # " index then else"
        k += e - p
        out[k] = 10
        k += 1
        s = e + 1
    return out[:k]
