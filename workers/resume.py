"""What a run of the same spec into the same directory reads back instead of computing again.

The relation chunks are reused by the store (:mod:`workers.relation_store`); the interconnection abstraction and the
abstraction's audit are read back here, from ``DIR/resume.json`` (:data:`workers.jobdir.RESUME`) and the
interconnection files (:func:`workers.jobdir.save_interconnection`), when they were written for this very spec
(its hash, which covers the seed, the audit size and everything the abstraction depends on):

- the interconnection, when its files hold what was computed (a SHA-256 of its content kept beside), together
  with the state of the job's random generator right after it, so that the audit that follows draws what a run
  from scratch draws;
- the audit's report, only when the interconnection was read back and no relation chunk was computed in this
  run: then the audit would check exactly what it checked before.

Anything missing, unreadable or of another spec is computed again, as before this module existed.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.interconnection import InterconnectionAbstraction, abstract_interconnection
from pipelines.network import Network
from pipelines.spec.model import JobSpec, spec_hash
from workers import jobdir

__all__ = ["digest", "interconnection", "keep_audit", "stored_audit"]

#: Keys of an audit report that describe one run of it, not what it found.
_RUN_ONLY = ("beside_synthesis", "waited_seconds", "pending", "stored")


def _read(out: Path | None, spec: JobSpec) -> dict[str, Any]:
    """``resume.json`` when it was written for ``spec``, else ``{}``."""
    if out is None:
        return {}
    try:
        data = json.loads((out / jobdir.RESUME).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) and data.get("spec_hash") == spec_hash(spec) else {}


def _write(out: Path, spec: JobSpec, **entries: Any) -> None:
    data = {**_read(out, spec), **entries, "spec_hash": spec_hash(spec)}
    tmp = out / f"{jobdir.RESUME}.partial"
    try:
        tmp.write_text(json.dumps(data, default=jobdir.json_default))
        tmp.replace(out / jobdir.RESUME)
    except OSError:  # resuming is an optimisation: a full disk fails the job where its own files are written
        return


def digest(ia: InterconnectionAbstraction) -> str:
    """SHA-256 of everything an interconnection abstraction holds (its arrays and its description): a stored one
    that differs from what was computed (damaged, edited) is computed again, never reused unaudited."""
    h = hashlib.sha256(json.dumps(ia.describe(), sort_keys=True, default=jobdir.json_default).encode())
    arrays = [ia.M_bar, ia.offsets, ia.error_bounds, *(a for node in ia.nodes for a in (node.lo, node.hi))]
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def interconnection(out: Path | None, spec: JobSpec, network: Network, rng: np.random.Generator
                    ) -> tuple[InterconnectionAbstraction, bool]:
    """The interconnection abstraction: read back (``rng`` set to its state after the first run computed it), or
    computed with ``rng`` (that state and the result's :func:`digest` kept in ``out``). Returns it and whether
    it was read back."""
    kept = _read(out, spec)
    if out is not None and kept.get("rng_after_interconnection") is not None:
        try:
            ia = jobdir.load_interconnection(out, spec)
            meta = json.loads((out / jobdir.INTERCONNECTION_META).read_text())
            if meta.get("spec_hash") == spec_hash(spec) and digest(ia) == kept.get("interconnection_sha256"):
                rng.bit_generator.state = kept["rng_after_interconnection"]
                return ia, True
        except (jobdir.ArtifactError, OSError, ValueError, TypeError, KeyError):
            pass  # damaged or of an older layout: computed again
    ia = abstract_interconnection(network, rng)
    if out is not None:
        _write(out, spec, rng_after_interconnection=rng.bit_generator.state, interconnection_sha256=digest(ia),
               audit=None)
    return ia, False


def stored_audit(out: Path | None, spec: JobSpec, *, interconnection_read_back: bool, chunks_computed: int
                 ) -> dict[str, Any] | None:
    """The audit report a run of ``spec`` stored, if it checked what this run would check (the interconnection
    read back, every relation chunk reused); ``None`` otherwise."""
    if not interconnection_read_back or chunks_computed:
        return None
    audit = _read(out, spec).get("audit")
    if not isinstance(audit, dict) or not audit.get("transitions_checked"):
        return None
    return {**audit, "stored": True}


def keep_audit(out: str | os.PathLike[str] | None, spec: JobSpec, audit: dict[str, Any]) -> None:
    """Store a finished audit's report for a later run of ``spec`` into ``out`` (nothing for an audit not run,
    still pending, or itself read back)."""
    if out is None or "://" in os.fspath(out) or audit.get("pending") or audit.get("stored"):
        return
    if not audit.get("transitions_checked") or not _read(Path(out), spec):
        return  # no interconnection state: a later run computes the interconnection, hence the audit, again
    _write(Path(out), spec, audit={k: v for k, v in audit.items() if k not in _RUN_ONLY})
