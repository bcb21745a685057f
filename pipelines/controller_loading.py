"""Reading any controller file back: the one entry point that knows every form (:func:`load_controller`).

A job's controller is a BDD (:mod:`.controller`, explicit or layered), an explicit game's arrays
(:mod:`.array_controller`), or a determinized one exported as JSON (:mod:`.export.table`); this module sits above
all three, so that none of them imports another's package to dispatch.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import TYPE_CHECKING

from pipelines.array_controller import ArrayController, is_array_controller
from pipelines.controller import CONTROLLER_FILE, Controller, LayeredController
from pipelines.controller_integrity import ControllerIntegrityError, job_spec_hash
from pipelines.errors import CompabsError
from pipelines.export.table import EXPORT_FORMAT, PRODUCT_EXPORT_FORMAT, ExportedController, load_export
from pipelines.product_controller import FORM as PRODUCT_FORM
from pipelines.product_controller import ProductController, is_product_arrays
from pipelines.symbolic.files import load_all

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.export.memory import ExportedProductController


def load_controller(
    directory: str | os.PathLike[str], name: str = CONTROLLER_FILE, job_hash: str | None = None
) -> Controller | ArrayController | ExportedController | ProductController | ExportedProductController:
    """Load a controller written by ``compabs run`` (``DIR/controller.json`` with ``DIR/controller.dddmp``, or
    with ``DIR/controller.npz`` for an explicit game's :class:`~.array_controller.ArrayController`), or a
    determinized one exported as JSON (``compabs export --format json``: pass the file), answering ``input(x)`` /
    ``inputs(x)`` (:class:`~.export.table.ExportedController`). An ``ltl`` job's controller has memory
    (:class:`~.product_controller.ProductController`, arrays or BDDs; its JSON export reads back as
    :class:`~.export.memory.ExportedProductController`).

    Every file is verified before use (:mod:`.controller_integrity`): the checksums and the spec hash its header
    records, and that spec hash against ``job_hash`` (default: the spec hash of ``DIR/spec.json`` when the
    controller lies in a job directory, so a controller copied from another job is refused).

    Raises
    ------
    ControllerIntegrityError
        A file missing, damaged, replaced, malformed, without an integrity record, or of another job.
    """
    path = Path(directory)
    if path.is_file():
        if is_export(path):
            return load_export(path)
        if is_export(path, PRODUCT_EXPORT_FORMAT):
            from pipelines.export.memory import load_product_export  # the export package's heavier half

            return load_product_export(path)
        directory, name = path.parent, path.name.removesuffix(".json").removesuffix(".dddmp").removesuffix(".npz")
    base = Path(directory) / name
    head = base.with_name(base.name + ".json")
    if not head.exists():
        raise CompabsError(f"no controller in {directory} (expected {base.name}.json and {base.name}.dddmp)")
    if job_hash is None:
        job_hash = job_spec_hash(directory)
    if is_array_controller(head):
        return ArrayController.load(directory, name, job_hash)
    if is_product_arrays(head):
        return ProductController.load(directory, name, job_hash)
    model, roots, meta = load_all(base, job_hash=job_hash)
    if meta.get("form") == PRODUCT_FORM:
        return ProductController.from_roots(model, roots, meta, head)
    try:
        if meta.get("form") != "layered":
            (bdd,) = roots
            return Controller(model, bdd, meta)
        n_chain, n_layers, shared = len(meta["chain_next_bits"]), int(meta["layers"]), bool(meta["shared"])
        if len(roots) != 1 + n_chain + n_layers + shared or n_layers < 1:
            raise ValueError(f"{len(roots)} BDD files for {n_chain} relations, {n_layers} layers")
        admissible, chain, layers = roots[0], roots[1:1 + n_chain], roots[1 + n_chain:1 + n_chain + n_layers]
        M = roots[1 + n_chain + n_layers] if shared else None
        bits = [[str(b) for b in group] for group in meta["chain_next_bits"]]
        return LayeredController(model, admissible, list(zip(chain, bits)), M, layers, meta["stay"], meta)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise ControllerIntegrityError(f"{head}: not a readable controller header ({type(exc).__name__}: {exc})"
                                       ) from None


def is_export(path: Path, fmt: str = EXPORT_FORMAT) -> bool:
    """Whether a file is a JSON export of format ``fmt`` (its ``format``; the first bytes are enough)."""
    with open(path, "rb") as f:
        head = f.read(4096)
    return re.search(rb'"format"\s*:\s*"' + re.escape(fmt.encode()) + rb'"', head) is not None
