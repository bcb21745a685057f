"""Controllers with integrity: every controller file is verified before use, and no file can crash the process.

Real jobs: small.yaml (a BDD controller, ``controller.json`` + ``controller.dddmp``, and the layered
``controller_reach_safe``) and dcdc.yaml at spacing 0.02 (an array controller, ``controller.npz``). Each file is
damaged as the issue's campaign did (bytes flipped, one node line changed, truncated), copied from another
spec's job, stripped of its integrity record, or forged with its checksums recomputed; ``compabs export``,
``control``, ``audit`` and ``import`` run in child processes (a segmentation fault would show as -11) and must
exit 2 with one ``error:`` line naming the file and what differs. The C export of a header whose text carries
code compiles with ``cc`` and holds none of it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from pipelines.controller import Controller
from pipelines.controller_integrity import INTEGRITY, ControllerIntegrityError, seal
from pipelines.controller_loading import load_controller
from pipelines.export.c import c_sources
from pipelines.export.emit import export_controller
from pipelines.spec.model import parse_spec
from service.job_store import TERMINAL
from workers.executors import Execution
from workers.job import run_job

from .conftest import EXAMPLES

ROOT = Path(__file__).resolve().parents[1]
PAYLOAD = '*/ system("x"); /*\n#include <stdlib.h>\nint evil(void) { return system("x"); }'


def small_data(**options) -> dict:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"].update({"audit_transitions": 0, "closed_loop_runs": 2, **options})
    return data


def make_job(data: dict, out: Path) -> Path:
    run_job(parse_spec(data), out, Execution(in_process=True), audit=False)
    return out


@pytest.fixture(scope="module")
def small_job(tmp_path_factory) -> Path:
    return make_job(small_data(), tmp_path_factory.mktemp("small") / "job")


@pytest.fixture(scope="module")
def other_job(tmp_path_factory) -> Path:
    """small.yaml with another seed: another spec hash, the same variables and grids."""
    return make_job(small_data(seed=1), tmp_path_factory.mktemp("other") / "job")


@pytest.fixture(scope="module")
def array_job(tmp_path_factory) -> Path:
    data = yaml.safe_load((EXAMPLES / "dcdc.yaml").read_text())
    data["subsystems"][0]["state"]["eta"] = 0.02  # 21 x 21 cells
    data["options"].update({"audit_transitions": 0, "closed_loop_runs": 2})
    out = make_job(data, tmp_path_factory.mktemp("dcdc") / "job")
    assert (out / "controller.npz").is_file()
    return out


@pytest.fixture
def job(small_job, tmp_path) -> Path:
    """A private copy of the small job (tests damage it)."""
    return Path(shutil.copytree(small_job, tmp_path / "job"))


def cli(*args) -> subprocess.CompletedProcess:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    env.pop("COMPABS_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "service.cli", *map(str, args)], cwd=ROOT, env=env, text=True,
                          capture_output=True, timeout=300)


def refused(r: subprocess.CompletedProcess, *fragments: str) -> str:
    """Exit 2 (never a signal), one ``error:`` line holding every fragment; the line."""
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert "internal error" not in lines[0] and "Traceback" not in r.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    return lines[0]


def flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x5A
    path.write_bytes(bytes(data))


def change_node_line(path: Path) -> None:
    """One node line's then child made a node not yet read: what made CUDD crash."""
    lines = path.read_text().split("\n")
    k = lines.index(".nodes") + 3
    ident, name, var, _then, other = lines[k].split()
    lines[k] = f"{ident} {name} {var} {int(ident) + 50} {other}"
    path.write_text("\n".join(lines))


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])


DAMAGES = {"flipped": flip, "node line": change_node_line, "truncated": truncate}


def reseal(head_path: Path) -> None:
    """Recompute a header's integrity record over the files as they are now (a forger's move)."""
    head = json.loads(head_path.read_text())
    head.pop(INTEGRITY)
    head_path.write_text(json.dumps(seal(head, head_path.parent, head["roots"]), indent=1))


# ============================================================================================ the intact job
def test_intact_job_passes_every_command(job, tmp_path):
    head = json.loads((job / "controller.json").read_text())
    record = head[INTEGRITY]
    assert set(record["files"]) == set(head["roots"]) == {"controller.dddmp"}
    assert record["spec_hash"] == json.loads((job / "report.json").read_text())["spec_hash"]
    assert cli("export", job, "--format", "json", "--out", tmp_path / "e.json").returncode == 0
    exported = json.loads((tmp_path / "e.json").read_text())
    assert exported[INTEGRITY]["spec_hash"] == record["spec_hash"]
    assert cli("import", tmp_path / "e.json").returncode == 0
    assert cli("control", job, "--x", "3,4").returncode == 0
    assert cli("control", job, "--x", "3,4", "--controller", "reach_safe").returncode == 0
    r = cli("audit", job, "--transitions", "200", "--runs", "2")
    assert r.returncode == 0, r.stderr


# ============================================================================================ damaged files
@pytest.mark.parametrize("damage", DAMAGES)
@pytest.mark.parametrize("file", ["controller.dddmp", "controller.json"])
def test_damaged_controller_file_is_refused_by_every_command(job, tmp_path, file, damage):
    if damage == "node line" and file == "controller.json":
        pytest.skip("a header has no node lines")
    DAMAGES[damage](job / file)
    for args in (["export", job, "--format", "c", "--out", tmp_path / "c"], ["control", job, "--x", "3,4"],
                 ["audit", job, "--transitions", "200", "--runs", "2"]):
        line = refused(cli(*args), str(job / file))
        assert "checksum differs" in line or (file.endswith(".json") and "not valid JSON" in line), line
    assert not (tmp_path / "c.c").exists()


@pytest.mark.parametrize("damage", DAMAGES)
def test_damaged_file_of_a_layered_controller_is_refused(job, damage):
    DAMAGES[damage](job / "controller_reach_safe.3.dddmp")
    refused(cli("control", job, "--x", "3,4", "--controller", "reach_safe"), "controller_reach_safe.3.dddmp",
            "checksum differs")


@pytest.mark.parametrize("what", ["missing", "no record"])
def test_missing_file_or_record_is_refused(job, what):
    if what == "missing":
        (job / "controller.dddmp").unlink()
        refused(cli("control", job, "--x", "3,4"), "controller.dddmp", "cannot read")
    else:  # a header of an older version: refused, with what to do
        head = json.loads((job / "controller.json").read_text())
        head.pop(INTEGRITY)
        (job / "controller.json").write_text(json.dumps(head))
        refused(cli("export", job, "--format", "json"), "controller.json", "no integrity record", "run the job again")


# ============================================================================================ forgeries
@pytest.mark.parametrize("damage", ["node line", "flipped", "truncated"])
def test_forged_dddmp_with_recomputed_checksums_never_reaches_cudd(job, damage):
    """A forger recomputes the checksums: the DDDMP file's own structure is checked before CUDD reads it."""
    DAMAGES[damage](job / "controller.dddmp")
    reseal(job / "controller.json")
    line = refused(cli("control", job, "--x", "3,4"), str(job / "controller.dddmp"), "not a DDDMP file")
    refused(cli("export", job, "--format", "c"), "not a DDDMP file")
    assert "CUDD" not in line


def test_every_node_line_changed_alone_never_crashes(job):
    """Each node line of a small BDD changed (a child out of range, a variable out of the support, another
    name), checksums recomputed: every one refused in this process, none handed to CUDD."""
    path = job / "controller_reach_safe.dddmp"
    good = path.read_text()
    lines = good.split("\n")
    start = lines.index(".nodes") + 1
    end = lines.index(".end")
    bad = 0
    for k in range(start + 1, end):
        ident, name, var, then, other = lines[k].split()
        for changed in (f"{ident} {name} {var} {ident} {other}", f"{ident} {name} 99 {then} {other}",
                        f"{ident} w0_0 {var} {then} {other}", f"{ident} {name} {var} {then} 0"):
            path.write_text("\n".join([*lines[:k], changed, *lines[k + 1:]]))
            reseal(job / "controller_reach_safe.json")
            with pytest.raises(ControllerIntegrityError, match="not a DDDMP file"):
                load_controller(job, "controller_reach_safe")
            bad += 1
    assert bad >= 12


def test_controller_of_another_spec_is_refused(job, other_job, tmp_path):
    """Copied whole from another spec's job (its files consistent among themselves): its spec hash is not the
    job's."""
    for f in ("controller.json", "controller.dddmp"):
        shutil.copy(other_job / f, job / f)
    for args in (["export", job, "--format", "json", "--out", tmp_path / "e.json"], ["control", job, "--x", "3,4"],
                 ["audit", job, "--transitions", "200", "--runs", "2"]):
        refused(cli(*args), "controller.json", "another job", "spec.json")


def test_header_spec_changed_is_refused(job):
    """The spec inside the header edited and the checksums recomputed: its hash no longer matches the job's."""
    head = json.loads((job / "controller.json").read_text())
    head["meta"]["spec"]["options"]["seed"] = 7
    head.pop(INTEGRITY)
    (job / "controller.json").write_text(json.dumps(seal(head, job, head["roots"])))
    refused(cli("control", job, "--x", "3,4"), "controller.json", "another job")


# ============================================================================================ array controllers
@pytest.mark.parametrize("damage", ["flipped", "truncated"])
@pytest.mark.parametrize("file", ["controller.npz", "controller.json"])
def test_damaged_array_controller_is_refused(array_job, tmp_path, file, damage):
    job = Path(shutil.copytree(array_job, tmp_path / "job"))
    DAMAGES[damage](job / file)
    refused(cli("control", job, "--x", "1.4,5.6"), str(job / file))
    refused(cli("export", job, "--format", "c", "--out", tmp_path / "c"), str(job / file))


def test_array_controller_of_another_spec_is_refused(array_job, small_job, tmp_path):
    job = Path(shutil.copytree(array_job, tmp_path / "job"))
    shutil.copy(small_job / "spec.json", job / "spec.json")
    with pytest.raises(ControllerIntegrityError, match="another job"):
        load_controller(job)
    assert cli("control", array_job, "--x", "1.4,5.6").returncode in (0, 1)


# ============================================================================================ JSON exports
@pytest.mark.parametrize("change", ["edited", "no record", "truncated"])
def test_damaged_export_is_refused_by_import(small_job, tmp_path, change):
    path = tmp_path / "e.json"
    assert cli("export", small_job, "--format", "json", "--out", path).returncode == 0
    data = json.loads(path.read_text())
    if change == "edited":
        data["bdd"]["low"][3] = 1 - data["bdd"]["low"][3]
        path.write_text(json.dumps(data))
        refused(cli("import", path, "--x", "3,4"), str(path), "checksum differs")
    elif change == "no record":
        data.pop(INTEGRITY)
        path.write_text(json.dumps(data))
        refused(cli("import", path), str(path), "no integrity record")
    else:
        truncate(path)
        refused(cli("import", path), str(path), "not JSON")


# ============================================================================================ the C export
def test_c_export_writes_no_header_text(job, tmp_path):
    """A header whose kind and fixed point carry C code (checksums recomputed, so it loads): the C export holds
    none of it and compiles."""
    head = json.loads((job / "controller.json").read_text())
    head["meta"]["kind"] = PAYLOAD
    head["meta"]["fixed_point"] = "*/ system(\"x\"); /*\n"
    head.pop(INTEGRITY)
    (job / "controller.json").write_text(json.dumps(seal(head, job, head["roots"])))
    r = cli("export", job, "--format", "c", "--out", tmp_path / "ctl")
    assert r.returncode == 0, r.stderr
    for f in ("ctl.c", "ctl.h"):
        text = (tmp_path / f).read_text()
        assert "system" not in text and "evil" not in text and "stdlib" not in text, f
    compiled = subprocess.run(["cc", "-std=c99", "-Wall", "-Werror", "-c", str(tmp_path / "ctl.c"), "-o",
                               str(tmp_path / "ctl.o")], capture_output=True, text=True, cwd=tmp_path)
    assert compiled.returncode == 0, compiled.stderr
    nm = subprocess.run(["nm", str(tmp_path / "ctl.o")], capture_output=True, text=True)
    assert "system" not in nm.stdout and "compabs_control" in nm.stdout


def test_c_export_names_are_checked(small_job):
    ctrl = load_controller(small_job)
    assert isinstance(ctrl, Controller)
    export = export_controller(ctrl)
    header, source = c_sources(export, "ok_name-1.v2")
    assert '#include "ok_name-1.v2.h"' in source
    for bad in ('x"\n#include <stdlib.h>', "a b", "../up", ""):
        with pytest.raises(Exception, match="base name"):
            c_sources(export, bad)


# ============================================================================================ damaged job files
@pytest.mark.parametrize("file", ["report.json", "spec.json"])
@pytest.mark.parametrize("damage", ["truncated", "a list"])
def test_damaged_job_file_is_named(job, file, damage):
    if damage == "truncated":
        truncate(job / file)
    else:
        (job / file).write_text("[1, 2]")
    line = refused(cli("audit", job, "--transitions", "200", "--runs", "2"), str(job / file), "damaged")
    assert "please report" not in line.lower()
    if file == "spec.json":
        refused(cli("control", job, "--x", "3,4"), str(job / file))


def test_report_without_subsystem_fields_is_named(job):
    report = json.loads((job / "report.json").read_text())
    for s in report["subsystems"]:
        s.pop("lipschitz")
    (job / "report.json").write_text(json.dumps(report))
    refused(cli("audit", job, "--transitions", "200"), str(job / "report.json"), "damaged")


# ============================================================================================ the API
def test_api_serves_only_a_verified_controller(other_job, tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    token = "t0ken"
    auth = {"Authorization": f"Bearer {token}"}
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", in_process=True, token=token))) as client:
        r = client.post("/jobs", json=small_data(), headers=auth)
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]
        deadline = time.monotonic() + 120
        while (status := client.get(f"/jobs/{job_id}", headers=auth).json()["status"]) not in TERMINAL:
            assert time.monotonic() < deadline, status
            time.sleep(0.1)
        assert status == "succeeded"
        job_dir = tmp_path / "data" / "jobs" / job_id
        assert client.get(f"/jobs/{job_id}/controller", headers=auth).status_code == 200
        # A damaged archive is made again from the verified files, never served as it is.
        (job_dir / "controller.zip").write_bytes(b"PK garbage")
        z = client.get(f"/jobs/{job_id}/controller", headers=auth)
        assert z.status_code == 200 and z.content[:2] == b"PK" and len(z.content) > 100
        change_node_line(job_dir / "controller.dddmp")
        r = client.get(f"/jobs/{job_id}/controller", headers=auth)
        assert r.status_code == 409, r.text
        detail = r.json()["detail"]
        assert "controller.dddmp" in detail and "checksum differs" in detail and str(tmp_path) not in detail
        for f in ("controller.json", "controller.dddmp"):  # another spec's controller, consistent in itself
            shutil.copy(other_job / f, job_dir / f)
        r = client.get(f"/jobs/{job_id}/controller", headers=auth)
        assert r.status_code == 409 and "another job" in r.json()["detail"], r.text


def test_in_process_refusals_name_the_file(job):
    change_node_line(job / "controller.dddmp")
    with pytest.raises(ControllerIntegrityError, match="controller.dddmp: its checksum differs"):
        load_controller(job)
