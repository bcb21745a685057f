"""A finished job's controller as the service hands it out: its files verified against their integrity record
and the job's spec (:mod:`pipelines.controller_integrity`), zipped once into the job directory.
"""

from __future__ import annotations

import hashlib
import os
import uuid
import zipfile
from pathlib import Path
from typing import Any

from pipelines.controller_integrity import (
    INTEGRITY,
    ControllerIntegrityError,
    job_spec_hash,
    read_header,
    verify_header,
)
from pipelines.spec.model import JobSpec, spec_hash
from pipelines.symbolic.files import check_dddmp
from workers.jobdir import CONTROLLER, has_controller

__all__ = ["controller_archive", "controller_files", "verify_controller"]


def controller_files(out_dir: str | os.PathLike[str]) -> list[Path]:
    """The controller's files: the payload files its header lists (a layered controller has several DDDMP
    files, an array controller one ``.npz``), then the header ``controller.json`` itself.

    Raises
    ------
    ControllerIntegrityError
        The header cannot be read or lists no payload files.
    """
    out = Path(out_dir)
    head = out / f"{CONTROLLER}.json"
    roots: Any = [f"{CONTROLLER}.dddmp"]
    if head.exists():
        roots = read_header(head).get("roots")
        if not isinstance(roots, list) or not roots or not all(isinstance(r, str) and Path(r).name == r for r in roots):
            raise ControllerIntegrityError(f"{head}: not a readable controller header (its 'roots' do not list its "
                                           "files); run the job again")
    return [out / name for name in (*roots, head.name)]


def verify_controller(out_dir: str | os.PathLike[str], spec: JobSpec | None = None) -> list[Path]:
    """The controller's files (:func:`controller_files`), each verified against the header's integrity record,
    and the header against the job's spec (``spec``, default ``spec.json``): what a download may serve.

    Raises
    ------
    ControllerIntegrityError
        Naming the file and what differs (:func:`pipelines.controller_integrity.verify_header`).
    """
    files = controller_files(out_dir)
    head = files[-1]
    job_hash = spec_hash(spec) if spec is not None else job_spec_hash(out_dir)
    header = read_header(head)
    verify_header(header, head, [f.name for f in files[:-1]], job_hash)
    # A header resealed by a writer of the job directory passes the checksums: the BDD files' structure is checked
    # too, so that no file a download serves can crash the CUDD that reads it.
    bdd_files = [f for f in files[:-1] if f.suffix == ".dddmp"]
    if bdd_files:
        variables = header.get("variables")
        if not isinstance(variables, list) or not all(isinstance(v, str) for v in variables):
            raise ControllerIntegrityError(f"{head}: not a readable controller header (its 'variables' are not a "
                                           "list of names); run the job again")
        for f in bdd_files:
            check_dddmp(f, variables)
    return files


def _archive_matches(archive: Path, files: list[Path]) -> bool:
    """Whether a made archive holds exactly ``files`` (verified), byte for byte: its header is the one on disk
    and every payload member has the checksum that header records (zip's CRC is checked on reading too)."""
    record = read_header(files[-1])[INTEGRITY]["files"]
    try:
        with zipfile.ZipFile(archive) as z:
            if sorted(z.namelist()) != sorted(f.name for f in files):
                return False
            if z.read(files[-1].name) != files[-1].read_bytes():
                return False
            for f in files[:-1]:
                h = hashlib.sha256()
                with z.open(f.name) as member:
                    for block in iter(lambda: member.read(1 << 20), b""):
                        h.update(block)
                if h.hexdigest() != record[f.name]:
                    return False
    except (OSError, zipfile.BadZipFile, KeyError):
        return False
    return True


def controller_archive(out_dir: str | os.PathLike[str], spec: JobSpec | None = None) -> Path | None:
    """The controller's files as one zip in the job directory (made once: a controller can be gigabytes), or
    ``None`` if the job has no controller; the unzipped files load with :func:`pipelines.controller_loading.load_controller`.

    The files are verified first (:func:`verify_controller`), and a zip made before is served only if it holds
    them byte for byte (else it is made again).

    Raises
    ------
    ControllerIntegrityError
        A controller file is damaged, replaced or of another job: nothing is served.
    """
    if not has_controller(out_dir):
        return None
    files = verify_controller(out_dir, spec)  # a payload file missing is named there
    archive = Path(out_dir) / f"{CONTROLLER}.zip"
    if not archive.is_file() or not _archive_matches(archive, files):
        tmp = archive.with_name(f"{archive.name}.{uuid.uuid4().hex[:8]}.partial")
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            for f in files:
                z.write(f, f.name)
        tmp.replace(archive)  # atomic: two concurrent downloads never see half an archive
    return archive
