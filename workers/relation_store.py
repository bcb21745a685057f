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
                                             (start, stop, successors, slope_x, slope_w, seconds) and its
                                             checksum sha256 (Integrity, below); "" = not done

``lo``, ``hi`` and ``blocking`` are chunked along the state cells with ``chunk_cells`` cells per chunk (all
inputs and internal cells in the chunk), which is exactly one task's range: each task owns whole chunks
(ENGINEERING "Zarr 3": half-chunk writes from two processes lose rows). Codec ``BloscCodec(zstd, bitshuffle)``.

``done`` has one element per chunk and chunks of one element, so a task owns its marker's chunk too. The task
writes its marker *after* its data: a marker says the data are complete. A chunk's data without a marker (a
task killed between the two writes, or a marker deleted) is recomputed. Keeping markers in a Zarr array (not
loose files) keeps the hierarchy valid for Zarr readers and consolidation; local writes are atomic (temp file +
rename), and the ``*.partial`` temporaries a killed writer leaves are never read, because Zarr reads exact keys
and never lists chunk directories.

Integrity
---------
Every marker carries ``sha256`` (:func:`chunk_checksum`): SHA-256 over the chunk's position (group, ``start``,
``stop``), the rest of its marker but ``seconds``, and each of ``lo``, ``hi``, ``blocking`` (name, dtype, shape,
bytes); the task writes it with the marker, after the data. A chunk is reused only if it reads back and matches
(:func:`check_chunks`, on the runner's one bulk read); otherwise it is *damaged*, logged and recomputed: a data
chunk missing under its marker reads as the fill value, which matches only if the data were all fill (chunks
Zarr does not write; the marker's ``all_fill`` names them); a chunk that cannot be read (garbage: any codec or
store error) is caught, chunk by chunk; another chunk's valid data (swapped, copied) do not match, the position
being in the checksum. A marker that cannot be read, is not JSON, names other cells or has no checksum counts as
not done. ``compabs audit`` (:func:`workers.jobdir.load_job`) checks every chunk it reads and reports the damaged
ones. Layout 1 stores (no checksums) are refused like a store of another spec.

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
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from pipelines.abstraction.relation import CellsResult, SlopeRecord
from pipelines.network import Network, Subsystem
from pipelines.spec.model import JobSpec, spec_hash
from workers.errors import StoreError, StoreMismatchError

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from zarr.core.common import JSON

#: Version of the layout above; a store of another layout is treated as stale. 2: markers carry ``sha256``.
LAYOUT_VERSION = 2
RELATION_ARRAYS = ("lo", "hi", "blocking")
#: The stored dtype of each relation array: what a chunk's checksum is computed over.
RELATION_DTYPES = {"lo": np.dtype("<i4"), "hi": np.dtype("<i4"), "blocking": np.dtype("|b1")}
#: Marker fields the checksum does not cover (the time a chunk took; the checksum itself).
_UNCHECKED = ("seconds", "sha256")


def code_version() -> str:
    """The installed compabs version ("unknown" when running from an uninstalled tree)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("compabs")
    except PackageNotFoundError:
        return "unknown"


def _constant_ident(L: Any) -> Any:
    """A constant's identity: the exact hex form of a number (so 0.98 and 0.98000001 differ), with the entries of a
    matrix of constants that are not all that number (:class:`~pipelines.abstraction.constants.LipschitzMatrix`)."""
    ident = float(L).hex()
    if getattr(L, "is_scalar", True):
        return ident
    return [ident, [[float(v).hex() for v in row] for row in L.entries.tolist()]]


def group_name(sub: Subsystem, L_x: Any, L_w: Any, method: str, objective: str, chunk_cells: int) -> str:
    """The group of a subsystem's relation computed with these constants and this chunking.

    ``sub.key`` already identifies the subsystem's spec, internal grid and parameters; the digest adds what the
    per-cell stage is given on top (float constants by their exact hex form, so 0.98 and 0.98000001 differ).
    """
    ident = {
        "L_x": _constant_ident(L_x),
        "L_w": _constant_ident(L_w),
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
    return r.as_dict()  # with the largest slope per entry of the constants, when recorded


def result_from(meta: dict[str, Any], lo: np.ndarray, hi: np.ndarray, blocking: np.ndarray) -> CellsResult:
    """Rebuild a chunk's :class:`CellsResult` from its marker and its arrays (shapes as in CellsResult)."""
    return CellsResult(
        int(meta["start"]),
        int(meta["stop"]),
        lo,
        hi,
        blocking,
        {k: (int(s), int(n)) for k, (s, n) in meta["successors"].items()},
        SlopeRecord.from_dict(meta["slope_x"]),
        SlopeRecord.from_dict(meta["slope_w"]),
    )


# ------------------------------------------------------------------ integrity: checksums and checks
def chunk_checksum(group: str, meta: dict[str, Any], lo: np.ndarray, hi: np.ndarray, blocking: np.ndarray) -> str:
    """The checksum of one chunk (module docstring, "Integrity"), as its marker carries it.

    ``meta`` is the chunk's marker (its ``start`` and ``stop`` are the position; ``seconds`` and ``sha256`` are
    left out); the arrays are the chunk's, in the stored dtypes.
    """
    h = hashlib.sha256()
    core = {k: v for k, v in meta.items() if k not in _UNCHECKED}
    h.update(json.dumps({"group": group, "marker": core}, sort_keys=True).encode())
    for name, a in (("lo", lo), ("hi", hi), ("blocking", blocking)):
        a = np.ascontiguousarray(a, dtype=RELATION_DTYPES[name])  # no copy for what Zarr reads back
        h.update(f"|{name}|{a.dtype.str}|{list(a.shape)}|".encode())
        h.update(a.reshape(-1).view(np.uint8).data)
    return h.hexdigest()


def chunk_place(group: str, chunk: int, chunk_cells: int, n_x: int) -> str:
    """How messages name a chunk: ``group G, chunk i (state cells a..b)``."""
    start = chunk * chunk_cells
    return f"group {group}, chunk {chunk} (state cells {start}..{min(start + chunk_cells, n_x) - 1})"


def _marker_problem(meta: Any, chunk: int, chunk_cells: int, n_x: int) -> str | None:
    """Why a parsed marker cannot stand for chunk ``chunk`` (``None``: it can, if its data match)."""
    if not isinstance(meta, dict) or not {"start", "stop", "successors", "slope_x", "slope_w"} <= set(meta):
        return "its done-marker is not a compabs marker (not JSON, or fields missing)"
    start = chunk * chunk_cells
    if (meta["start"], meta["stop"]) != (start, min(start + chunk_cells, n_x)):
        return f"its done-marker names state cells [{meta['start']}, {meta['stop']}) (another chunk's)"
    if not isinstance(meta.get("sha256"), str):
        return "its done-marker has no checksum (written by an older compabs)"
    return None


def group_markers(g: Any) -> tuple[dict[int, dict[str, Any]], dict[int, str]]:
    """The done-markers of an open relation group: (chunk -> marker of each usable one, chunk -> why a marker
    that is there cannot be used). Chunks in neither are not done. Nothing raises for a damaged marker."""
    done, lo = g["done"], g["lo"]
    chunk_cells, n_x = int(lo.chunks[0]), int(lo.shape[0])
    try:
        texts: list[Any] = done[:].tolist()
    except Exception:  # a marker's chunk is damaged: read them one by one
        texts = []
        for i in range(int(done.shape[0])):
            try:
                texts.append(done[i:i + 1].tolist()[0])
            except Exception as exc:  # any codec or store error: that marker only
                texts.append(exc)
    good: dict[int, dict[str, Any]] = {}
    bad: dict[int, str] = {}
    for i, text in enumerate(texts):
        if isinstance(text, Exception):
            bad[i] = f"its done-marker cannot be read ({type(text).__name__}: {text})"
        elif text:
            try:
                meta = json.loads(text)
            except ValueError:
                meta = None
            problem = _marker_problem(meta, i, chunk_cells, n_x)
            if problem is None:
                good[i] = meta
            else:
                bad[i] = problem
    return good, bad


@dataclass
class ChunkCheck:
    """What :func:`check_chunks` read (``arrays``: state cells from ``offset`` on, zeros where a chunk could not
    be read: the chunks ``unreadable``) and found (``damaged``: chunk -> why it cannot be reused)."""

    offset: int
    arrays: dict[str, np.ndarray]
    damaged: dict[int, str]
    unreadable: frozenset[int] = frozenset()


def check_chunks(g: Any, group: str, metas: dict[int, dict[str, Any]], whole: bool = False) -> ChunkCheck:
    """Read the chunks ``metas`` names (chunk -> marker) of a relation group and verify their checksums.

    One read per array (of all cells for several chunks or ``whole``, else of the one chunk); if that fails, chunk
    by chunk, so only the damaged ones are lost. ``whole``: unreadable chunks are reported even without a marker.
    """
    lo_a = g["lo"]
    chunk_cells, n_x = int(lo_a.chunks[0]), int(lo_a.shape[0])
    if not metas and not whole:
        return ChunkCheck(0, {}, {})
    if len(metas) == 1 and not whole:
        (i,) = metas
        a, b = i * chunk_cells, min((i + 1) * chunk_cells, n_x)
    else:
        a, b = 0, n_x
    wanted = range(-(-n_x // chunk_cells)) if whole else sorted(metas)
    arrays, damaged = _read_cells(g, a, b, wanted, chunk_cells)
    unreadable = frozenset(damaged)
    for i, meta in metas.items():
        if i in damaged:
            continue
        s = slice(int(meta["start"]) - a, int(meta["stop"]) - a)
        if meta["sha256"] != chunk_checksum(group, meta, *(arrays[k][s] for k in RELATION_ARRAYS)):
            damaged[i] = _mismatch(g, i, meta)
    return ChunkCheck(a, arrays, damaged, unreadable)


def _read_cells(g: Any, a: int, b: int, chunks: Any, chunk_cells: int) -> tuple[dict[str, np.ndarray], dict[int, str]]:
    """State cells ``[a, b)`` of the relation arrays, in one read each, or chunk by chunk if that fails."""
    try:
        return {k: np.asarray(g[k][a:b]) for k in RELATION_ARRAYS}, {}
    except Exception:  # a chunk cannot be read (decompression error, truncated file, ...): find which
        pass
    arrays = {k: np.zeros((b - a, *g[k].shape[1:]), dtype=RELATION_DTYPES[k]) for k in RELATION_ARRAYS}
    damaged: dict[int, str] = {}
    for i in chunks:
        s, e = i * chunk_cells, min((i + 1) * chunk_cells, b)
        for k in RELATION_ARRAYS:
            try:
                arrays[k][s - a:e - a] = g[k][s:e]
            except Exception as exc:  # any codec or store error: this chunk is recomputed
                damaged[i] = f"its {k} data chunk cannot be read ({type(exc).__name__}: {exc})"
                break
    return arrays, damaged


def _mismatch(g: Any, chunk: int, meta: dict[str, Any]) -> str:
    """Why a readable chunk does not match: which data chunks are missing, if any (best effort)."""
    try:
        from zarr.core.sync import sync

        keys = {k: f"{g[k].store_path.path}/{g[k].metadata.encode_chunk_key((chunk,) + (0,) * (g[k].ndim - 1))}"
                for k in RELATION_ARRAYS if k not in meta.get("all_fill", ())}  # all fill: not written, rightly
        missing = [k for k, key in keys.items() if not sync(g[k].store_path.store.exists(key))]
    except Exception:  # only for the message
        missing = []
    if missing:
        return (f"its {' and '.join(missing)} data chunk {'is' if len(missing) == 1 else 'are'} missing (read as "
                "the fill value) and the chunk does not match the checksum in its done-marker")
    return "its data do not match the checksum in its done-marker (altered, or another chunk's data)"


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
    """Write one chunk's arrays, then its done-marker with the chunk's checksum; return the marker.

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
    arrays = {k: np.ascontiguousarray(getattr(result, k), dtype=RELATION_DTYPES[k]) for k in RELATION_ARRAYS}
    w.lo[start:stop] = arrays["lo"]
    w.hi[start:stop] = arrays["hi"]
    w.blocking[start:stop] = arrays["blocking"]
    # The checksum over the marker as it reads back (JSON round trip), and the arrays as stored.
    meta = json.loads(json.dumps(marker(result, seconds)))
    # Arrays whose chunk is all fill value, which Zarr does not write: for the message when a chunk goes missing.
    meta["all_fill"] = [k for k in RELATION_ARRAYS if not arrays[k].any()]
    meta["sha256"] = chunk_checksum(group, meta, arrays["lo"], arrays["hi"], arrays["blocking"])
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
        self._open: dict[str, dict[str, Any]] = {}  # group -> its open arrays (metadata read once)

    def _arrays(self, group: str) -> dict[str, Any]:
        a = self._open.get(group)
        if a is None:
            g = self._root[group]
            a = self._open[group] = {k: g[k] for k in (*RELATION_ARRAYS, "done")}
        return a

    # ---------------------------------------------------------------- opening
    @classmethod
    def open(cls, url: str, spec: JobSpec, network: Network, *, overwrite: bool = False) -> RelationStore:
        """Open (or create) the store at ``url`` (a path or fsspec URL: :func:`workers.jobdir.relations_url` of the
        job's directory) for a job.

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
        if have["spec_hash"] == want["spec_hash"]:
            # The same spec, stored by another compabs: layout 1 stores have no chunk checksums, say so.
            why = " (layout 1 stores no chunk checksums)" if have["layout"] == 1 else ""
            return (
                f"{url} holds this job's relations ('{name}') written by another compabs version or store layout: "
                f"{diffs}{why}. Its chunks are not reused. Pass --overwrite (overwrite=True) to delete the store "
                "and recompute, or use another output directory."
            )
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
        self._open.pop(group, None)
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
        """Done-markers of a group: chunk index -> metadata. Damaged markers count as not done."""
        return group_markers(self._arrays(group))[0]

    def marker_state(self, group: str) -> tuple[dict[int, dict[str, Any]], dict[int, str]]:
        """:func:`group_markers` of a group: its usable markers, and why the other markers there are not."""
        return group_markers(self._arrays(group))

    def check(self, group: str, metas: dict[int, dict[str, Any]]) -> ChunkCheck:
        """Read and verify the chunks ``metas`` names (:func:`check_chunks`): one bulk read for many chunks."""
        return check_chunks(self._arrays(group), group, metas)

    def clear_marker(self, group: str, chunk: int) -> None:
        """Mark a chunk not done (a damaged chunk, before it is recomputed)."""
        try:
            self._arrays(group)["done"][chunk] = ""
        except OSError as exc:
            raise StoreError(f"relation store {self.url}: cannot clear the done-marker of {group} chunk {chunk}: "
                             f"{exc}. Check the store's permissions and free space, then run the job again.") from None

    def read(self, group: str, meta: dict[str, Any], check: ChunkCheck | None = None) -> CellsResult:
        """Rebuild the CellsResult of a done chunk, verified.

        Parameters
        ----------
        check : ChunkCheck, optional
            What :meth:`check` read and verified, to slice instead of reading (and verifying) this chunk alone.

        Raises
        ------
        StoreError
            Without ``check``: the chunk does not read back as its marker says (a chunk just written by a task
            and damaged since: another process writes this store, or the storage fails).
        """
        if check is None:
            c = int(self._arrays(group)["lo"].chunks[0])
            i = int(meta["start"]) // c
            check = self.check(group, {i: meta})
            if i in check.damaged:
                raise StoreError(f"relation store {self.url}: {group} chunk {i} does not read back as written: "
                                 f"{check.damaged[i]}. Another process may be writing this store, or the storage "
                                 "is failing; run the job again (the chunk is then recomputed).")
        s = slice(int(meta["start"]) - check.offset, int(meta["stop"]) - check.offset)
        lo, hi, bl = (np.array(check.arrays[k][s]) for k in RELATION_ARRAYS)
        return result_from(meta, lo, hi, bl)

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
