"""The engine comparison of ``bench/engines.py`` (issue 49) on ``examples/small.yaml``: the replica of the fixed point
on ``dd.cudd`` gives the synthesis's own domain, and ``oxidd`` (plain and complement-edge BDDs, one and two threads)
gives the same set, compared in oxidd's manager after reading CUDD's DDDMP file (CUDD's reader trusts its input, so
files go from CUDD to oxidd only). No time is asserted.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.engines import export_problem, run_engine
from pipelines.symbolic.engines import oxidd_available


@pytest.fixture(scope="module")
def problem(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """``small.yaml`` abstracted, its CPre written as a problem, and the synthesis's own domain (the reference)."""
    d = tmp_path_factory.mktemp("engines")
    rec = export_problem("small", None, d, pipeline=True, say=lambda message: None)
    return d, rec


def test_the_cudd_replica_computes_the_synthesis_domain(problem, tmp_path):
    d, rec = problem
    row = run_engine(d / "problem", "dd.cudd", 1, d / "pipeline.dddmp", tmp_path / "domain.dddmp")
    assert row["same_set"] and row["symmetric_difference"] == 0
    assert row["domain_states"] == rec["pipeline"]["domain_states"] > 0
    assert row["iterations"] > 1 and row["peak_rss_mb"] > 0


@pytest.mark.skipif(not oxidd_available(), reason="oxidd is not installed (the test extra installs it: pip install -e .[test]); "
                                                  "the engine comparison needs it")
@pytest.mark.parametrize(("name", "threads"), [("oxidd.bdd", 1), ("oxidd.bcdd", 1), ("oxidd.bcdd", 2)])
def test_oxidd_gives_the_same_domain_set(problem, tmp_path, name, threads):
    d, rec = problem
    row = run_engine(d / "problem", name, threads, d / "pipeline.dddmp", tmp_path / "domain.dddmp")
    assert row["same_set"] and row["symmetric_difference"] == 0
    assert row["domain_states"] == rec["pipeline"]["domain_states"]
    assert (tmp_path / "domain.dddmp").stat().st_size > 0
