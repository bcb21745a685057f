"""Integrity of the relation store (issue 23): a damaged chunk is recomputed, never reused, and the audit names it.

Every chunk's done-marker carries a checksum of the chunk's data and position (``workers/relation_store.py``, "Integrity").
Three damages, each as the issue's campaign made them on a finished store: a data chunk deleted while its marker
stays (it reads back as the fill value), two valid chunks swapped, garbage bytes in a chunk (a Blosc
decompression error). A rerun of the same spec recomputes exactly the damaged chunks and gives the relations of a
fresh run (in-process, and once on the cluster); ``compabs audit`` reports each damaged chunk by group and chunk
(exit 3) instead of passing silently or printing a traceback.

small.yaml with ``options.chunk_cells: 4``: 33 state cells in 9 chunks (8 of 4 cells, the last of 1).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
import zarr

from pipelines.spec.model import parse_spec
from service.cli import main
from workers.errors import StoreMismatchError
from workers.executors import Execution
from workers.job import abstract_job, run_abstraction
from workers.jobdir import relations_url
from workers.relation_store import RelationStore

from .conftest import EXAMPLES
from .trust_log import record

CHUNK_CELLS = 4
N_CHUNKS = 9
DAMAGES = ("deleted", "swapped", "garbage")


def spec_data(**options) -> dict:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"] = {**data.get("options", {}), "chunk_cells": CHUNK_CELLS, "audit_transitions": 0, **options}
    return data


@pytest.fixture(scope="module")
def spec():
    return parse_spec(spec_data())


@pytest.fixture(scope="module")
def fresh(spec):
    """The relations of a fresh run (in memory, no store)."""
    return run_abstraction(spec, audit=False)


@pytest.fixture(scope="module")
def stored(spec, tmp_path_factory) -> Path:
    """A store of the spec with every chunk done (in-process)."""
    out = tmp_path_factory.mktemp("integrity") / "job"
    _, info = abstract_job(spec, out, execution=Execution(in_process=True), audit=False)
    assert info["chunks_computed"] == N_CHUNKS
    return out


@pytest.fixture
def job(stored, tmp_path) -> Path:
    """A private copy of the stored job (tests damage it)."""
    return Path(shutil.copytree(stored, tmp_path / "job"))


def the_group(out: Path) -> str:
    (group,) = [p.name for p in (out / "relations.zarr").iterdir() if p.is_dir()]
    return group


def chunk_file(out: Path, array: str, chunk: int) -> Path:
    """The file of ``array``'s chunk ``chunk`` (chunked along the state cells only)."""
    ndim = 4 if array in ("lo", "hi") else 3
    return out / "relations.zarr" / the_group(out) / array / "c" / str(chunk) / Path(*["0"] * (ndim - 1))


def damage(out: Path, kind: str) -> list[int]:
    """Damage the store in ``out`` as the issue's campaign did; the chunks damaged."""
    if kind == "deleted":  # the data chunk goes, its marker stays
        path = chunk_file(out, "lo", 3)
        assert path.exists()
        path.unlink()
        return [3]
    if kind == "swapped":  # two valid chunks (same shape, different data) change places
        a, b = chunk_file(out, "hi", 2), chunk_file(out, "hi", 5)
        da, db = a.read_bytes(), b.read_bytes()
        assert da != db
        a.write_bytes(db)
        b.write_bytes(da)
        return [2, 5]
    if kind == "garbage":  # bytes no codec can decode
        chunk_file(out, "lo", 6).write_bytes(b"\x13garbage, not a blosc frame" * 20)
        return [6]
    raise AssertionError(kind)


def assert_same(a, b) -> None:
    assert a.relations.keys() == b.relations.keys()
    for key, ra in a.relations.items():
        for field in ("lo", "hi", "blocking"):
            x, y = getattr(ra, field), getattr(b.relations[key], field)
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), (key, field)


# ============================================================================================ the runner
@pytest.mark.parametrize("kind", DAMAGES)
def test_damaged_chunk_is_recomputed_not_reused(job, spec, fresh, kind, caplog):
    chunks = damage(job, kind)
    group = the_group(job)
    with caplog.at_level("WARNING", logger="workers.executors"):
        result, info = abstract_job(spec, job, execution=Execution(in_process=True), audit=False)  # no exception, no traceback
    assert (info["chunks_computed"], info["chunks_reused"]) == (len(chunks), N_CHUNKS - len(chunks))
    assert_same(fresh, result)
    warned = [r.getMessage() for r in caplog.records if r.name == "workers.executors"]
    assert len(warned) == len(chunks), warned
    for k, message in zip(chunks, warned):
        assert f"group {group}, chunk {k} (state cells {4 * k}..{4 * k + 3})" in message, message
        assert "recomputed, not reused" in message
    if kind == "garbage":
        assert "cannot be read" in warned[0] and "RuntimeError" in warned[0]
    if kind == "deleted":
        assert "lo data chunk is missing" in warned[0]
    # Repaired: the next run reuses everything.
    again, info = abstract_job(spec, job, execution=Execution(in_process=True), audit=False)
    assert (info["chunks_computed"], info["chunks_reused"]) == (0, N_CHUNKS)
    assert_same(fresh, again)
    record(f"integrity: {kind} relation chunk (rerun)", faults=1, identical=1, wrong=0)


def test_chunk_swapped_with_its_marker_is_recomputed(job, spec, fresh, caplog):
    """Data and marker of two chunks swapped together: each marker names the other chunk's cells (said)."""
    for array in ("lo", "hi", "done"):
        if array == "done":
            a = job / "relations.zarr" / the_group(job) / "done" / "c" / "1"
            b = a.parent / "4"
        else:
            a, b = chunk_file(job, array, 1), chunk_file(job, array, 4)
        da, db = a.read_bytes(), b.read_bytes()
        a.write_bytes(db)
        b.write_bytes(da)
    with caplog.at_level("WARNING", logger="workers.executors"):
        result, info = abstract_job(spec, job, execution=Execution(in_process=True), audit=False)
    assert (info["chunks_computed"], info["chunks_reused"]) == (2, N_CHUNKS - 2)
    assert_same(fresh, result)
    warned = [r.getMessage() for r in caplog.records if r.name == "workers.executors"]
    assert len(warned) == 2 and "chunk 1 (state cells 4..7)" in warned[0], warned
    assert "done-marker names state cells [16, 20) (another chunk's)" in warned[0], warned


@pytest.mark.parametrize("marker", ["garbage", "no checksum", "altered slope"])
def test_damaged_marker_counts_as_not_done(job, spec, fresh, marker):
    group = the_group(job)
    path = job / "relations.zarr" / group / "done" / "c" / "2"
    if marker == "garbage":
        path.write_bytes(b"\x00\x01 not zstd" * 7)
    else:
        done = zarr.open_group(str(job / "relations.zarr"), path=group, mode="r+", use_consolidated=False)["done"]
        meta = json.loads(done[2:3].tolist()[0])
        if marker == "no checksum":  # as layout 1 wrote them
            meta.pop("sha256")
        else:  # the slopes feed the Lipschitz check: a marker's metadata are in the checksum too
            meta["slope_x"]["slope"] = 0.0
        done[2] = json.dumps(meta)
    result, info = abstract_job(spec, job, execution=Execution(in_process=True), audit=False)
    assert (info["chunks_computed"], info["chunks_reused"]) == (1, N_CHUNKS - 1)
    assert_same(fresh, result)
    assert result.report["subsystems"] == fresh.report["subsystems"]


def test_store_of_the_previous_layout_is_refused_then_overwritten(job, spec, fresh):
    """Layout 1 markers carry no checksum: such a store is refused, saying why, and --overwrite recomputes it."""
    root = zarr.open_group(str(job / "relations.zarr"), mode="r+", use_consolidated=False)
    root.attrs["layout"] = 1
    with pytest.raises(StoreMismatchError) as err:
        abstract_job(spec, job, execution=Execution(in_process=True), audit=False)
    message = str(err.value)
    assert "layout 1" in message and "no chunk checksums" in message and "--overwrite" in message, message
    assert "another job" not in message  # the same spec: only the store layout differs
    result, info = abstract_job(spec, job, execution=Execution(in_process=True), audit=False, overwrite=True)
    assert info["chunks_computed"] == N_CHUNKS
    assert_same(fresh, result)
    assert RelationStore.open(relations_url(job), spec, result.network).attrs()["layout"] == 2


def test_cluster_recomputes_damaged_chunks(tmp_path, client, spec, fresh, caplog):
    """The Dask path: deleted, swapped and garbage chunks at once; the reused ones are verified while the cluster
    computes, the damaged ones become tasks."""
    out = tmp_path / "job"
    _, info = abstract_job(spec, out, execution=Execution(client=client), audit=False)
    assert info["chunks_computed"] == N_CHUNKS
    chunks = sorted(k for kind in DAMAGES for k in damage(out, kind))
    with caplog.at_level("WARNING", logger="workers.executors"):
        result, info = abstract_job(spec, out, execution=Execution(client=client), audit=False)
    assert (info["chunks_computed"], info["chunks_reused"]) == (len(chunks), N_CHUNKS - len(chunks))
    assert_same(fresh, result)
    warned = " ".join(r.getMessage() for r in caplog.records if r.name == "workers.executors")
    assert all(f"chunk {k} (state cells" in warned for k in chunks), warned
    record("integrity: deleted + swapped + garbage chunks (cluster rerun)", faults=3, identical=1, wrong=0)


# ============================================================================================ the audit
@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished job (``compabs run --in-process --no-synthesis``) of the spec, for ``compabs audit``."""
    base = tmp_path_factory.mktemp("integrity-audit")
    spec_file = base / "small.yaml"
    spec_file.write_text(yaml.safe_dump(spec_data(audit_transitions=10_000)))
    out = base / "job"
    assert main(["run", str(spec_file), "--out", str(out), "--quiet", "--in-process", "--no-synthesis"]) == 0
    return out


def run_audit(job: Path, capsys) -> tuple[int, str, str, dict]:
    code = main(["audit", str(job), "--transitions", "20000", "--seed", "5", "--runs", "0"])
    cap = capsys.readouterr()
    return code, cap.out, cap.err, json.loads((job / "audit.json").read_text())


def test_audit_of_an_intact_store_checks_every_chunk(finished, tmp_path, capsys):
    job = Path(shutil.copytree(finished, tmp_path / "job"))
    code, out, err, result = run_audit(job, capsys)
    assert code == 0, out + err
    assert result["relation_store"]["chunks_checked"] == N_CHUNKS and result["relation_store"]["damaged"] == []
    assert "relation store" not in result["parts"]


@pytest.mark.parametrize("kind", DAMAGES)
def test_audit_reports_damaged_chunks(finished, tmp_path, capsys, kind):
    job = Path(shutil.copytree(finished, tmp_path / "job"))
    chunks = damage(job, kind)
    group = the_group(job)
    code, out, err, result = run_audit(job, capsys)
    assert code == 3, out + err
    assert "Traceback" not in out + err
    damaged = result["relation_store"]["damaged"]
    assert [(d["group"], d["chunk"], d["start"], d["stop"]) for d in damaged] == [
        (group, k, 4 * k, 4 * k + 4) for k in chunks]
    part = result["parts"]["relation store"]
    assert part["violations"] == len(chunks) and result["violations"] >= len(chunks)
    place = f"group {group}, chunk {chunks[0]} (state cells {4 * chunks[0]}..{4 * chunks[0] + 3})"
    assert place in part["first_violation"] and "run the job again" in part["first_violation"].lower()
    assert place in out  # the table's first-violation line names the chunk
    assert "error: the audit" in err
    if kind == "garbage":  # nothing to check in that chunk: its cells are skipped, the rest is audited
        assert "cannot be read" in damaged[0]["reason"]
        assert result["parts"]["subsystem agent[0]"]["transitions_checked"] > 0

    # Running the job again recomputes the damaged chunks; the audit passes.
    spec_file = finished.parent / "small.yaml"
    assert main(["run", str(spec_file), "--out", str(job), "--quiet", "--in-process", "--no-synthesis"]) == 0
    capsys.readouterr()
    code, out, err, result = run_audit(job, capsys)
    assert code == 0 and result["relation_store"]["damaged"] == [], out + err
    record(f"integrity: {kind} relation chunk (compabs audit)", faults=1, failed_cleanly=1, wrong=0)
