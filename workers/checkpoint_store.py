"""The job directory's store of safety iterates (:class:`~pipelines.synthesis.checkpoints.Checkpoints`).

::

    DIR/checkpoints/<fixed point>.dddmp   the last stored iterate (CUDD's DDDMP, one root)
    DIR/checkpoints/<fixed point>.json    {format, problem, name, iteration, sha256, nodes, saved}

The JSON is written after the DDDMP, each by a rename, so a job killed while writing leaves the previous pair or a
DDDMP without its JSON, never a JSON naming bytes it does not have. An iterate is used only when its JSON names
this problem (:func:`problem_key`: the specification, the subsystem relations and the interconnection's node
relations, hashed;
:func:`variables_key`: the BDD variables) and the DDDMP's SHA-256 is the one the JSON records; otherwise the fixed point starts afresh
and the report's warnings say why (a store of another problem is replaced silently: that is what a changed spec
leaves behind). ``pipelines/synthesis/checkpoints.py`` says why even a wrong iterate could not make the
controller unsound.

The files go once the synthesis is done (:meth:`DirectoryCheckpoints.clear`): they hold one BDD as large as the
largest iterate (hundreds of MB for the tanks at spacing 1.25).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.errors import CompabsError
from pipelines.symbolic.files import check_dddmp, file_sha256
from pipelines.symbolic.symbolic_model import Function, SymbolicModel

FORMAT = "compabs-checkpoint/1"
#: Least seconds between two writes of a fixed point's iterate (the last one is always written): dumping an
#: iterate of millions of nodes takes seconds, an iteration of the cases that need this takes minutes.
EVERY = 60.0


def problem_key(specification: Mapping[str, Any], relations: Mapping[str, Any], nodes: Iterable[Any],
                quotient: int = 0) -> str:
    """A hash of what the safety iterates are computed from: the spec's ``specification`` section (its regions,
    JSON-ready), every subsystem relation's arrays (by key), every node relation's arrays and the quotient's level
    (``options.synthesis_quotient``: its iterates are another game's; the stored iterate also records the BDD
    variables, :func:`variables_key`). Timing options, worker counts and the variable order are not in it: the
    iterates are the same sets under all of them."""
    h = hashlib.blake2b(digest_size=20)
    h.update(json.dumps(specification, sort_keys=True).encode())
    if quotient:  # the exact game's keys are the ones written before quotients existed
        h.update(f"|quotient|{int(quotient)}|".encode())

    def add(label: str, a: np.ndarray) -> None:
        a = np.ascontiguousarray(a)
        h.update(f"|{label}|{a.dtype.str}|{list(a.shape)}|".encode())
        h.update(a.reshape(-1).view(np.uint8).data)

    for key in sorted(relations):
        rel = relations[key]
        for name in ("lo", "hi", "blocking"):
            add(f"{key}.{name}", getattr(rel, name))
    for k, node in enumerate(nodes):
        h.update(f"|node{k}|{node.output}|{list(node.inputs)}|".encode())
        add(f"node{k}.lo", node.lo)
        add(f"node{k}.hi", node.hi)
    return h.hexdigest()


def variables_key(model: SymbolicModel) -> str:
    """A hash of the BDD variables' names (not their order): an iterate is read back by name."""
    return hashlib.blake2b(json.dumps(sorted(model.variables)).encode(), digest_size=12).hexdigest()


def _stem(name: str) -> str:
    """``reach_safe/safe`` -> ``reach_safe-safe`` (one file name per fixed point)."""
    return name.replace("/", "-")


def remove(root: str | os.PathLike[str]) -> None:
    """Remove a store's files from ``root`` (a job's ``checkpoints/``), and ``root`` if nothing else is in it.

    After a synthesis the controller holds what they were kept for; a job that ended cancelled or failed is never
    resumed (a new submission is a new job, in a directory of its own), and its iterates can be hundreds of MB.
    """
    root = Path(root)
    if root.is_dir():
        for path in root.iterdir():
            if path.suffix in (".dddmp", ".json"):
                path.unlink(missing_ok=True)
        try:
            root.rmdir()
        except OSError:
            pass  # something else in it: not ours to remove


class DirectoryCheckpoints:
    """Safety iterates in ``root`` (a job's ``checkpoints/``) for the problem ``key`` (:func:`problem_key`).

    ``every``: least seconds between writes (:data:`EVERY`; 0 writes every iterate). ``warnings``: why a stored
    iterate was not used, for the report. ``resumed``/``written``: per fixed point, the iteration resumed from
    and the iterations written.
    """

    def __init__(self, root: str | os.PathLike[str], key: str, every: float = EVERY) -> None:
        self.root = Path(root)
        self.key = key
        self.every = float(every)
        self.warnings: list[str] = []
        self.resumed: dict[str, int] = {}
        self.written: dict[str, list[int]] = {}
        self._last: dict[str, float] = {}

    def _paths(self, name: str) -> tuple[Path, Path]:
        stem = _stem(name)
        return self.root / f"{stem}.dddmp", self.root / f"{stem}.json"

    # ------------------------------------------------------------------ Checkpoints
    def resume(self, model: SymbolicModel, name: str) -> tuple[Function, int] | None:
        self._last[name] = time.monotonic()
        bdd_path, head_path = self._paths(name)
        if not head_path.exists():
            return None
        where = f"synthesis checkpoint {head_path}"
        try:
            head = json.loads(head_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            return self._refuse(f"{where} is not readable JSON ({exc}); the fixed point started afresh")
        if not isinstance(head, dict) or head.get("format") != FORMAT or head.get("name") != name:
            return self._refuse(f"{where} is not a compabs checkpoint of '{name}'; the fixed point started afresh")
        if head.get("problem") != self.key or head.get("variables") != variables_key(model):
            return None  # another spec's, or another abstraction's: replaced by this run's first write
        iteration = head.get("iteration")
        if not isinstance(iteration, int) or isinstance(iteration, bool) or iteration < 0:
            return self._refuse(f"{where} has no iteration count; the fixed point started afresh")
        if not bdd_path.exists():
            return self._refuse(f"{where} names {bdd_path.name}, which is missing; the fixed point started afresh")
        if file_sha256(bdd_path) != head.get("sha256"):
            return self._refuse(f"{bdd_path} does not match the SHA-256 its checkpoint records (damaged or "
                                f"replaced); the fixed point started afresh")
        try:  # its structure before CUDD reads it: a file forged with its checksum recomputed must not crash us
            check_dddmp(bdd_path, model.variables)
        except CompabsError as exc:
            return self._refuse(f"{exc}; the fixed point started afresh")
        try:
            with model.guard(f"loading {bdd_path}"):
                (Z,) = model.bdd.load(str(bdd_path))
        except Exception as exc:  # noqa: BLE001 - dd raises bare errors for a file it cannot read
            return self._refuse(f"{bdd_path} could not be read back ({type(exc).__name__}: {exc}); the fixed point "
                                f"started afresh")
        outside = set(model.bdd.support(Z)) - set(model.x_bits)
        if outside:
            return self._refuse(f"{bdd_path} is not a set of states (it reads {sorted(outside)[:3]}); the fixed "
                                f"point started afresh")
        self.resumed[name] = iteration
        return Z, iteration

    def iterate(self, model: SymbolicModel, name: str, Z: Function, iteration: int) -> None:
        if time.monotonic() - self._last.get(name, 0.0) >= self.every:
            self._write(model, name, Z, iteration)

    def converged(self, model: SymbolicModel, name: str, Z: Function, iteration: int) -> None:
        self._write(model, name, Z, iteration)

    # ------------------------------------------------------------------ files
    def _refuse(self, why: str) -> tuple[Function, int] | None:
        """Note why a stored iterate is not used (for the report) and use none."""
        self.warnings.append(why)
        return None

    def _write(self, model: SymbolicModel, name: str, Z: Function, iteration: int) -> None:
        self.root.mkdir(parents=True, exist_ok=True)  # CUDD's DDDMP writer aborts the process on a missing directory
        bdd_path, head_path = self._paths(name)
        tmp_bdd = bdd_path.with_name(f"{bdd_path.stem}.tmp.dddmp")
        tmp_head = head_path.with_name(f"{head_path.stem}.tmp.json")
        with model.guard(f"writing {bdd_path}"):
            model.bdd.dump(str(tmp_bdd), [Z], filetype="dddmp")
        head = {"format": FORMAT, "problem": self.key, "variables": variables_key(model), "name": name,
                "iteration": int(iteration),
                "sha256": file_sha256(tmp_bdd), "nodes": Z.dag_size, "saved": time.time()}
        os.replace(tmp_bdd, bdd_path)
        tmp_head.write_text(json.dumps(head, indent=1))
        os.replace(tmp_head, head_path)
        self._last[name] = time.monotonic()
        self.written.setdefault(name, []).append(int(iteration))

    def clear(self) -> None:
        """Remove the store's files (after the synthesis: the controller holds what they were for)."""
        remove(self.root)

    def describe(self) -> dict[str, Any]:
        """JSON-ready, for the report."""
        return {"directory": str(self.root), "resumed_at_iteration": dict(self.resumed),
                "iterations_written": dict(self.written), "warnings": list(self.warnings)}
