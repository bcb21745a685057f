"""A finished job's stored abstraction, read back as it was written (for ``compabs audit``).

A job directory holds ``spec.json`` and ``report.json`` (written last, so a report means the job finished), the
subsystem relations (``relations.zarr`` from a cluster run, layout in :mod:`workers.store`, or
``relations/<key>.npz`` from an ``--in-process`` run), the interconnection abstraction
(``interconnection.npz`` + ``interconnection.json``, written here by :func:`save_interconnection`) and the
controller files (``controller.dddmp``/``.json``, :func:`pipelines.controller.load_controller`).

:func:`load_job` rebuilds the network from ``spec.json`` and reads every stored relation exactly as stored;
nothing is recomputed, so an audit of what it returns checks what a controller was synthesized from. Reading
Zarr needs ``zarr`` (a dependency of the package); it is imported only for a Zarr store.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipelines.errors import CompabsError
from pipelines.grid import UniformGrid
from pipelines.interconnection.core import InterconnectionAbstraction, NodeRelation
from pipelines.network import Network, build_network
from pipelines.spec.model import JobSpec, parse_spec, spec_hash
from pipelines.abstraction.cells import SubsystemRelation

INTERCONNECTION_META = "interconnection.json"
INTERCONNECTION_ARRAYS = "interconnection.npz"
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
    _atomic_write(npz, lambda fh: np.savez_compressed(fh, **arrays))
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


def _load_npz_relations(out: Path, network: Network, params: dict[str, dict[str, Any]]) -> dict[str, SubsystemRelation]:
    rels = {}
    subs = {s.key: s for s in network.subsystems}
    for key, p in params.items():
        path = out / "relations" / f"{key}.npz"
        if not path.exists():
            raise ArtifactError(f"{path} is missing (subsystem '{p['name']}'); run the job again")
        with np.load(path, allow_pickle=False) as data:
            rel = SubsystemRelation(p["method"], data["lo"], data["hi"], data["blocking"], p["L_x"], p["L_w"])
        _check_shape(rel, subs[key], str(path))
        rels[key] = rel
    return rels


def _load_zarr_relations(url: str, spec: JobSpec, network: Network, params: dict[str, dict[str, Any]]) -> tuple[dict[str, SubsystemRelation], dict[str, str]]:
    import zarr

    try:
        root = zarr.open_group(store=url, mode="r", use_consolidated=False)
    except (FileNotFoundError, zarr.errors.BaseZarrError, OSError) as exc:
        raise ArtifactError(f"{url}: not a readable relation store ({exc})") from None
    if root.attrs.get("spec_hash") != spec_hash(spec):
        raise ArtifactError(
            f"{url} holds the relations of spec hash {root.attrs.get('spec_hash')!r}, spec.json has {spec_hash(spec)!r}: "
            "the directory mixes two jobs"
        )
    subs = {s.key: s for s in network.subsystems}
    rels, groups = {}, {}
    for key, p in params.items():
        candidates = []
        for name, g in root.groups():
            a = g.attrs
            if (a.get("key"), a.get("method"), a.get("objective")) != (key, p["method"], p["objective"]):
                continue
            if float(a.get("L_x", np.nan)) != p["L_x"] or float(a.get("L_w", np.nan)) != p["L_w"]:
                continue
            if "done" not in g:
                continue
            done = g["done"][:]
            if all(t for t in done.tolist()):
                candidates.append(name)
        if not candidates:
            raise ArtifactError(
                f"{url}: no complete relation group for subsystem '{p['name']}' (key {key}, L_x = {p['L_x']:g}, "
                f"L_w = {p['L_w']:g}, {p['method']}); the job did not finish: run it again"
            )
        if len(candidates) > 1:
            raise ArtifactError(f"{url}: several complete relation groups {candidates} fit subsystem '{p['name']}'")
        g = root[candidates[0]]
        rel = SubsystemRelation(p["method"], g["lo"][:], g["hi"][:], g["blocking"][:], p["L_x"], p["L_w"])
        _check_shape(rel, subs[key], f"{url}/{candidates[0]}")
        rels[key] = rel
        groups[key] = candidates[0]
    return rels, groups


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
        ``"zarr"`` or ``"npz"``.
    relation_files : dict of str to str
        Per key, the Zarr group or ``.npz`` file the relation came from.
    interconnection : InterconnectionAbstraction
        As stored.
    """

    directory: Path
    spec: JobSpec
    network: Network
    report: dict[str, Any]
    relations: dict[str, SubsystemRelation]
    relation_source: str
    relation_files: dict[str, str] = field(default_factory=dict)
    interconnection: InterconnectionAbstraction | None = None

    @property
    def has_controller(self) -> bool:
        return (self.directory / "controller.json").exists()


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
    for name in ("spec.json", "report.json"):
        if not (out / name).exists():
            raise ArtifactError(
                f"{out / name} is missing: {out} is not a finished job (report.json is written last); run the job"
            )
    try:
        spec = parse_spec(json.loads((out / "spec.json").read_text()))
        report = json.loads((out / "report.json").read_text())
    except ValueError as exc:
        raise ArtifactError(f"{out}: spec.json or report.json is not valid JSON ({exc})") from None
    if report.get("spec_hash") not in (None, spec_hash(spec)):
        raise ArtifactError(f"{out}: report.json (spec hash {report.get('spec_hash')}) and spec.json ({spec_hash(spec)}) "
                            "belong to different jobs")
    network = build_network(spec, allowed_modules)
    params = _relation_params(report, network)
    zarr_dir = out / "relations.zarr"
    if zarr_dir.is_dir():
        rels, groups = _load_zarr_relations(str(zarr_dir), spec, network, params)
        source, files = "zarr", groups
    elif (out / "relations").is_dir():
        rels = _load_npz_relations(out, network, params)
        source, files = "npz", {k: f"relations/{k}.npz" for k in rels}
    else:
        raise ArtifactError(f"{out} holds no relations (relations.zarr or relations/); run the job again")
    ia = load_interconnection(out, spec)
    if ia.n != network.state_dim or ia.p != len(network.internal_grids):
        raise ArtifactError(
            f"{out / INTERCONNECTION_META}: maps {ia.n} states to {ia.p} internal variables; the spec has "
            f"{network.state_dim} and {len(network.internal_grids)}"
        )
    return JobArtifacts(out, spec, network, report, rels, source, files, ia)
