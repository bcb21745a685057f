"""The relation store: subsystem relations as Zarr v3 arrays, written chunk by chunk by tasks.

Layout under ``DIR/relations.zarr`` (``DIR`` a local path or any fsspec URL)::

    relations.zarr/                 root group; attributes:
                                      layout        store layout version (LAYOUT_VERSION)
                                      spec_hash     pipelines.spec.model.spec_hash of the job that wrote it
                                      spec_name     the spec's name (for people)
                                      code_version  the compabs package version that wrote it
                                      grids         subsystem name -> {key, state, input, internal, groups}
                                                    (UniformGrid.describe(); groups: its relation groups)
      <key>-<digest>/               one group per distinct subsystem AND per (L_x, L_w, method, objective,
                                    chunk_cells): a raised Lipschitz constant or another chunking names another
                                    group, so stale chunks are never read. Attributes: subsystem, members,
                                    key, L_x, L_w, method, objective, chunk_cells, n_chunks.
        lo        int32 (n_x, n_u, n_w, n)   successor index range per triple (Definition 4.2) ...
        hi        int32 (n_x, n_u, n_w, n)   ... empty (0, -1) where blocking
        blocking  bool  (n_x, n_u, n_w)      input not admissible at that state under that internal cell
        done      string (n_chunks,)         per chunk, its done-marker: the JSON of the chunk's metadata
                                             (start, stop, successors, slope_x, slope_w, seconds); "" = not done

``lo``, ``hi`` and ``blocking`` are chunked along the state cells with ``chunk_cells`` cells per chunk (all
inputs and internal cells in the chunk), which is exactly one task's range: each task owns whole chunks
(ENGINEERING "Zarr 3": half-chunk writes from two processes lose rows). Codec ``BloscCodec(zstd, bitshuffle)``.

``done`` has one element per chunk and chunks of one element, so a task owns its marker's chunk too. The task
writes its marker *after* its data: a marker says the data are complete. A chunk's data without a marker (a
task killed between the two writes, or a marker deleted) is recomputed; data chunks that are missing while
their marker exists are all-fill chunks Zarr did not write (``write_empty_chunks=False``), which read back as
the fill value, i.e. correctly. Keeping markers in a Zarr array (not loose files) keeps the hierarchy valid for
Zarr readers and consolidation; local writes are atomic (temp file + rename), and the ``*.partial`` temporaries
a killed writer leaves are never read, because Zarr reads exact keys and never lists chunk directories.

Consolidated metadata is written once at the end of a job (:meth:`RelationStore.consolidate`). The runner
itself always opens the store without it, so groups added after a consolidation are seen.

A store whose ``spec_hash``, ``code_version`` or ``layout`` differs from the job's is never reused: opening it
raises :class:`StoreMismatchError` (nothing is deleted), unless the caller passes ``overwrite=True``, which
deletes the stale store and starts a new one. Refusing is the default because a store may hold hours of
work of another job and ``--out`` may simply be mistyped.

One runner per store at a time: groups are created by the runner, chunks by its tasks.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from pipelines.abstraction.relation import CellsResult, SlopeRecord
from pipelines.network import Network, Subsystem
from pipelines.spec.model import JobSpec, spec_hash
from workers.errors import StoreError, StoreMismatchError
from workers.jobdir import relations_url

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from zarr.core.common import JSON

#: Version of the layout above; a store of another layout is treated as stale.
LAYOUT_VERSION = 1
RELATION_ARRAYS = ("lo", "hi", "blocking")


def code_version() -> str:
    """The installed compabs version ("unknown" when running from an uninstalled tree)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("compabs")
    except PackageNotFoundError:
        return "unknown"


def group_name(sub: Subsystem, L_x: float, L_w: float, method: str, objective: str, chunk_cells: int) -> str:
    """The group of a subsystem's relation computed with these constants and this chunking.

    ``sub.key`` already identifies the subsystem's spec, internal grid and parameters; the digest adds what the
    per-cell stage is given on top (float constants by their exact hex form, so 0.98 and 0.98000001 differ).
    """
    ident = {
        "L_x": float(L_x).hex(),
        "L_w": float(L_w).hex(),
        "method": method,
        "objective": objective,
        "chunk_cells": int(chunk_cells),
    }
    digest = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:12]
    return f"{sub.key}-{digest}"


def _compressors() -> list:
    from zarr.codecs import BloscCodec

    # bitshuffle suits small integer index arrays (ENGINEERING "Zarr 3").
    return [BloscCodec(cname="zstd", clevel=5, shuffle="bitshuffle")]


def _wipe(url: str) -> None:
    import fsspec

    fs, path = fsspec.core.url_to_fs(url)
    if fs.exists(path):
        fs.rm(path, recursive=True)


def _open_root(url: str, mode: Literal["r", "r+", "a", "w", "w-"]):
    import zarr

    return zarr.open_group(store=url, mode=mode, use_consolidated=False)


# ------------------------------------------------------------------ markers: CellsResult metadata <-> JSON
def marker(result: CellsResult, seconds: float) -> dict[str, Any]:
    """The done-marker of a computed chunk: everything of a CellsResult except its arrays.

    Floats survive JSON exactly (``repr`` round-trips float64), so a rebuilt result equals the computed one.
    """
    return {
        "start": int(result.start),
        "stop": int(result.stop),
        "successors": {k: [int(s), int(n)] for k, (s, n) in result.successors.items()},
        "slope_x": _slope_dict(result.slope_x),
        "slope_w": _slope_dict(result.slope_w),
        "seconds": float(seconds),
    }


def _slope_dict(r: SlopeRecord) -> dict[str, Any]:
    return {"slope": float(r.slope), "x_cell": int(r.x_cell), "u_index": int(r.u_index), "w_cell": int(r.w_cell)}


def result_from(meta: dict[str, Any], lo: np.ndarray, hi: np.ndarray, blocking: np.ndarray) -> CellsResult:
    """Rebuild a chunk's :class:`CellsResult` from its marker and its arrays (shapes as in CellsResult)."""
    return CellsResult(
        int(meta["start"]),
        int(meta["stop"]),
        lo,
        hi,
        blocking,
        {k: (int(s), int(n)) for k, (s, n) in meta["successors"].items()},
        SlopeRecord(**meta["slope_x"]),
        SlopeRecord(**meta["slope_w"]),
    )


# ------------------------------------------------------------------ the task side
@dataclass
class _ChunkWriter:
    """Open arrays of one group, as a worker sees them."""

    lo: Any
    hi: Any
    blocking: Any
    done: Any

    @property
    def chunk_cells(self) -> int:
        return int(self.lo.chunks[0])


# Array metadata never changes under a group name (the name fixes shapes and chunking), so a worker process
# may keep arrays open across tasks: this saves four metadata reads per task. Bounded: one entry per group.
_WRITERS: dict[tuple[str, str], _ChunkWriter] = {}


def _writer(url: str, group: str) -> _ChunkWriter:
    w = _WRITERS.get((url, group))
    if w is None:
        import zarr

        try:
            g = zarr.open_group(store=url, path=group, mode="r+", use_consolidated=False)
            w = _ChunkWriter(g["lo"], g["hi"], g["blocking"], g["done"])
        except (FileNotFoundError, KeyError) as exc:
            raise StoreError(
                f"relation store {url}: group {group} is missing ({exc}); the store was deleted or replaced "
                "while the job ran. Run the job again."
            ) from None
        if len(_WRITERS) > 64:
            _WRITERS.clear()
        _WRITERS[(url, group)] = w
    return w


def write_chunk(url: str, group: str, result: CellsResult, seconds: float) -> dict[str, Any]:
    """Write one chunk's arrays, then its done-marker; return the marker.

    The range ``[result.start, result.stop)`` must be exactly one chunk of the group's arrays: a task owns
    whole chunks (the last chunk may be shorter, ending at ``n_x``).

    Raises
    ------
    StoreError
        The group does not exist, or the range is not one whole chunk (a runner bug).
    """
    w = _writer(url, group)
    c = w.chunk_cells
    n_x = int(w.lo.shape[0])
    start, stop = result.start, result.stop
    if start % c or stop != min(start + c, n_x):
        raise StoreError(f"relation store {url}: cells [{start}, {stop}) are not one chunk of {c} cells in {group}")
    # Data first, marker last: a marker means the data are complete.
    w.lo[start:stop] = result.lo
    w.hi[start:stop] = result.hi
    w.blocking[start:stop] = result.blocking
    meta = marker(result, seconds)
    w.done[start // c] = json.dumps(meta, sort_keys=True)
    return meta


# ------------------------------------------------------------------ the runner side
class RelationStore:
    """A relation store opened by a job's runner.

    Use :meth:`open`; then per distinct subsystem :meth:`prepare`, :meth:`markers`, :meth:`read`, and
    :meth:`consolidate` at the end. Tasks write through :func:`write_chunk` with :attr:`url` and a group name.
    """

    def __init__(self, url: str, root: Any) -> None:
        self.url = url
        self._root = root

    # ---------------------------------------------------------------- opening
    @classmethod
    def open(cls, out_dir: str | os.PathLike[str], spec: JobSpec, network: Network, *, overwrite: bool = False) -> RelationStore:
        """Open (or create) the store of ``out_dir`` for a job.

        Parameters
        ----------
        overwrite : bool
            If the store was written for another spec (or compabs version, or layout), delete it and start a
            new one instead of refusing. A store of the same spec is always kept and reused (resume).

        Raises
        ------
        StoreMismatchError
            The store belongs to another spec, compabs version or layout and ``overwrite`` is false.
        StoreError
            The location cannot be read or written.
        """
        import zarr

        url = relations_url(out_dir)
        want: dict[str, JSON] = {"layout": LAYOUT_VERSION, "spec_hash": spec_hash(spec), "code_version": code_version()}
        try:
            try:
                root = _open_root(url, "r+")
            except (FileNotFoundError, zarr.errors.BaseZarrError):  # nothing there, or not a group
                root = None
            if root is not None:
                have = {k: root.attrs.get(k) for k in want}
                if have != want:
                    if not overwrite:
                        raise StoreMismatchError(cls._mismatch_message(url, have, want, root.attrs.get("spec_name")))
                    _wipe(url)
                    root = None
            elif _exists(url):
                if not overwrite:
                    raise StoreMismatchError(
                        f"{url} exists but is not a compabs relation store. Use another output directory, or "
                        "pass --overwrite (overwrite=True) to delete it."
                    )
                _wipe(url)
            if root is None:
                attrs = dict(want, spec_name=spec.name, grids=_grids(network))
                root = zarr.open_group(store=url, mode="w", attributes=attrs, use_consolidated=False)
        except OSError as exc:
            raise StoreError(f"relation store {url}: {exc}. Check the path (or URL) and its permissions.") from None
        return cls(url, root)

    @staticmethod
    def _mismatch_message(url: str, have: dict, want: dict, name: str | None) -> str:
        diffs = ", ".join(f"{k} {have[k]!r} (this job: {want[k]!r})" for k in want if have[k] != want[k])
        return (
            f"{url} holds the relations of another job ('{name}'): {diffs}. Its chunks cannot be reused for this "
            "spec. Use another output directory, or pass --overwrite (overwrite=True) to delete the store and "
            "recompute."
        )

    # ---------------------------------------------------------------- per subsystem
    def prepare(self, group: str, sub: Subsystem, members: list[str], chunk_cells: int, attrs: dict[str, Any]) -> None:
        """Create a group's arrays if they do not exist; check them if they do.

        Parameters
        ----------
        chunk_cells : int
            State cells per chunk = per task.
        attrs : dict
            Extra group attributes (constants, method, objective).
        """
        n_x, n_u, n_w, n = sub.state_grid.size, sub.input_grid.size, sub.n_w_cells, sub.n
        n_chunks = -(-n_x // chunk_cells)
        shapes = {
            "lo": ((n_x, n_u, n_w, n), (chunk_cells, n_u, n_w, n), "int32", 0),
            "hi": ((n_x, n_u, n_w, n), (chunk_cells, n_u, n_w, n), "int32", 0),
            "blocking": ((n_x, n_u, n_w), (chunk_cells, n_u, n_w), "bool", False),
        }
        if group in self._root and "done" not in self._root[group]:
            # A runner died while creating this group (`done` is created last): nothing was computed in it.
            del self._root[group]
        if group in self._root:
            g = self._root[group]
            for name, (shape, chunks, _, _) in shapes.items():
                a = g[name]
                if tuple(a.shape) != shape or tuple(a.chunks) != chunks:
                    raise StoreError(
                        f"relation store {self.url}: {group}/{name} has shape {a.shape} chunks {a.chunks}, "
                        f"expected {shape} {chunks}; the store is damaged. Delete it and run the job again."
                    )
            return
        g = self._root.create_group(group, attributes=dict(
            attrs, subsystem=sub.name, members=members, key=sub.key, chunk_cells=chunk_cells, n_chunks=n_chunks))
        for name, (shape, chunks, dtype, fill) in shapes.items():
            g.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill, compressors=_compressors())
        # Created last: a group with a `done` array has all its arrays.
        g.create_array("done", shape=(n_chunks,), chunks=(1,), dtype=str, fill_value="")
        grids = dict(self._root.attrs.get("grids", {}))
        for m in members:
            if m in grids:
                grids[m] = dict(grids[m], groups=sorted(set(grids[m].get("groups", [])) | {group}))
        self._root.attrs["grids"] = grids

    def write(self, group: str, result: CellsResult, seconds: float) -> dict[str, Any]:
        """Write one computed chunk and its marker (:func:`write_chunk`)."""
        return write_chunk(self.url, group, result, seconds)

    def markers(self, group: str) -> dict[int, dict[str, Any]]:
        """Done-markers of a group: chunk index -> metadata. Unreadable markers count as not done."""
        done = self._root[group]["done"][:]
        out: dict[int, dict[str, Any]] = {}
        for i, text in enumerate(done.tolist()):
            if not text:
                continue
            try:
                out[i] = json.loads(text)
            except ValueError:  # a damaged marker: recompute that chunk
                continue
        return out

    def read(self, group: str, meta: dict[str, Any], arrays: dict[str, np.ndarray] | None = None) -> CellsResult:
        """Rebuild the CellsResult of a done chunk.

        Parameters
        ----------
        arrays : dict, optional
            The group's whole ``lo``, ``hi``, ``blocking`` already read (see :meth:`read_all`), to slice instead
            of reading chunk by chunk.
        """
        s = slice(int(meta["start"]), int(meta["stop"]))
        if arrays is None:
            g = self._root[group]
            lo, hi, bl = g["lo"][s], g["hi"][s], g["blocking"][s]
        else:
            lo, hi, bl = (np.array(arrays[k][s]) for k in RELATION_ARRAYS)
        return result_from(meta, lo, hi, bl)

    def read_all(self, group: str) -> dict[str, np.ndarray]:
        """The whole ``lo``, ``hi``, ``blocking`` arrays of a group (one concurrent read each)."""
        g = self._root[group]
        return {k: g[k][:] for k in RELATION_ARRAYS}

    def consolidate(self) -> None:
        """Write consolidated metadata (once, at the end of a job)."""
        import zarr

        with warnings.catch_warnings():
            # Zarr warns that consolidated metadata is not part of the v3 spec yet; we know, and readers that
            # ignore it still find every array's own metadata.
            warnings.simplefilter("ignore")
            zarr.consolidate_metadata(self.url)

    # ---------------------------------------------------------------- inspection (tests, tools)
    def groups(self) -> list[str]:
        return sorted(name for name, _ in self._root.groups())

    def attrs(self) -> dict[str, Any]:
        return dict(self._root.attrs)


def _exists(url: str) -> bool:
    import fsspec

    fs, path = fsspec.core.url_to_fs(url)
    return fs.exists(path)


def _grids(network: Network) -> dict[str, Any]:
    return {
        s.name: {
            "key": s.key,
            "state": s.state_grid.describe(),
            "input": s.input_grid.describe(),
            "internal": None if s.internal_grid is None else s.internal_grid.describe(),
        }
        for s in network.subsystems
    }
