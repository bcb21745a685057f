"""BDDs as DDDMP (written by CUDD through ``dd``): the one place that writes and reads them.

Two uses. **Files with a header** (ARCHITECTURE "Storage"): the header names the variable order, the bit widths,
the subsystems' layouts and the grids, so a file is read back without the job store: :func:`model_from_header`
declares the same variables at the same levels, and :func:`load_all` reads the roots into it. CUDD's DDDMP writer
takes one root per file, so root ``k > 0`` of a dump goes to ``<path>.<k>.dddmp`` and the header lists the files
in order. **One root between processes** (:func:`to_bytes`, :func:`from_bytes`): the partitioned ``∃u.CPre``
sends its problem, its sets and the parts' answers as bytes to a process whose model was declared from the same
header (:mod:`pipelines.synthesis.parts`), so the levels match.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from pipelines.symbolic.model import Function, SymbolicModel
from pipelines.symbolic.order import SubsystemLayout

HEADER_FORMAT = "compabs-bdd/1"


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes, read in blocks (controller and checkpoint files carry it in their headers)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


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
    head_path.write_text(json.dumps(head, indent=1))
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


def load_all(path: str | os.PathLike, max_memory: int | None = None) -> tuple[SymbolicModel, list[Function], dict]:
    """Read ``<path>.dddmp`` (and the further roots its header lists) with the header:
    ``(model, roots in dump order, meta)``."""
    bdd_path, head_path = _paths(path)
    head = json.loads(head_path.read_text())
    model = model_from_header(head, max_memory)
    names = head.get("roots", [bdd_path.name])
    roots = [read_root(model, bdd_path.with_name(name)) for name in names]
    return model, roots, head.get("meta", {})


def load(path: str | os.PathLike, max_memory: int | None = None) -> tuple[SymbolicModel, Function, dict]:
    """Read a single-function ``<path>.dddmp`` and its header: ``(model, function, meta)``."""
    model, roots, meta = load_all(path, max_memory)
    if len(roots) != 1:
        raise ValueError(f"{path} holds {len(roots)} functions; use load_all")
    return model, roots[0], meta
