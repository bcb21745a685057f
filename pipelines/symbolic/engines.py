"""BDD engines behind one seam: the same problem, read from the same DDDMP files, on ``dd.cudd`` or on ``oxidd``.

A *problem* is what :func:`~.files.dump` writes for a model: its header (the variables in level order) and named
roots (``meta["names"]``), e.g. a controllable predecessor's chain, its admissible pairs and a fixed point's sets.
An engine reads it back into a manager of its own, with every variable at the level the header gives, and offers
the few operations a fixed point of :mod:`pipelines.synthesis.fixed_points` is made of: the Boolean operators of its
functions (``&``, ``|``, ``~``, ``==``), the relational product :meth:`Engine.and_exists`, the renaming
:meth:`Engine.to_next` and an exact :meth:`Engine.count` of a set of states. Sets go from one engine to the other as
DDDMP (:meth:`Engine.write`, :meth:`Engine.read`), so two engines' results can be compared as sets: from CUDD to
oxidd (back only through :func:`~.oxidd_mirror.cudd_dddmp`, for BDDs with complement edges: CUDD's reader trusts its
input, and a plain BDD of oxidd's has a false terminal CUDD's files never hold).

The synthesis itself runs its ``∃u.CPre`` on oxidd through :class:`~.oxidd_mirror.OxiddMirror`
(:mod:`pipelines.synthesis.engine_cpre`); this module is the bench's (``bench/engines.py``).

:class:`CuddEngine` is the model the synthesis uses today (:func:`~.files.load_all`: the same CUDD settings).
:class:`OxiddEngine` is ``oxidd`` (Rust, PyPI; :func:`oxidd_available`), plain BDDs (``bdd``) or BDDs
with complement edges (``bcdd``, as CUDD's), its apply run on ``threads`` threads.
"""

from __future__ import annotations

import resource
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

from pipelines.controller_integrity import read_header, verify_header
from pipelines.symbolic.counting import count_states
from pipelines.symbolic.files import check_dddmp, load_all, read_root, write_root
from pipelines.symbolic.oxidd_mirror import OXIDD_CACHE, OXIDD_NODES, OxiddManager, oxidd_available

__all__ = ["CuddEngine", "Engine", "OxiddEngine", "engine", "oxidd_available", "peak_rss_mb"]


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, MiB: Linux's ``VmHWM`` of its memory map, else ``getrusage``
    (whose peak a process started by ``exec`` inherits from the process it replaced: a child of a large parent
    would report the parent's)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class Engine(Protocol):
    """What a fixed point over a problem needs of a BDD library. Functions support ``&``, ``|``, ``~`` and ``==``
    (equality of the functions, constant time in a canonical manager)."""

    name: str
    roots: dict[str, Any]
    meta: dict[str, Any]
    false: Any

    def and_exists(self, f: Any, g: Any, bits: Sequence[str]) -> Any:
        """``∃bits. f ∧ g`` in one operation (the relational product)."""

    def to_next(self, f: Any) -> Any:
        """``f(x) -> f(x')``: each current-state bit renamed to its next-state bit (``f`` reads no next-state bit)."""

    def count(self, f: Any) -> int:
        """Exact number of states of ``f``, a set over the current-state bits inside the state domain."""

    def nodes(self, f: Any) -> int:
        """Nodes of ``f``'s diagram."""

    def write(self, f: Any, path: str | Path) -> None:
        """``f`` as a one-root DDDMP file."""

    def read(self, path: str | Path) -> Any:
        """The one root of a DDDMP file over the problem's variables, written by CUDD (either engine reads those)."""


def _named(roots: Sequence[Any], meta: dict[str, Any]) -> dict[str, Any]:
    names = meta.get("names")
    if not isinstance(names, list) or len(names) != len(roots):
        raise ValueError("the problem's meta must name each of its roots ('names')")
    return dict(zip(names, roots))


class CuddEngine:
    """``dd.cudd`` as the synthesis uses it: the problem read by :func:`~.files.load_all` into a
    :class:`~.symbolic_model.SymbolicModel` (its CUDD settings, reordering off)."""

    name = "dd.cudd"

    def __init__(self, path: str | Path) -> None:
        self.model, roots, self.meta = load_all(path)
        self.roots = _named(roots, self.meta)
        self.false = self.model.bdd.false

    def and_exists(self, f: Any, g: Any, bits: Sequence[str]) -> Any:
        from pipelines.symbolic.symbolic_model import and_exists

        return and_exists(f, g, list(bits))

    def to_next(self, f: Any) -> Any:
        return self.model.to_next(f)

    def count(self, f: Any) -> int:
        return count_states(self.model, f)

    def nodes(self, f: Any) -> int:
        return int(f.dag_size)

    def write(self, f: Any, path: str | Path) -> None:
        write_root(self.model, path, f)

    def read(self, path: str | Path) -> Any:
        """A file CUDD wrote over these variables (checked first: :func:`~.files.read_root` is CUDD's reader)."""
        check_dddmp(path, self.model.variables)
        return read_root(self.model, path)


class OxiddEngine(OxiddManager):
    """``oxidd``'s BDDs (``kind='bdd'``) or BDDs with complement edges (``'bcdd'``), apply on ``threads`` threads:
    an :class:`~.oxidd_mirror.OxiddManager` over the problem header's variables, in its level order, never
    reordered; a DDDMP file's support variables are matched by name, so a file CUDD wrote (complemented edges
    included) reads into either kind.
    """

    def __init__(self, path: str | Path, kind: str = "bcdd", threads: int = 1, nodes: int = OXIDD_NODES,
                 cache: int = OXIDD_CACHE) -> None:
        head_path = Path(str(path) + ".json")
        head = read_header(head_path)
        verify_header(head, head_path, head["roots"], None)
        self.meta = dict(head.get("meta") or {})
        super().__init__(head["variables"], self.meta["x_bits"], self.meta["xn_bits"], kind, threads, nodes, cache)
        self.name = f"oxidd.{kind}, {threads} thread{'s' if threads > 1 else ''}"
        self._spare_bits = len(self.variables) - len(self.meta["x_bits"])
        self.roots = _named([self.read(head_path.with_name(name)) for name in head["roots"]], self.meta)

    def count(self, f: Any) -> int:
        # every model of f over all variables is a state times each value of the bits f does not read
        return int(f.sat_count(len(self.variables))) >> self._spare_bits


def engine(path: str | Path, name: str, threads: int = 1, **oxidd_options: int) -> Engine:
    """The engine ``name`` (``'dd.cudd'``, ``'oxidd.bdd'`` or ``'oxidd.bcdd'``) with the problem at ``path`` read."""
    if name == "dd.cudd":
        return CuddEngine(path)
    if name.startswith("oxidd."):
        return OxiddEngine(path, name.split(".", 1)[1], threads, **oxidd_options)
    raise ValueError(f"unknown BDD engine {name!r}: 'dd.cudd', 'oxidd.bdd' or 'oxidd.bcdd'")
