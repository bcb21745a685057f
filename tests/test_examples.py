"""The paper's cases end to end: exact counts, and audits of >= 10^6 transitions with no violation."""

import json

import pytest

from pipelines.job import run_abstraction
from pipelines.spec import load_spec
from service.cli import main

from .conftest import EXAMPLES


@pytest.mark.slow
@pytest.mark.parametrize(
    "name,states,region",
    [("consensus", 1_406_408_618_241, 9_493_117), ("tanks", 13_422_659_310_152_401, 2_015_993_900_449)],
)
def test_paper_case(tmp_path, name, states, region):
    assert main(["run", str(EXAMPLES / f"{name}.yaml"), "--out", str(tmp_path), "--quiet"]) == 0
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


def test_small_example_report(tmp_path):
    assert main(["run", str(EXAMPLES / "small.yaml"), "--out", str(tmp_path), "--quiet"]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["abstract_states"] == 33**2
    assert report["audit"]["violations"] == 0
    assert list((tmp_path / "relations").glob("*.npz"))
