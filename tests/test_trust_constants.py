"""Sound constants (issue 7): Lipschitz constants the data contradict never yield a controller unless asked.

With the default ``on_violation: fail`` the job stops with a LipschitzError that names the constant, where the
data contradict it (the cell, input and internal cell of the steepest sample pair) and by how much, and writes
no controller. With ``on_violation: raise`` it goes on with the constant raised and the report says which constant
was raised, from what, to what and by how much; the stored abstraction then passes ``compabs audit``. The
interconnection's ``L_M`` (certify/direct modes) has no raise option: contradicted, the job fails naming it.
The distributed path is checked in ``tests/test_trust_cluster.py``.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest
import yaml

from service.cli import main

from .conftest import EXAMPLES
from .trust_log import record


def write_spec(directory: Path, constants: dict, **interconnection) -> Path:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["subsystems"][0]["lipschitz"] = constants
    data["interconnection"].update(interconnection)
    data["options"] = {**data.get("options", {}), "closed_loop_runs": 3, "audit_transitions": 20_000}
    path = directory / "spec.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("arg,lipschitz,given", [
    ("x", {"x": 1.599, "w": 0.16}, 1.599),  # the paper's constant; the dynamics' bound is 1.76
    ("w", {"x": 1.76, "w": 0.05}, 0.05),    # the bound in w is 0.16
])
def test_a_contradicted_constant_fails_the_job_and_no_controller_is_written(tmp_path, capsys, arg, lipschitz, given):
    out = tmp_path / "out"
    code = main(["run", str(write_spec(tmp_path, lipschitz)), "--out", str(out), "--quiet", "--in-process"])
    err = capsys.readouterr().err
    assert code == 2, err
    m = re.search(rf"the given L_{arg} = {given:g} is contradicted by the data: slope ([0-9.]+) observed at state cell "
                  rf"\d+ \(x in \[[0-9., ]+\]\), input u=\[-?[0-9.]+\], internal cell \d+ \(w in \[[0-9., ]+\]\), "
                  rf"([0-9.]+) \(([0-9.]+)%\) above it", err)
    assert m, err
    slope, excess, percent = float(m[1]), float(m[2]), float(m[3])
    assert slope > given and excess == pytest.approx(slope - given, rel=1e-4, abs=1e-5)
    assert percent == pytest.approx(100 * (slope / given - 1), abs=0.01)
    assert f"L_{arg} >= " in err and "on_violation: raise" in err  # what to do
    assert not list(out.glob("controller*")) and not (out / "report.json").exists()
    record(f"constants: contradicted L_{arg}, on_violation fail (CLI)", inputs=1, failed_cleanly=1, wrong=0)


def test_a_raised_constant_is_reported_and_the_result_audits_clean(tmp_path, capsys):
    out = tmp_path / "out"
    spec = write_spec(tmp_path, {"x": 1.599, "w": 0.16, "on_violation": "raise", "safety_factor": 1.1})
    assert main(["run", str(spec), "--out", str(out), "--quiet", "--in-process"]) == 0
    capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    lx = report["subsystems"][0]["lipschitz"]["x"]
    assert lx["source"] == "raised" and lx["given"] == 1.599
    assert lx["value"] == pytest.approx(lx["observed_max_slope"] * 1.1) and lx["observed_max_slope"] > 1.7
    assert lx["raised_by"] == pytest.approx(lx["value"] - 1.599) and lx["raised_factor"] == pytest.approx(lx["value"] / 1.599)
    assert re.match(r"state cell \d+ \(x in .*\), input u=.*, internal cell \d+", lx["where"]), lx["where"]
    assert report["subsystems"][0]["lipschitz"]["w"]["source"] == "given"  # not contradicted: untouched
    assert (out / "controller.json").exists() and report["closed_loop"]["violations"] == 0
    # The abstraction built with the raised constant is sound on fresh samples.
    assert main(["audit", str(out), "--transitions", "100000", "--seed", "11", "--runs", "5"]) == 0
    record("constants: contradicted L_x, on_violation raise (reported, audited)", inputs=1, wrong=0)


def test_a_contradicted_interconnection_constant_fails_naming_it(tmp_path, capsys):
    # mean(x) has L_M = 1 in the infinity norm (1/8 holds in the 1-norm only, README).
    spec = write_spec(tmp_path, {"x": 1.76, "w": 0.16}, error="certify", lipschitz=0.4)
    out = tmp_path / "out"
    assert main(["run", str(spec), "--out", str(out), "--quiet", "--in-process"]) == 2
    err = capsys.readouterr().err
    m = re.search(r"interconnection map output w0: slope ([0-9.]+) between x = \[.*\] and x' = \[.*\] exceeds the given "
                  r"Lipschitz constant L_M = 0.4 .* raise interconnection.lipschitz to at least ([0-9.]+)", err)
    assert m and float(m[1]) > 0.4, err
    assert not list(out.glob("controller*"))
    record("constants: contradicted L_M (CLI)", inputs=1, failed_cleanly=1, wrong=0)


def test_a_contradicted_constant_submitted_to_the_service_fails_without_a_controller(tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["subsystems"][0]["lipschitz"] = {"x": 1.599, "w": 0.16}
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", in_process=True))) as client:
        r = client.post("/jobs", json=data)
        assert r.status_code == 201, r.text  # the constant can only be refuted by running the job
        job_id = r.json()["id"]
        deadline = time.monotonic() + 120
        while (job := client.get(f"/jobs/{job_id}").json())["status"] not in ("succeeded", "failed", "cancelled"):
            assert time.monotonic() < deadline, job
            time.sleep(0.1)
        assert job["status"] == "failed"
        assert "the given L_x = 1.599 is contradicted by the data" in job["error"] and "state cell" in job["error"]
        assert client.get(f"/jobs/{job_id}/controller").status_code == 409
    record("constants: contradicted L_x (POST /jobs)", inputs=1, failed_cleanly=1, wrong=0)
