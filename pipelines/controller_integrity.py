"""The integrity of controller files: checksums and the spec hash in every header, verified before any use.

A controller header (``NAME.json`` of a BDD controller, :mod:`.symbolic.files`, or of an array controller,
:mod:`.array_controller`) carries an ``integrity`` record::

    "integrity": {"files": {"NAME.dddmp": "<sha256>", ...},   every payload file the header lists
                  "spec_hash": "<spec hash>" or null,          the job's (pipelines.spec.model.spec_hash)
                  "header_sha256": "<sha256>"}                 of the header itself, this key left out

:func:`verify_header` checks all three, and the spec hash against the spec the header's ``meta`` holds and
against the job's ``spec.json`` when the controller lies in a job directory, before a payload file is read:
CUDD's DDDMP reader trusts its input (a changed node line is a segmentation fault), so an unverified file never
reaches it. A JSON export (``compabs export --format json``) carries the same record for itself
(:func:`seal_export`, :func:`verify_export`).

The checksums detect damage and files mixed up between jobs; they are not signatures: whoever can write a job
directory can write a consistent forgery. That is why the DDDMP files are also checked for structure
(:func:`~.symbolic.files.check_dddmp`) and the C export writes numbers and identifiers only.

Headers written without the record (older versions of compabs) are refused: their payload cannot be verified,
and the job is run again to write them anew (its stored relations are reused).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from pipelines.errors import CompabsError

#: Key of the integrity record in a controller header or a JSON export.
INTEGRITY = "integrity"
#: The job spec's file in a job directory (``workers.jobdir.SPEC``).
JOB_SPEC = "spec.json"
#: What a refusal tells the user to do.
RERUN = "run the job again (or synthesize the controller again) to write it anew"


class ControllerIntegrityError(CompabsError):
    """A controller file (header, payload or export) is damaged, replaced, unverifiable or of another job."""


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes, read in blocks (controller and checkpoint files carry it in their headers)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def canonical_sha256(data: Any) -> str:
    """The SHA-256 of a JSON value's canonical text (sorted keys, no spaces): what a header's own checksum is of."""
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()


def meta_spec_hash(meta: Mapping[str, Any], where: str | os.PathLike) -> str | None:
    """The spec hash of the spec a header's ``meta`` holds (``None`` without one)."""
    spec = meta.get("spec") if isinstance(meta, Mapping) else None
    if spec is None:
        return None
    from pipelines.spec.model import parse_spec, spec_hash

    try:
        return spec_hash(parse_spec(spec))
    except CompabsError as exc:
        raise ControllerIntegrityError(f"{where}: the spec it records is not a valid spec ({exc}); {RERUN}") from None


def job_spec_hash(directory: str | os.PathLike) -> str | None:
    """The spec hash of ``DIR/spec.json``, or ``None`` if ``directory`` holds none (a controller on its own)."""
    path = Path(directory) / JOB_SPEC
    if not path.is_file():
        return None
    from pipelines.spec.model import parse_spec, spec_hash

    try:
        return spec_hash(parse_spec(json.loads(path.read_text())))
    except (OSError, ValueError) as exc:
        raise ControllerIntegrityError(f"{path}: the job's spec cannot be read ({type(exc).__name__}: {exc}); the job "
                                       "directory is damaged: run the job again") from None
    except CompabsError as exc:
        raise ControllerIntegrityError(f"{path}: the job's spec is not a valid spec ({exc}); the job directory is "
                                       "damaged: run the job again") from None


class JsonMessages(NamedTuple):
    """The messages of :func:`read_json_object`: ``str.format`` templates of ``path``, ``what`` (the file's role)
    and ``reason``: the system's error, the JSON parser's, or the JSON type the file holds."""

    unreadable: str
    not_json: str
    not_object: str


#: A controller header that cannot be read: the controller is written anew.
HEADER_MESSAGES = JsonMessages(
    "{path}: cannot read the {what} ({reason})",
    "{path}: not a readable {what}: not valid JSON ({reason}); " + RERUN,
    "{path}: not a readable {what}: a JSON {reason}, not an object; " + RERUN,
)


def read_json_object(path: str | os.PathLike, what: str, error: type[Exception],
                     messages: JsonMessages) -> dict[str, Any]:
    """The JSON object in a file; one that is missing, unreadable, not JSON or not an object raises ``error`` with
    the matching message (every caller names the file and what it is for)."""
    try:
        data = json.loads(Path(path).read_bytes())
    except OSError as exc:
        raise error(messages.unreadable.format(path=path, what=what, reason=exc.strerror or exc)) from None
    except ValueError as exc:
        raise error(messages.not_json.format(path=path, what=what, reason=exc)) from None
    if not isinstance(data, dict):
        raise error(messages.not_object.format(path=path, what=what, reason=type(data).__name__))
    return data


def read_header(path: str | os.PathLike, what: str = "controller header") -> dict[str, Any]:
    """A header's JSON object; a file that is missing, unreadable or not a JSON object is refused, named."""
    return read_json_object(path, what, ControllerIntegrityError, HEADER_MESSAGES)


def seal(head: dict[str, Any], directory: str | os.PathLike, files: Iterable[str]) -> dict[str, Any]:
    """``head`` with its integrity record: the checksums of ``files`` (names in ``directory``), the spec hash of
    its ``meta``'s spec, and the header's own checksum."""
    where = Path(directory)
    record: dict[str, Any] = {
        "files": {name: file_sha256(where / name) for name in files},
        "spec_hash": meta_spec_hash(head.get("meta") or {}, where),
    }
    sealed = {**head, INTEGRITY: record}
    # Of the header as it reads back (JSON turns tuples into lists, keys into strings).
    record["header_sha256"] = canonical_sha256(json.loads(json.dumps(sealed)))
    return sealed


def _record(head: Mapping[str, Any], path: Path) -> dict[str, Any]:
    record = head.get(INTEGRITY)
    if record is None:
        raise ControllerIntegrityError(
            f"{path} has no integrity record (no checksums, no spec hash: written by an older version of compabs, "
            f"or stripped), so its files cannot be verified; {RERUN}")
    ok = (isinstance(record, dict) and isinstance(record.get("files"), dict)
          and all(isinstance(k, str) and isinstance(v, str) for k, v in record["files"].items())
          and isinstance(record.get("header_sha256"), str) and isinstance(record.get("spec_hash"), str | None))
    if not ok:
        raise ControllerIntegrityError(f"{path}: its integrity record is malformed; {RERUN}")
    return record


def verify_header(head: Mapping[str, Any], path: str | os.PathLike, payload: Iterable[str],
                  job_hash: str | None = None) -> None:
    """Verify a controller header read from ``path`` before any of its payload files is used.

    Parameters
    ----------
    head : mapping
        The header (:func:`read_header`).
    path : path
        Where it was read from; payload files lie beside it.
    payload : iterable of str
        The payload files the header lists (its ``roots``); each must have a checksum in the record.
    job_hash : str, optional
        The spec hash of the job the controller must belong to (its ``spec.json``); ``None``: no job to match.

    Raises
    ------
    ControllerIntegrityError
        Naming the file and what differs: no record, the header's own checksum, a payload file's checksum (or
        a file missing), the spec hash against the header's spec or the job's.
    """
    path = Path(path)
    record = _record(head, path)
    stripped = {**head, INTEGRITY: {k: v for k, v in record.items() if k != "header_sha256"}}
    if canonical_sha256(stripped) != record["header_sha256"]:
        raise ControllerIntegrityError(f"{path}: its checksum differs from the one it records (the header was edited "
                                       f"or damaged); {RERUN}")
    files = record["files"]
    for name in payload:
        if not isinstance(name, str) or Path(name).name != name or name not in files:
            raise ControllerIntegrityError(f"{path}: lists payload file {str(name)[:80]!r} without a checksum; {RERUN}")
        target = path.with_name(name)
        try:
            digest = file_sha256(target)
        except OSError as exc:
            raise ControllerIntegrityError(f"{target}: cannot read the controller file ({exc.strerror or exc}); "
                                           f"{RERUN}") from None
        if digest != files[name]:
            raise ControllerIntegrityError(f"{target}: its checksum differs from the one in {path.name} (a damaged or "
                                           f"replaced file); {RERUN}")
    recorded = record["spec_hash"]
    own = meta_spec_hash(head.get("meta") or {}, path)
    if own != recorded:
        raise ControllerIntegrityError(f"{path}: records spec hash {recorded} but the spec it holds has spec hash {own}; "
                                       f"{RERUN}")
    if job_hash is not None and recorded != job_hash:
        raise ControllerIntegrityError(
            f"{path}: synthesized for spec hash {recorded}, but the job's {JOB_SPEC} has spec hash {job_hash}: "
            f"the controller belongs to another job; {RERUN}")


class ArraysHeader(NamedTuple):
    """A verified header of a controller stored as one array file: the header, that file, its shape and meta."""

    header: dict[str, Any]
    arrays: Path
    shape: tuple[int, ...]
    meta: dict[str, Any]


def read_arrays_header(head_path: Path, what: str, expected_format: str, job_hash: str | None) -> ArraysHeader:
    """The header of a controller whose payload is one array file (``roots``: its name), its ``format`` checked
    and its integrity record verified (:func:`verify_header`) before the payload is read.

    Raises
    ------
    ControllerIntegrityError
        A missing or malformed header, another format, or a record that does not match, naming the file.
    """
    header = read_header(head_path, f"{what} header")
    if header.get("format") != expected_format:
        raise ControllerIntegrityError(f"{head_path}: format {header.get('format')!r}, expected {expected_format!r}")
    try:
        (root,) = header["roots"]
        shape = tuple(int(k) for k in header["shape"])
        meta = dict(header["meta"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ControllerIntegrityError(f"{head_path}: not a readable {what} header ({type(exc).__name__}: {exc})"
                                       ) from None
    verify_header(header, head_path, [root], job_hash)
    return ArraysHeader(header, head_path.with_name(root), shape, meta)


def seal_export(data: dict[str, Any]) -> dict[str, Any]:
    """A JSON export with its integrity record (its spec's hash and its own checksum)."""
    body = {k: v for k, v in data.items() if k != INTEGRITY}
    record = {"spec_hash": meta_spec_hash(body, "the export"), "sha256": canonical_sha256(json.loads(json.dumps(body)))}
    return {**body, INTEGRITY: record}


def verify_export(data: Mapping[str, Any], path: str | os.PathLike) -> None:
    """Verify a JSON export read from ``path`` (:func:`seal_export`) before it is used."""
    record = data.get(INTEGRITY)
    if record is None:
        raise ControllerIntegrityError(f"{path} has no integrity record (no checksum: written by an older version "
                                       "of compabs, or stripped); export the controller again")
    if not (isinstance(record, dict) and isinstance(record.get("sha256"), str)
            and isinstance(record.get("spec_hash"), str | None)):
        raise ControllerIntegrityError(f"{path}: its integrity record is malformed; export the controller again")
    body = {k: v for k, v in data.items() if k != INTEGRITY}
    if canonical_sha256(body) != record["sha256"]:
        raise ControllerIntegrityError(f"{path}: its checksum differs from the one it records (the export was edited "
                                       "or damaged); export the controller again")
    own = meta_spec_hash(body, path)
    if own != record["spec_hash"]:
        raise ControllerIntegrityError(f"{path}: records spec hash {record['spec_hash']} but the spec it holds has "
                                       f"spec hash {own}; export the controller again")
