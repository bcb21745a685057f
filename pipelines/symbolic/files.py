"""BDDs as DDDMP (written by CUDD through ``dd``): the one place that writes and reads them.

Two uses. **Files with a header** (ARCHITECTURE "Storage"): the header names the variable order, the bit widths,
the subsystems' layouts and the grids, so a file is read back without the job store: :func:`model_from_header`
declares the same variables at the same levels, and :func:`load_all` reads the roots into it. CUDD's DDDMP writer
takes one root per file, so root ``k > 0`` of a dump goes to ``<path>.<k>.dddmp`` and the header lists the files
in order. **One root between processes** (:func:`to_bytes`, :func:`from_bytes`): the partitioned ``∃u.CPre``
sends its problem, its sets and the parts' answers as bytes to a process whose model was declared from the same
header (:mod:`pipelines.synthesis.parts`), so the levels match.

CUDD's DDDMP reader trusts its input: a node line that names a node not yet read, or a variable out of range, is
a segmentation fault. A file with a header is therefore read only after its header's integrity record
(:mod:`pipelines.controller_integrity`) and its own structure (:func:`check_dddmp`) have been verified.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.controller_integrity import ControllerIntegrityError, file_sha256, read_header, seal, verify_header
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.symbolic_model import Function, SymbolicModel

HEADER_FORMAT = "compabs-bdd/1"


__all__ = ["HEADER_FORMAT", "check_dddmp", "dump", "file_sha256", "from_bytes", "header", "load", "load_all",
           "model_from_header", "read_root", "to_bytes", "write_root"]


def header(model: SymbolicModel) -> dict[str, Any]:
    """What :func:`model_from_header` needs to declare the variables of ``model`` again (JSON-ready)."""
    return {
        "format": HEADER_FORMAT,
        "order": model.order,
        "variables": list(model.variables),
        "bit_widths": {d: len(b) for d, b in model.bits.items()},
        "sizes": dict(model.sizes),
        "subsystems": [asdict(s) for s in model.subsystems],
        "w_sizes": list(model.w_sizes),
        "z_sizes": dict(model.z_sizes),
        "z_owner": dict(model.z_owner),
        "z_below": dict(model.z_below),
        "grids": model.grids,
        "blocks": list(model.blocks),
    }


def write_root(model: SymbolicModel, path: str | os.PathLike, f: Function, what: str = "") -> None:
    """Write the one root ``f`` of ``model`` to the DDDMP file ``path``; CUDD out of memory is a BDDMemoryError
    naming ``what`` (default: the path)."""
    with model.guard(what or f"writing {path}"):
        model.bdd.dump(str(path), [f])


def read_root(model: SymbolicModel, path: str | os.PathLike, what: str = "") -> Function:
    """The one root of the DDDMP file ``path``, read into ``model`` (whose variables the writer's header declared)."""
    with model.guard(what or f"reading {path}"):
        (root,) = model.bdd.load(str(path))
    return root


def to_bytes(model: SymbolicModel, f: Function, what: str = "writing a BDD for another process") -> bytes:
    """``f`` as DDDMP bytes (``dd`` writes DDDMP to files only: through a temporary file)."""
    fd, path = tempfile.mkstemp(suffix=".dddmp", prefix="compabs-bdd-")
    os.close(fd)
    try:
        write_root(model, path, f, what)
        with open(path, "rb") as fh:
            return fh.read()
    finally:
        os.unlink(path)


def from_bytes(model: SymbolicModel, blob: bytes, what: str = "reading a BDD from another process") -> Function:
    """The function of DDDMP bytes (:func:`to_bytes`) in ``model``."""
    fd, path = tempfile.mkstemp(suffix=".dddmp", prefix="compabs-bdd-")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
        return read_root(model, path, what)
    finally:
        os.unlink(path)


def _paths(path: str | os.PathLike) -> tuple[Path, Path]:
    p = Path(path)
    if p.suffix.lower() == ".dddmp":
        p = p.with_suffix("")
    return p.with_name(p.name + ".dddmp"), p.with_name(p.name + ".json")


def dump(
    model: SymbolicModel, path: str | os.PathLike, f: Function | Sequence[Function], meta: dict | None = None
) -> tuple[Path, ...]:
    """Write ``f`` to ``<path>.dddmp`` and the header to ``<path>.json``; returns the paths written.

    ``f`` may be a list of roots: root ``k > 0`` goes to ``<path>.<k>.dddmp`` and the header lists the files in
    order.
    """
    bdd_path, head_path = _paths(path)
    roots = [f] if isinstance(f, Function) else list(f)
    files = [bdd_path] + [bdd_path.with_name(f"{bdd_path.stem}.{k}.dddmp") for k in range(1, len(roots))]
    for root, file in zip(roots, files):
        write_root(model, file, root)
    head = header(model)
    head["meta"] = meta or {}
    head["roots"] = [file.name for file in files]
    head_path.write_text(json.dumps(seal(head, head_path.parent, head["roots"]), indent=1))
    return (*files, head_path)


def model_from_header(head: Mapping[str, Any], max_memory: int | None = None) -> SymbolicModel:
    """A fresh model with the variables of a header, declared in its level order."""
    if head.get("format") != HEADER_FORMAT:
        raise ValueError(f"not a {HEADER_FORMAT} header: {head.get('format')!r}")
    subs = [SubsystemLayout(**{**s, "state_shape": tuple(s["state_shape"]), "reads": tuple(s["reads"])})
            for s in head["subsystems"]]
    model = SymbolicModel(subs, head["w_sizes"], head["z_sizes"], z_owner=head["z_owner"],
                          z_below=head.get("z_below"), order=head["order"],
                          max_memory=max_memory, grids=head.get("grids"), blocks=head.get("blocks"))
    if model.variables != list(head["variables"]):
        raise ValueError("the header's variable order differs from the one this code declares")
    return model


def load_all(path: str | os.PathLike, max_memory: int | None = None, job_hash: str | None = None
             ) -> tuple[SymbolicModel, list[Function], dict]:
    """Read ``<path>.dddmp`` (and the further roots its header lists) with the header:
    ``(model, roots in dump order, meta)``.

    Nothing reaches CUDD before the header's integrity record (checksums, spec hash; with ``job_hash``, the job's
    spec hash too: :func:`~pipelines.controller_integrity.verify_header`) and every file's structure
    (:func:`check_dddmp`) are verified.

    Raises
    ------
    ControllerIntegrityError
        A file missing, damaged, replaced, malformed or of another job, named with what differs.
    """
    _, head_path = _paths(path)
    head = read_header(head_path)
    names = head.get("roots")
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise ControllerIntegrityError(f"{head_path}: not a readable controller header (its 'roots' do not list the "
                                       "BDD files)")
    verify_header(head, head_path, names, job_hash)
    try:
        model = model_from_header(head, max_memory)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise ControllerIntegrityError(f"{head_path}: not a readable controller header ({type(exc).__name__}: "
                                       f"{exc})") from None
    files = [head_path.with_name(name) for name in names]
    for file in files:
        check_dddmp(file, model.variables)
    roots = [read_root(model, file) for file in files]
    meta = head.get("meta", {})
    if not isinstance(meta, dict):
        raise ControllerIntegrityError(f"{head_path}: its 'meta' is not an object")
    return model, roots, meta


def load(path: str | os.PathLike, max_memory: int | None = None) -> tuple[SymbolicModel, Function, dict]:
    """Read a single-function ``<path>.dddmp`` and its header: ``(model, function, meta)``."""
    model, roots, meta = load_all(path, max_memory)
    if len(roots) != 1:
        raise ValueError(f"{path} holds {len(roots)} functions; use load_all")
    return model, roots[0], meta


#: The header lines of a DDDMP file as ``dd`` writes one root in text mode, in their order.
DDDMP_KEYS = (".ver", ".mode", ".varinfo", ".nnodes", ".nvars", ".nsuppvars", ".suppvarnames", ".orderedvarnames",
              ".ids", ".permids", ".nroots", ".rootids", ".nodes")
#: A node line: id, variable name, support index, then child, else child (``-`` a complemented edge). Numbers
#: have at most 10 digits, so every value fits CUDD's ``int``.
_NODE_LINES = re.compile(rb"(?:[0-9]{1,10} [A-Za-z_][A-Za-z0-9_]{0,99} -?[0-9]{1,10} -?[0-9]{1,10} -?[0-9]{1,10}\n)*")
_INT = re.compile(r"-?[0-9]{1,10}")
#: Bytes a DDDMP file may hold: printable ASCII and newlines (CUDD reads tokens with fscanf and stops at a NUL).
_TEXT = np.zeros(256, dtype=bool)
_TEXT[0x20:0x7F] = True
_TEXT[0x0A] = True


def _ints(values: list[str], what: str) -> list[int]:
    if not all(_INT.fullmatch(v) for v in values):
        raise ValueError(f"{what} holds a token that is not an integer")
    return [int(v) for v in values]


def check_dddmp(path: str | os.PathLike, variables: Sequence[str]) -> None:
    """Check that ``path`` is a one-root DDDMP text file over ``variables`` (listed in level order) as ``dd``
    writes them, before CUDD reads it: every header line, then per node (in bulk) the id, a variable of the
    support named as the support lists it, children already read and on lower levels, and the root among the
    nodes.

    Raises
    ------
    ControllerIntegrityError
        Naming the file and the first thing that does not fit.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ControllerIntegrityError(f"{path}: cannot read the BDD file ({exc.strerror or exc})") from None
    try:
        _check_dddmp(data, list(variables))
    except ValueError as exc:
        raise ControllerIntegrityError(f"{path}: not a DDDMP file of this controller ({exc})") from None


def _check_dddmp(data: bytes, variables: list[str]) -> None:  # noqa: PLR0912 - one check per header line
    if not _TEXT[np.frombuffer(data, dtype=np.uint8)].all():
        raise ValueError("it holds bytes other than printable ASCII and newlines")
    n_keys = len(DDDMP_KEYS)
    lines = data.split(b"\n", n_keys)
    if len(lines) <= n_keys:
        raise ValueError("its header is truncated")
    head = [line.decode().split(" ") for line in lines[:n_keys]]
    if [h[0] for h in head] != list(DDDMP_KEYS):
        raise ValueError(f"its header lines are not {' '.join(DDDMP_KEYS)}")
    values = {h[0]: h[1:] for h in head}
    if values[".ver"] != ["DDDMP-2.0"] or values[".mode"] != ["A"] or values[".varinfo"] != ["3"]:
        raise ValueError("not DDDMP-2.0 text with variable names (.ver, .mode, .varinfo)")
    counts = {k: _ints(values[k], k) for k in (".nnodes", ".nvars", ".nsuppvars", ".nroots", ".rootids", ".ids",
                                               ".permids")}
    if any(len(counts[k]) != 1 for k in (".nnodes", ".nvars", ".nsuppvars", ".nroots")):
        raise ValueError(".nnodes, .nvars, .nsuppvars and .nroots each take one number")
    n, n_vars, n_supp = counts[".nnodes"][0], counts[".nvars"][0], counts[".nsuppvars"][0]
    if n_vars != len(variables) or sorted(values[".orderedvarnames"]) != sorted(variables):
        raise ValueError(f"its variables (.nvars, .orderedvarnames) are not the header's {len(variables)}")
    supp = values[".suppvarnames"] if values[".suppvarnames"] != [""] else []
    ids = counts[".ids"]
    if not (len(supp) == n_supp == len(ids) == len(counts[".permids"]) and len(set(supp)) == n_supp
            and set(supp) <= set(variables)):
        raise ValueError("its support (.nsuppvars, .suppvarnames, .ids, .permids) is inconsistent")
    if not all(0 <= i < n_vars for i in (*ids, *counts[".permids"])):
        raise ValueError("a variable id (.ids, .permids) is out of range")
    if counts[".nroots"] != [1] or len(counts[".rootids"]) != 1 or not 1 <= abs(counts[".rootids"][0]) <= n:
        raise ValueError("it does not hold one root among its nodes (.nroots, .rootids)")
    body = lines[n_keys]
    end = body.find(b".end\n")
    nodes = body[:end] if end >= 0 else b""
    if end < 0 or body[end:] != b".end\n" or _NODE_LINES.fullmatch(nodes) is None:
        raise ValueError("its node lines are malformed or truncated (each 'id name index then else', then .end)")
    table = np.array(nodes.split()).reshape(-1, 5)
    if table.shape[0] != n:
        raise ValueError(f"it has {table.shape[0]} node lines, .nnodes says {n}")
    node_id, var, then, other = (table[:, k].astype(np.int64) for k in (0, 2, 3, 4))
    names = table[:, 1].astype(str)
    if not np.array_equal(node_id, np.arange(1, n + 1)):
        raise ValueError("its node ids are not 1, 2, ... in order")
    if (names[0], var[0], then[0], other[0]) != ("T", 1, 0, 0):
        raise ValueError("its first node is not the constant TRUE ('1 T 1 0 0')")
    var, then, other, names, node_id = var[1:], then[1:], other[1:], names[1:], node_id[1:]
    if not np.all((var >= 0) & (var < n_supp)):
        raise ValueError("a node's variable index is outside the support")
    if not np.all((then >= 1) & (then < node_id) & (other != 0) & (np.abs(other) < node_id)):
        raise ValueError("a node's child is not a node read before it")
    if n_supp and not np.array_equal(names, np.asarray(supp)[var]):
        raise ValueError("a node's variable name differs from the support's")
    # Levels in the reading model: a child must lie below its parent, as in any reduced ordered BDD.
    level = {name: k for k, name in enumerate(variables)}
    node_level = np.full(n + 1, len(variables), dtype=np.int64)  # the constant below every variable
    if n_supp:
        node_level[2:] = np.asarray([level[s] for s in supp], dtype=np.int64)[var]
    if not np.all((node_level[then] > node_level[node_id]) & (node_level[np.abs(other)] > node_level[node_id])):
        raise ValueError("a node's child is not below it in the variable order")
