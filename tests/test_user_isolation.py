"""Users of one server are kept apart by their tokens (issue 47): a user's token sees, reads, follows, downloads
and cancels only its own jobs; another user's job answers exactly as an unknown id does (so ids are not an
oracle); ``GET /jobs`` lists only the caller's jobs; the operator's token sees and may cancel every job.

The app runs in this process (``TestClient``) with in-process jobs and the real SQLite job store: real job
processes under the API's supervisor, nothing replaced. Nothing here asserts a speed.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings

from .test_fair_queue import ALICE, BOB, OPERATOR, auth, submit, users_settings
from .test_service_processes import ended, long_in, small, wait_until

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def client(tmp_path_factory) -> Iterator[TestClient]:
    with TestClient(create_app(users_settings(tmp_path_factory.mktemp("isolation") / "data"))) as c:
        yield c


@pytest.fixture(scope="module")
def alices_done(client) -> dict[str, Any]:
    """Alice's job, succeeded, with a controller and figures."""
    job_id = submit(client, small(), ALICE)
    done = wait_until(client, job_id, ended, "alice's job to end")
    assert done["status"] == "succeeded", done
    assert done["figures"], done
    return done


def unknown_like(job_id: str) -> str:
    """An id no job has, of the same form as ``job_id``."""
    return uuid.uuid4().hex[:len(job_id)]


def same_as_unknown(c: TestClient, method: str, path: str, job_id: str, headers: dict[str, str]) -> httpx.Response:
    """Request ``path`` (holding ``{id}``) for ``job_id`` and for an unknown id of its form: the two answers are
    404s alike in every byte but the id, and in their headers (but the date); the first answer."""
    other = unknown_like(job_id)
    theirs = c.request(method, path.format(id=job_id), headers=headers)
    none = c.request(method, path.format(id=other), headers=headers)
    assert theirs.status_code == none.status_code == 404, (path, theirs.text, none.text)
    assert theirs.content.replace(job_id.encode(), b"<id>") == none.content.replace(other.encode(), b"<id>")
    assert theirs.json() == {"detail": f"no job {job_id}"}
    assert {k: v for k, v in theirs.headers.items() if k != "date"} == \
        {k: v for k, v in none.headers.items() if k != "date"}, path
    return theirs


#: Every route of one job, ``{id}`` for its id (``{fig}``: one of its figures).
PATHS = [("GET", "/jobs/{id}"), ("GET", "/jobs/{id}/events"), ("GET", "/jobs/{id}/report"),
         ("GET", "/jobs/{id}/figures/{fig}"), ("GET", "/jobs/{id}/controller"), ("DELETE", "/jobs/{id}")]


@pytest.mark.parametrize(("method", "path"), PATHS)
def test_another_users_job_answers_as_an_unknown_one(client, alices_done, method, path):
    job_id = alices_done["id"]
    path = path.replace("{fig}", alices_done["figures"][0])
    same_as_unknown(client, method, path, job_id, auth(BOB))
    # The same with the token in the query, as the dashboard's event streams and images send it.
    same_as_unknown(client, method, path + f"?token={BOB}", job_id, {})
    # Alice herself, and the operator, get the job.
    for token in (ALICE, OPERATOR):
        if method == "GET":
            r = client.get(path.format(id=job_id), headers=auth(token))
            assert r.status_code == 200, (path, r.text)
    assert client.get(f"/jobs/{job_id}", headers=auth(ALICE)).json()["status"] == "succeeded"


def test_a_stream_of_anothers_job_resuming_is_refused_like_an_unknown_one(client, alices_done):
    """With ``Last-Event-ID`` (an ended job's stream that has every event answers 204 to its owner): 404 to
    another user, not 204, which would tell that the job exists and has ended."""
    job_id, last = alices_done["id"], "999999"
    r = client.get(f"/jobs/{job_id}/events", headers={**auth(ALICE), "Last-Event-ID": last})
    assert r.status_code == 204, r.text
    same_as_unknown(client, "GET", "/jobs/{id}/events", job_id, {**auth(BOB), "Last-Event-ID": last})


def test_the_owner_follows_its_job_with_the_token_in_the_query(client, alices_done):
    """The dashboard's ``EventSource`` path: every stored event of the owner's job, ending with its status."""
    with client.stream("GET", f"/jobs/{alices_done['id']}/events?token={ALICE}") as r:
        assert r.status_code == 200
        text = "".join(r.iter_text())
    assert "event: progress" in text and '"status":"succeeded"' in text.replace(" ", "")


def test_each_token_lists_its_own_jobs_and_cancels_only_those(client, alices_done):
    running = submit(client, long_in("subsystems"), ALICE)  # holds the one running slot (max_running = 1)
    queued = submit(client, small(synthesis=False), ALICE)
    bobs = submit(client, small(synthesis=False), BOB)
    try:
        wait_until(client, running, lambda j: j["status"] == "running", "alice's long job to start")

        def listed(token: str) -> dict[str, Any]:
            r = client.get("/jobs", headers=auth(token))
            assert r.status_code == 200, r.text
            return {j["id"]: j for j in r.json()["jobs"]}

        assert set(listed(ALICE)) == {alices_done["id"], running, queued}
        assert set(listed(BOB)) == {bobs}
        assert {alices_done["id"], running, queued, bobs} <= set(listed(OPERATOR))
        # Bob's own job shows its place; Alice's jobs are not his to see, read or cancel.
        assert listed(BOB)[bobs]["status"] == "queued" and listed(BOB)[bobs]["queue_position"] >= 1
        for job_id in (running, queued):
            same_as_unknown(client, "DELETE", "/jobs/{id}", job_id, auth(BOB))
        assert listed(ALICE)[running]["status"] == "running" and listed(ALICE)[queued]["status"] == "queued"
        # Alice cancels her queued job; the operator cancels Bob's.
        assert client.delete(f"/jobs/{queued}", headers=auth(ALICE)).json()["status"] == "cancelled"
        assert client.delete(f"/jobs/{bobs}", headers=auth(OPERATOR)).json()["status"] == "cancelled"
        assert listed(BOB)[bobs]["status"] == "cancelled"
    finally:
        for job_id in (running, queued, bobs):
            client.delete(f"/jobs/{job_id}", headers=auth(OPERATOR))
    assert wait_until(client, running, ended, "alice's long job to end")["status"] == "cancelled"


def test_a_server_without_user_tokens_shows_every_job_to_its_one_token(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", in_process=True, token=OPERATOR)
    with TestClient(create_app(settings)) as c:
        job_id = submit(c, small(synthesis=False), OPERATOR)
        assert [j["id"] for j in c.get("/jobs", headers=auth(OPERATOR)).json()["jobs"]] == [job_id]
        c.delete(f"/jobs/{job_id}", headers=auth(OPERATOR))
