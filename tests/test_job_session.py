"""What a job holds open between its abstraction and its report (:class:`workers.job_session.JobSession`): the
cluster client synthesis runs on, left open when it is the caller's, closed when the job started the cluster; the
abstraction record carries none of it."""

from __future__ import annotations

import dataclasses

import pytest

from pipelines.spec.model import load_spec
from workers.executors import Execution
from workers.job import abstract_job
from workers.job_session import JobSession
from workers.stages import Abstraction

from .conftest import EXAMPLES


def small():
    spec = load_spec(EXAMPLES / "small.yaml")
    return spec.model_copy(update={"options": spec.options.model_copy(update={"audit_transitions": 20_000})})


def test_the_abstraction_record_holds_results_only():
    assert [f.name for f in dataclasses.fields(Abstraction)] == ["spec", "network", "relations", "interconnection",
                                                                 "report"]


@pytest.mark.slow
def test_a_callers_client_is_held_for_synthesis_and_left_open(tmp_path, client):
    with JobSession() as session:
        result, runner = abstract_job(small(), tmp_path, Execution(client=client), session=session)
        assert session.client is client and session.connection is None
        assert session.pending_audit is not None and result.report["audit"]["pending"]
        session.finish_audit(result)
        assert result.report["audit"]["beside_synthesis"] and result.report["audit"]["violations"] == 0
    assert session.client is None and client.status == "running"


@pytest.mark.slow
def test_a_cluster_the_job_started_stays_up_until_the_session_closes(tmp_path):
    with JobSession() as session:
        abstract_job(small(), tmp_path, Execution(workers=1), audit=False, session=session)
        conn = session.connection
        assert conn is not None and session.client is conn.client
        assert conn.client.submit(sum, [1, 2]).result(timeout=60) == 3  # open for synthesis
    assert session.client is None and session.connection is None and conn.client.status == "closed"
    session.close()  # idempotent

