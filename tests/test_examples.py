"""The paper's cases end to end: exact counts, and audits of >= 10^6 transitions with no violation."""

import json

import pytest

from pipelines.spec.model import load_spec
from service.cli import main
from workers.job import run_abstraction

from .conftest import EXAMPLES


@pytest.mark.slow
@pytest.mark.parametrize(
    "name,states,region",
    [("consensus", 1_406_408_618_241, 9_493_117), ("tanks", 13_422_659_310_152_401, 2_015_993_900_449)],
)
def test_paper_case(tmp_path, name, states, region):
    # Synthesis of these cases is tested in tests/test_closed_loop.py (tanks) and benchmarked (consensus).
    args = ["run", str(EXAMPLES / f"{name}.yaml"), "--out", str(tmp_path), "--quiet", "--in-process", "--no-synthesis"]
    assert main(args) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["abstract_states"] == states
    assert report["region_states"] == region
    assert report["audit"]["transitions_checked"] >= 1_000_000
    assert report["audit"]["violations"] == 0
    for sub in report["subsystems"]:
        assert set(sub["mean_successors"]) == {"lipschitz", "scp", "scp_radius", "hull"}
        assert sub["lipschitz"]["x"]["source"] == "given"
    assert all("error_bound" in n for n in report["interconnection"]["nodes"])
    assert set(report["stage_seconds"]) >= {"plan", "subsystems", "interconnection", "audit"}


@pytest.mark.slow
@pytest.mark.parametrize("n", [4, 8, 16, 32])
def test_scalability_runs(n):
    spec = load_spec(EXAMPLES / "scalability.yaml", {"N": n})
    result = run_abstraction(spec)
    assert result.report["abstract_states"] == 33**n
    assert result.report["audit"]["transitions_checked"] >= 1_000_000
    assert result.report["audit"]["violations"] == 0


@pytest.mark.parametrize("where", ["--cluster", "default"])
def test_small_example_end_to_end(tmp_path, where):
    """On the embedded two-worker cluster (``--cluster``) and by default (a small job: in this process), each with
    the Zarr store, synthesis, closed loop, figures."""
    args = ["run", str(EXAMPLES / "small.yaml"), "--out", str(tmp_path), "--quiet"]
    assert main(args + ([where] if where != "default" else [])) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["abstract_states"] == 33**2
    assert report["audit"]["violations"] == 0
    assert (tmp_path / "relations.zarr").is_dir()
    assert report["runner"]["chunks_computed"] >= 1
    if where == "--cluster":
        assert report["runner"]["workers"] == 2 and not report["runner"].get("in_process")
    else:
        assert report["runner"]["in_process"]
    assert report["domain_states"] > report["region_states"] > 0
    assert set(report["domain_states_by_fixed_point"]) == {"cobuchi", "reach_safe"}
    assert report["closed_loop"]["runs"] >= 100 and report["closed_loop"]["violations"] == 0
    assert report["closed_loop"]["initial_states"][0]["in_domain"]
    for fig in ("trajectory.png", "phase_plane.png"):
        assert (tmp_path / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "controller.dddmp").exists() and (tmp_path / "controller.json").exists()


@pytest.mark.slow
def test_tanks_controller_in_closed_loop(tanks_job):
    """Issue 'symbolic composition': a non-empty reach-and-stay controller for the ten tanks, >= 100 closed-loop
    runs of the concrete black boxes from random domain states, none violating the specification (the run is the
    session's ``tanks_job``)."""
    report = json.loads((tanks_job / "report.json").read_text())
    assert report["domain_states"] > report["region_states"] // 10
    closed = report["closed_loop"]
    assert closed["runs"] >= 100 and closed["violations"] == 0, closed["first_violation"]
    assert closed["initial_states"][0]["x0"] == [5, 6, 65, 7, 7.5, 70, 8, 65.5, 75, 80]
    assert (tanks_job / "trajectory.png").exists()
