"""The job directory: the one module that knows its layout, and reads and writes every file in it.

::

    DIR/spec.json                    the job spec, as run (:func:`write_spec`)
    DIR/relations.zarr/              the subsystem relations (:mod:`workers.relation_store`), the one relation format
    DIR/interconnection.json, .npz   the interconnection abstraction (:func:`save_interconnection`)
    DIR/controller.dddmp, .json      the controller (:mod:`pipelines.controller`); controller_<fixed point>.* for
                                     the other reach-and-stay fixed point
    DIR/trajectory.png, phase_plane.png, closed_loop_example.json   the figures and the runs they show
    DIR/report.json                  written last, atomically: a report means the job's files are complete
    DIR/audit.json                   written by ``compabs audit DIR`` (:func:`workers.job_audit.audit_job`)
    DIR/resume.json                  what a run of the same spec reads back (:mod:`workers.resume`)
    DIR/checkpoints/                 the safety fixed points' last iterates while synthesis runs, removed once the
                                     controller is written or the service ends the job cancelled or failed
                                     (:mod:`workers.checkpoint_store` reads and writes them)

:func:`load_job` rebuilds the network from ``spec.json`` and reads every stored relation exactly as stored;
nothing is recomputed, so an audit of what it returns checks what a controller was synthesized from. Every
relation chunk is verified against the checksum in its done-marker; damaged chunks are returned, named, for
the audit to report (``JobArtifacts.damaged_chunks``).

Interconnection files
---------------------
``interconnection.json``: ``format`` (:data:`INTERCONNECTION_FORMAT`), ``spec_hash``, ``mode``,
``output_modes``, ``supports``, ``intermediate_grids`` (name -> :meth:`UniformGrid.describe`), ``details`` and
per node ``output``, ``inputs``, ``output_grid``, ``input_grids``, ``weights``, ``error_bound``.
``interconnection.npz``: ``M_bar``, ``offsets``, ``error_bounds`` and per node ``k`` (in the JSON's order,
which is topological) ``node{k}_lo`` and ``node{k}_hi``.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.controller_integrity import JsonMessages, read_json_object
from pipelines.errors import CompabsError, SpecError
from pipelines.grid import UniformGrid
from pipelines.interconnection import InterconnectionAbstraction, NodeRelation
from pipelines.network import Network, build_network
from pipelines.spec.model import JobSpec, parse_spec, spec_hash
from workers.errors import StoreError, StoreMismatchError

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    import zarr

SPEC = "spec.json"
REPORT = "report.json"
RELATIONS = "relations.zarr"
INTERCONNECTION_META = "interconnection.json"
INTERCONNECTION_ARRAYS = "interconnection.npz"
#: Name (without suffix) of the controller files.
CONTROLLER = "controller"
#: Directory of the synthesis checkpoints (:mod:`workers.checkpoint_store`).
CHECKPOINTS = "checkpoints"
EXAMPLE_RUN = "closed_loop_example.json"
AUDIT = "audit.json"
RESUME = "resume.json"
#: Version of the interconnection files' layout.
INTERCONNECTION_FORMAT = 1


class ArtifactError(CompabsError):
    """A job directory lacks a file the audit needs, or holds one that does not fit its spec."""


def _json_safe(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): _json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_json_safe(v) for v in o]
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return _json_safe(o.tolist())
    return o


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as fh:
        write(fh)
    tmp.replace(path)


def json_default(o: Any) -> Any:
    """``json.dumps`` fallback for numpy scalars and arrays in reports."""
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# ====================================================================================== paths and small files
def create(out_dir: str | os.PathLike[str]) -> Path:
    """The job directory, created if needed."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SpecError(f"--out {out}: cannot create the directory: {exc.strerror}") from None
    return out


# ====================================================================================== claiming a directory
def _writable(directory: Path) -> None:
    """Create and remove a file in ``directory``: a read-only one fails here, at the start of a job."""
    probe = directory / f".compabs-write-check-{uuid.uuid4().hex[:8]}"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        probe.unlink()
    except OSError as exc:
        raise StoreError(f"--out {directory}: cannot write in this directory ({exc.strerror or exc}); fix its "
                         "permissions or give another output directory") from None


def _job_files(out: Path) -> list[Path]:
    """The job files (other than the relation store) in ``out``, report.json first."""
    named = [out / n for n in (REPORT, SPEC, AUDIT, RESUME, INTERCONNECTION_META, INTERCONNECTION_ARRAYS, EXAMPLE_RUN,
                               "trajectory.png", "phase_plane.png", "domain_slice.png")]
    named += sorted(p for ext in ("dddmp", "json", "zip") for p in out.glob(f"{CONTROLLER}*.{ext}"))
    return [p for p in dict.fromkeys(named) if p.is_file()]


def _stored_hashes(out: Path) -> set[str]:
    """The spec hashes the job files of ``out`` belong to (report.json's ``spec_hash``, spec.json's spec)."""
    hashes = set()
    try:
        if (out / REPORT).is_file():
            report = json.loads((out / REPORT).read_text())
            hashes.add(str(report.get("spec_hash")) if isinstance(report, dict) else "(not a compabs report)")
        if (out / SPEC).is_file():
            hashes.add(spec_hash(parse_spec(json.loads((out / SPEC).read_text()))))
    except (OSError, ValueError, CompabsError) as exc:
        hashes.add(f"(unreadable: {type(exc).__name__})")
    return hashes - {"None"}


def claim(out_dir: str | os.PathLike[str], spec: JobSpec, *, overwrite: bool = False) -> tuple[Path, Path | None]:
    """Create (or take over) the job directory of ``spec``; returns it and the topmost directory this call created
    (``out_dir`` or an ancestor; ``None`` if it existed), which :func:`discard_unused` removes after a failure.

    Raises
    ------
    StoreMismatchError
        ``out_dir`` holds the files of another spec's job (report.json or spec.json of another spec hash),
        unless ``overwrite``, which deletes them (report.json first; the relation store is checked, and with
        ``overwrite`` replaced, by :meth:`workers.relation_store.RelationStore.open`).
    StoreError, SpecError
        ``out_dir`` (or its relation store) cannot be written, or created: at the start, not after the work.
    """
    out = Path(out_dir)
    created = None
    for d in (out, *out.parents):
        if os.path.lexists(d):
            break
        created = d
    out = create(out)
    try:
        for d in (out, out / RELATIONS):
            if d == out or d.is_dir():
                _writable(d)
        mine = spec_hash(spec)
        theirs = sorted(_stored_hashes(out) - {mine})
        if theirs and not overwrite:
            raise StoreMismatchError(
                f"{out} holds the files of another job (spec hash {', '.join(theirs)}; this job: {mine}): its "
                f"{REPORT} would be overwritten. Use another output directory, or pass --overwrite (overwrite=True) "
                "to delete them and recompute."
            )
        if theirs:
            for path in _job_files(out):
                path.unlink()
    except BaseException:
        if created is not None:
            discard_unused(created)
        raise
    return out, created


def discard_unused(out_dir: str | os.PathLike[str]) -> bool:
    """Remove a directory that holds no work (no file but Zarr metadata): what a run that created it (``claim``)
    and failed before storing anything leaves. Returns whether it was removed."""
    out = Path(out_dir)
    for _root, _dirs, files in os.walk(out):
        if any(name != "zarr.json" for name in files):
            return False
    shutil.rmtree(out, ignore_errors=True)
    return not out.exists()


def relations_url(out_dir: str | os.PathLike[str]) -> str:
    """Where the relation store of a job directory (or fsspec URL) lives."""
    s = os.fspath(out_dir)
    if "://" in s:
        return s.rstrip("/") + "/" + RELATIONS
    return str(Path(s) / RELATIONS)


def figure(out_dir: str | os.PathLike[str], name: str) -> Path:
    """The path of figure ``name`` (``trajectory``, ``phase_plane``; ``domain_slice`` in jobs of older versions)."""
    return Path(out_dir) / f"{name}.png"


def write_spec(out_dir: str | os.PathLike[str], spec: JobSpec) -> Path:
    path = Path(out_dir) / SPEC
    path.write_text(json.dumps(spec.model_dump(mode="json"), indent=1))
    return path


def write_report(out_dir: str | os.PathLike[str], report: dict[str, Any]) -> Path:
    """``report.json``, through a temporary and a rename: a report on disk means the job's files are complete."""
    path = Path(out_dir) / REPORT
    _atomic_write(path, lambda fh: fh.write(json.dumps(report, indent=2, default=json_default).encode()))
    return path


def write_audit(out_dir: str | os.PathLike[str], audit: dict[str, Any]) -> Path:
    path = Path(out_dir) / AUDIT
    _atomic_write(path, lambda fh: fh.write(json.dumps(audit, indent=2, default=json_default).encode()))
    return path


def write_example_run(out_dir: str | os.PathLike[str], runs: dict[str, Any]) -> Path:
    path = Path(out_dir) / EXAMPLE_RUN
    path.write_text(json.dumps(runs))
    return path


def has_controller(out_dir: str | os.PathLike[str]) -> bool:
    return (Path(out_dir) / f"{CONTROLLER}.json").exists()


def report_path(out_dir: str | os.PathLike[str]) -> Path:
    return Path(out_dir) / REPORT


# ====================================================================================== interconnection
def save_interconnection(ia: InterconnectionAbstraction, out_dir: str | os.PathLike[str], spec: JobSpec | None = None) -> tuple[Path, Path]:
    """Write the interconnection abstraction into a job directory (arrays first, then the JSON header).

    Parameters
    ----------
    ia : InterconnectionAbstraction
    out_dir : path
        The job directory (must exist).
    spec : JobSpec, optional
        Its hash is recorded, so that files of another spec are refused when loaded.

    Returns
    -------
    (Path, Path)
        The ``.npz`` and ``.json`` files.
    """
    out = Path(out_dir)
    arrays: dict[str, np.ndarray] = {
        "M_bar": np.asarray(ia.M_bar, dtype=float),
        "offsets": np.asarray(ia.offsets, dtype=float),
        "error_bounds": np.asarray(ia.error_bounds, dtype=float),
    }
    nodes = []
    for k, node in enumerate(ia.nodes):
        arrays[f"node{k}_lo"] = np.asarray(node.lo)
        arrays[f"node{k}_hi"] = np.asarray(node.hi)
        nodes.append({
            "output": node.output,
            "inputs": list(node.inputs),
            "output_grid": node.output_grid.describe(),
            "input_grids": [g.describe() for g in node.input_grids],
            "weights": None if node.weights is None else [float(a) for a in node.weights],
            "error_bound": float(node.error_bound),
        })
    meta = {
        "format": INTERCONNECTION_FORMAT,
        "spec_hash": None if spec is None else spec_hash(spec),
        "mode": ia.mode,
        "output_modes": list(ia.output_modes),
        "supports": [list(s) for s in ia.supports],
        "intermediate_grids": {k: g.describe() for k, g in ia.intermediate_grids.items()},
        "nodes": nodes,
        "details": _json_safe(ia.details),
    }
    npz, js = out / INTERCONNECTION_ARRAYS, out / INTERCONNECTION_META
    # (The keys are array names, never savez's own allow_pickle: the cast only tells mypy so.)
    _atomic_write(npz, lambda fh: np.savez_compressed(fh, **cast(dict[str, Any], arrays)))
    _atomic_write(js, lambda fh: fh.write(json.dumps(meta, indent=1).encode()))
    return npz, js


def load_interconnection(out_dir: str | os.PathLike[str], spec: JobSpec | None = None) -> InterconnectionAbstraction:
    """Read the interconnection abstraction :func:`save_interconnection` wrote.

    Raises
    ------
    ArtifactError
        The files are missing, damaged, of another layout, or (with ``spec``) of another spec.
    """
    out = Path(out_dir)
    npz, js = out / INTERCONNECTION_ARRAYS, out / INTERCONNECTION_META
    if not npz.exists() or not js.exists():
        raise ArtifactError(
            f"{out}: no stored interconnection abstraction ({INTERCONNECTION_META} and {INTERCONNECTION_ARRAYS}); "
            "it is written by 'compabs run' (jobs run before it was persisted, or with --in-process --no-synthesis, "
            "lack it). Run the job again into this directory: stored relation chunks are reused."
        )
    try:
        meta = json.loads(js.read_text())
        with np.load(npz, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise ArtifactError(f"{out}: the stored interconnection abstraction cannot be read ({exc}); run the job again") from None
    if meta.get("format") != INTERCONNECTION_FORMAT:
        raise ArtifactError(f"{js}: layout {meta.get('format')!r}, this version reads {INTERCONNECTION_FORMAT}; run the job again")
    if spec is not None and meta.get("spec_hash") not in (None, spec_hash(spec)):
        raise ArtifactError(f"{js} was written for another spec (hash {meta.get('spec_hash')}, spec.json: {spec_hash(spec)})")
    try:
        nodes = []
        for k, nd in enumerate(meta["nodes"]):
            nodes.append(NodeRelation(
                output=nd["output"],
                output_grid=UniformGrid.from_description(nd["output_grid"]),
                inputs=tuple(nd["inputs"]),
                input_grids=tuple(UniformGrid.from_description(g) for g in nd["input_grids"]),
                weights=None if nd["weights"] is None else tuple(float(a) for a in nd["weights"]),
                lo=arrays[f"node{k}_lo"],
                hi=arrays[f"node{k}_hi"],
                error_bound=float(nd["error_bound"]),
            ))
        return InterconnectionAbstraction(
            mode=meta["mode"],
            M_bar=arrays["M_bar"],
            supports=tuple(tuple(int(i) for i in s) for s in meta["supports"]),
            offsets=arrays["offsets"],
            error_bounds=arrays["error_bounds"],
            nodes=tuple(nodes),
            intermediate_grids={k: UniformGrid.from_description(g) for k, g in meta["intermediate_grids"].items()},
            output_modes=tuple(meta["output_modes"]),
            details=meta.get("details", {}),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ArtifactError(f"{out}: the stored interconnection abstraction is damaged ({type(exc).__name__}: {exc}); "
                            "run the job again") from None


# ====================================================================================== subsystem relations
def _relation_params(report: dict[str, Any], network: Network) -> dict[str, dict[str, Any]]:
    """Per subsystem key, what the report says its final relation was computed with."""
    by_name = {s.name: s for s in network.subsystems}
    out: dict[str, dict[str, Any]] = {}
    for info in report.get("subsystems", []):
        sub = by_name.get(info["name"])
        if sub is None:
            raise ArtifactError(f"report.json names subsystem '{info['name']}', which spec.json does not define")
        lip = info["lipschitz"]
        out[sub.key] = {
            "name": info["name"],
            "members": info.get("members", [info["name"]]),
            "method": info["growth_bound"],
            "objective": info.get("scp_objective", "paper"),
            "L_x": float(lip["x"]["value"]),
            "L_w": float(lip["w"]["value"]),
        }
    missing = {s.key for s in network.subsystems} - set(out)
    if missing:
        names = sorted(s.name for s in network.subsystems if s.key in missing)
        raise ArtifactError(f"report.json has no relation for subsystems {names}; the job did not finish: run it again")
    return out


def _check_shape(rel: SubsystemRelation, sub, where: str) -> None:
    n_x, n_u, n_w, n = sub.state_grid.size, sub.input_grid.size, sub.n_w_cells, sub.n
    if rel.lo.shape != (n_x, n_u, n_w, n) or rel.hi.shape != rel.lo.shape or rel.blocking.shape != (n_x, n_u, n_w):
        raise ArtifactError(
            f"{where}: arrays of shape lo {rel.lo.shape}, blocking {rel.blocking.shape}; subsystem '{sub.name}' needs "
            f"{(n_x, n_u, n_w, n)} and {(n_x, n_u, n_w)}: the store does not belong to this spec"
        )


def _load_zarr_relations(url: str, spec: JobSpec, network: Network, params: dict[str, dict[str, Any]]
                         ) -> tuple[dict[str, SubsystemRelation], dict[str, str], list[dict[str, Any]], int]:
    """The stored relations, each chunk verified against its checksum (:func:`workers.relation_store.check_chunks`).

    Returns the relations (by subsystem key), their groups, the damaged chunks (``group``, ``subsystem``,
    ``chunk``, ``start``, ``stop``, ``reason``, ``message``) and the number of chunks checked. A damaged chunk's
    data are kept as read when they can be read (the audit checks them too); cells that cannot be read are
    blocking (their transitions are skipped, the chunk is reported).
    """
    import zarr

    from workers.relation_store import LAYOUT_VERSION, check_chunks, chunk_place, group_markers

    try:
        root = zarr.open_group(store=url, mode="r", use_consolidated=False)
    except (FileNotFoundError, zarr.errors.BaseZarrError, OSError) as exc:
        raise ArtifactError(f"{url}: not a readable relation store ({exc})") from None
    if root.attrs.get("spec_hash") != spec_hash(spec):
        raise ArtifactError(
            f"{url} holds the relations of spec hash {root.attrs.get('spec_hash')!r}, spec.json has {spec_hash(spec)!r}: "
            "the directory mixes two jobs"
        )
    if root.attrs.get("layout") != LAYOUT_VERSION:
        raise ArtifactError(
            f"{url} has store layout {root.attrs.get('layout')!r}; this version reads layout {LAYOUT_VERSION} (chunks "
            "with checksums) and cannot verify it. Run the job again into this directory with --overwrite."
        )
    subs = {s.key: s for s in network.subsystems}
    rels, groups, damaged, checked = {}, {}, [], 0
    for key, p in params.items():
        candidates = []
        for name, g in root.groups():
            a = g.attrs
            if (a.get("key"), a.get("method"), a.get("objective")) != (key, p["method"], p["objective"]):
                continue
            # Numbers the store wrote (zarr types an attribute as any JSON value).
            L_x, L_w = cast(float, a.get("L_x", np.nan)), cast(float, a.get("L_w", np.nan))
            if float(L_x) != p["L_x"] or float(L_w) != p["L_w"]:
                continue
            if "done" not in g or "lo" not in g:
                continue
            markers, bad = group_markers(g)
            if len(markers) + len(bad) == cast("zarr.Array", g["done"]).shape[0]:  # every chunk marked (or damaged)
                candidates.append((name, markers, bad))
        if not candidates:
            raise ArtifactError(
                f"{url}: no complete relation group for subsystem '{p['name']}' (key {key}, L_x = {p['L_x']:g}, "
                f"L_w = {p['L_w']:g}, {p['method']}); the job did not finish: run it again"
            )
        if len(candidates) > 1:
            raise ArtifactError(f"{url}: several complete relation groups {[c[0] for c in candidates]} fit subsystem "
                                f"'{p['name']}'")
        name, markers, bad = candidates[0]
        g = cast("zarr.Group", root[name])  # a name from root.groups()
        check = check_chunks(g, name, markers, whole=True)
        lo, hi, blocking = (check.arrays[k] for k in ("lo", "hi", "blocking"))
        rel = SubsystemRelation(p["method"], lo, hi, blocking, p["L_x"], p["L_w"])
        _check_shape(rel, subs[key], f"{url}/{name}")
        chunk_cells, n_x = int(cast("zarr.Array", g["lo"]).chunks[0]), lo.shape[0]
        checked += -(-n_x // chunk_cells)
        for i, reason in sorted({**bad, **check.damaged}.items()):
            start, stop = i * chunk_cells, min((i + 1) * chunk_cells, n_x)
            if i in check.unreadable:  # no data to audit: skipped as blocking
                lo[start:stop], hi[start:stop], blocking[start:stop] = 0, -1, True
            damaged.append({"group": name, "subsystem": p["name"], "chunk": i, "start": start, "stop": stop,
                            "reason": reason, "message": f"{chunk_place(name, i, chunk_cells, n_x)}: {reason}"})
        rels[key] = rel
        groups[key] = name
    return rels, groups, damaged, checked


# ====================================================================================== the whole job
@dataclass
class JobArtifacts:
    """What a finished job stored, read back.

    Attributes
    ----------
    directory : Path
    spec : JobSpec
        From ``spec.json``.
    network : Network
        Built from the spec (black boxes compiled again).
    report : dict
        ``report.json``.
    relations : dict of str to SubsystemRelation
        By subsystem key, as stored.
    relation_source : str
        ``"zarr"`` (the one format).
    relation_files : dict of str to str
        Per key, the Zarr group the relation came from.
    interconnection : InterconnectionAbstraction
        As stored.
    damaged_chunks : list of dict
        Relation chunks that are missing, unreadable or do not match their checksum (``group``, ``subsystem``,
        ``chunk``, ``start``, ``stop``, ``reason``, ``message``); their cells are as read (blocking where unreadable).
    chunks_checked : int
        Relation chunks verified against their checksums.
    """

    directory: Path
    spec: JobSpec
    network: Network
    report: dict[str, Any]
    relations: dict[str, SubsystemRelation]
    relation_source: str
    relation_files: dict[str, str] = field(default_factory=dict)
    interconnection: InterconnectionAbstraction | None = None
    damaged_chunks: list[dict[str, Any]] = field(default_factory=list)
    chunks_checked: int = 0

    @property
    def has_controller(self) -> bool:
        return has_controller(self.directory)


#: A job file that cannot be read: the job directory is damaged.
JOB_FILE_MESSAGES = JsonMessages(
    "{path}: cannot read the job's {what} ({reason})",
    "{path}: damaged: the job's {what} is not valid JSON ({reason}); run the job again",
    "{path}: damaged: the job's {what} is a JSON {reason}, not an object; run the job again",
)


def _read_json_object(path: Path, what: str) -> dict[str, Any]:
    """A job file's JSON object; one that is unreadable, not JSON or not an object is named (damaged)."""
    return read_json_object(path, what, ArtifactError, JOB_FILE_MESSAGES)


def _read_spec_file(path: Path) -> JobSpec:
    """The job's ``spec.json``; a damaged one is named."""
    try:
        return parse_spec(_read_json_object(path, "spec"))
    except SpecError as exc:
        raise ArtifactError(f"{path}: damaged: the job's spec is not a valid spec ({exc}); run the job again") from None


def load_job(directory: str | os.PathLike[str], allowed_modules: Sequence[str] | None = None) -> JobArtifacts:
    """Read a finished job's directory: spec, report, stored relations and interconnection abstraction.

    Parameters
    ----------
    directory : path
        What ``compabs run --out`` (or the service) wrote.
    allowed_modules : sequence of str, optional
        Modules a ``module:function`` black box may come from (``None``: any, as on the local command line).

    Raises
    ------
    ArtifactError
        A file is missing, damaged, or belongs to another spec; the message says which and what to do.
    CompabsError
        The spec no longer builds (e.g. a ``module:function`` that cannot be imported here).
    """
    out = Path(directory)
    if not out.is_dir():
        raise ArtifactError(f"{out} is not a directory; give the --out directory of a finished 'compabs run'")
    for name in (SPEC, REPORT):
        if not (out / name).exists():
            raise ArtifactError(
                f"{out / name} is missing: {out} is not a finished job (report.json is written last); run the job"
            )
    spec = _read_spec_file(out / SPEC)
    report = _read_json_object(out / REPORT, "report")
    if report.get("spec_hash") not in (None, spec_hash(spec)):
        raise ArtifactError(f"{out}: report.json (spec hash {report.get('spec_hash')}) and spec.json ({spec_hash(spec)}) "
                            "belong to different jobs")
    network = build_network(spec, allowed_modules)
    try:
        params = _relation_params(report, network)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ArtifactError(f"{out / REPORT}: damaged: its subsystems' entries are incomplete ({type(exc).__name__}: "
                            f"{exc}); run the job again") from None
    zarr_dir = out / RELATIONS
    if not zarr_dir.is_dir():
        raise ArtifactError(f"{out} holds no relations ({RELATIONS}); run the job again")
    rels, files, damaged, checked = _load_zarr_relations(str(zarr_dir), spec, network, params)
    ia = load_interconnection(out, spec)
    if ia.n != network.state_dim or ia.p != len(network.internal_grids):
        raise ArtifactError(
            f"{out / INTERCONNECTION_META}: maps {ia.n} states to {ia.p} internal variables; the spec has "
            f"{network.state_dim} and {len(network.internal_grids)}"
        )
    return JobArtifacts(out, spec, network, report, rels, "zarr", files, ia, damaged, checked)
