"""The dashboard in a real browser: Playwright drives Debian's Chromium against ``compabs serve``.

One server serves the module: ``compabs serve`` as a subprocess on a free port with a temporary ``--data``, its
embedded two-worker Dask cluster and ``COMPABS_TOKEN`` set. Without the token the page says 401; with it, the
small example submitted through the form runs to the end while the page shows every stage's progress reach
100 % and then the trajectory figure. A second server (``--in-process``, over a job store seeded with a job whose
counts exceed 2^53) serves the exact-integer test and ``/docs`` and ``/redoc`` on a closed network (every request
but the server's aborted). Chromium is Debian's (``.ci/run`` installs it); ``playwright install`` is never run.
"""

from __future__ import annotations

import json
import re
import secrets
import time
from pathlib import Path

import httpx
import pytest
import yaml

from .conftest import EXAMPLES, ROOT
from .processes import Proc, clean_env, free_port, wait_http_ok

CHROMIUM = Path("/usr/bin/chromium")
#: Without the networking flags Chromium floods the closed network with refused connections (ENGINEERING.md).
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-quic", "--no-first-run"]
STAGES = ("plan", "lipschitz", "subsystems", "interconnection", "audit", "synthesis", "closed_loop")
TOKEN = "dashboard-test-" + secrets.token_hex(8)
#: The small example takes ~15 s alone on this 2-core machine; allow for a loaded one.
JOB_TIMEOUT_MS = 300_000

needs_chromium = pytest.mark.skipif(not CHROMIUM.exists(),
                                    reason=f"{CHROMIUM} is missing: install Debian's chromium (.ci/run does)")


def test_embedded_example_is_small_yaml():
    """The form's "Load example" text is examples/small.yaml, verbatim (no drift)."""
    html = (ROOT / "service" / "static" / "index.html").read_text()
    m = re.search(r'<script type="text/plain" id="example-spec">(.*?)</script>', html, re.S)
    assert m, "index.html has no #example-spec"
    assert m.group(1) == (EXAMPLES / "small.yaml").read_text()


class Server:
    def __init__(self, url: str, proc: Proc) -> None:
        self.url = url
        self.proc = proc

    def job(self, job_id: str) -> dict:
        r = httpx.get(f"{self.url}/jobs/{job_id}", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
        return r.json() if r.status_code == 200 else {"status_code": r.status_code, "text": r.text}

    def explain(self, job_id: str | None = None) -> str:
        parts = [self.proc.tail(60, skip='"GET /jobs HTTP')]  # not the page's polls
        if job_id:
            parts.insert(0, "job: " + json.dumps(self.job(job_id), indent=1)[:4000])
        return "\n".join(parts)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is missing: install Debian's chromium (.ci/run does)")
    tmp = tmp_path_factory.mktemp("dashboard")
    port = free_port()
    argv = ["compabs", "serve", "--host", "127.0.0.1", "--port", str(port), "--data", str(tmp / "data"),
            "--workers", "2"]
    proc = Proc("compabs serve", argv, clean_env(COMPABS_TOKEN=TOKEN), tmp, tmp / "serve.log")
    try:
        url = f"http://127.0.0.1:{port}"
        wait_http_ok(f"{url}/health", 120, [proc])
        yield Server(url, proc)
    finally:
        proc.stop()


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is missing: install Debian's chromium (.ci/run does)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def open_page(browser, server):
    """``open_page(token=None)``: a fresh browser context (empty localStorage) on the dashboard."""
    contexts, errors = [], []

    def _open(token: str | None = None):
        context = browser.new_context()
        contexts.append(context)
        if token is not None:
            context.add_init_script(f"window.localStorage.setItem('compabs.token', {json.dumps(token)});")
        page = context.new_page()
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{server.url}/")
        return page

    yield _open
    for context in contexts:
        context.close()
    assert not errors, f"JavaScript errors on the page: {errors}"


def _spec_text(**changes) -> str:
    if not changes:
        return (EXAMPLES / "small.yaml").read_text()
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["subsystems"][0].update(changes)
    return yaml.safe_dump(data, sort_keys=False)


def _shown(job) -> str:
    """What the page shows of a job, for failure messages."""
    try:
        return "page: " + job.inner_text(timeout=2000)
    except Exception as exc:  # the element may be missing: say so rather than fail again
        return f"page: the job is not shown ({type(exc).__name__})"


def _submit(page, text: str) -> str:
    """Paste a spec into the form, submit it, return the new job's id."""
    from playwright.sync_api import expect

    page.fill("#spec", text)
    page.click("#submit")
    message = page.locator("#submit-message")
    expect(message).to_have_attribute("data-submitted-id", re.compile(r".+"), timeout=30_000)
    return message.get_attribute("data-submitted-id")


@pytest.mark.slow
@needs_chromium
def test_dashboard_token_errors_failed_and_cancelled_jobs(open_page, server):
    """No token: the page shows the 401 message. With the token: the list loads, a spec the API rejects shows
    the API's message, a job that fails shows its error, the cancel button cancels a job."""
    from playwright.sync_api import expect

    page = open_page()
    notice = page.locator("#notice")
    expect(notice).to_be_visible(timeout=15_000)
    expect(notice).to_contain_text("401")
    page.click("#submit")  # the prefilled example, still without a token
    expect(page.locator("#submit-message")).to_contain_text("Not submitted", timeout=15_000)

    page.fill("#token", TOKEN)
    page.press("#token", "Enter")
    expect(notice).to_be_hidden(timeout=15_000)
    assert page.evaluate("localStorage.getItem('compabs.token')") == TOKEN

    # A non-whitelisted expression: 4xx, and the page shows the API's message naming it.
    page.fill("#spec", _spec_text(dynamics="__import__('os').getcwd()"))
    page.click("#submit")
    rejected = page.locator("#submit-message")
    expect(rejected).to_contain_text("Not submitted", timeout=15_000)
    expect(rejected).to_contain_text("__import__")

    # The paper's L_x = 1.599 is contradicted by the data: the job fails in its lipschitz stage.
    job_id = _submit(page, _spec_text(lipschitz={"x": 1.599, "w": 0.16}))
    job = page.locator(f'[data-job-id="{job_id}"]')
    try:
        expect(job).to_have_attribute("data-status", "failed", timeout=JOB_TIMEOUT_MS)
        expect(job.locator(".error")).to_be_visible()
        expect(job.locator(".error")).to_contain_text("contradicted by the data")
        expect(job.locator(".cancel")).to_be_hidden()
        expect(job.locator("img")).to_have_count(0)
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{_shown(job)}\n{server.explain(job_id)}") from None

    # The cancel button of a job just submitted (it takes ~10 s; the click comes within a second).
    job_id = _submit(page, _spec_text())
    job = page.locator(f'[data-job-id="{job_id}"]')
    try:
        job.locator(".cancel").click(timeout=10_000)
        expect(job).to_have_attribute("data-status", "cancelled", timeout=120_000)
        expect(job.locator(".cancel")).to_be_hidden()
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{_shown(job)}\n{server.explain(job_id)}") from None


@pytest.mark.slow
@needs_chromium
def test_dashboard_runs_small_example(open_page, server):
    """Submit examples/small.yaml through the form; every stage's bar reaches 100 %, the job succeeds, the
    trajectory figure loads and the summary shows the example's counts."""
    from playwright.sync_api import expect

    page = open_page(TOKEN)
    streams = []
    page.on("request", lambda r: streams.append(r.url) if "/events" in r.url else None)
    expect(page.locator("#notice")).to_be_hidden()

    t0 = time.monotonic()
    job_id = _submit(page, (EXAMPLES / "small.yaml").read_text())
    job = page.locator(f'[data-job-id="{job_id}"]')
    try:
        for stage in STAGES:
            expect(job.locator(f'[data-stage="{stage}"] .pct')).to_have_text("100%", timeout=JOB_TIMEOUT_MS)
        expect(job).to_have_attribute("data-status", "succeeded", timeout=30_000)
        expect(job.locator(".status")).to_have_text("succeeded")
        expect(job.locator(".error")).to_be_hidden()
        expect(job.locator(".cancel")).to_be_hidden()
        for stage in STAGES:
            assert job.locator(f'[data-stage="{stage}"] progress').evaluate("p => p.value") == 100, stage
        img = job.locator('img[data-figure="trajectory.png"]')
        expect(img).to_be_visible(timeout=30_000)
        img.scroll_into_view_if_needed()
        page.wait_for_function("img => img.complete && img.naturalWidth > 0", arg=img.element_handle(),
                               timeout=30_000)
        expect(job.locator('img[data-figure="phase_plane.png"]')).to_have_count(1)
        # small.yaml: 33^2 abstract states, a 629-state controller domain (README).
        expect(job.locator('dd[data-key="abstract_states"]')).to_have_text("1,089")
        expect(job.locator('dd[data-key="domain_states"]')).to_have_text("629")
        # The embedded cluster's Dask dashboard (bound to 127.0.0.1).
        expect(job.locator("a.dask-dashboard")).to_have_attribute(
            "href", re.compile(r"^http://127\.0\.0\.1:\d+/status$"))
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{_shown(job)}\n{server.explain(job_id)}") from None
    print(f"small example through the dashboard: {time.monotonic() - t0:.1f} s")
    # Progress came from the job's event stream, which carries the token in its URL.
    assert any(f"/jobs/{job_id}/events" in u and f"token={TOKEN}" in u for u in streams), streams


# ============================================================================ exact integers, /docs and /redoc offline
#: The tanks' abstract states (examples/tanks.yaml: 41^10), beyond JavaScript's exact integers (2^53).
TANKS_STATES = 41**10
#: 2^53 + 1: the first integer a double cannot hold.
FIRST_INEXACT = 2**53 + 1
XSS = "x';alert(document.domain)//"


@pytest.fixture(scope="module")
def seeded_server(tmp_path_factory):
    """``compabs serve --in-process`` over a job store holding one succeeded job whose counts exceed 2^53."""
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is missing: install Debian's chromium (.ci/run does)")
    from service.job_store import JobStatus
    from service.manager import new_store
    from service.settings import Settings

    tmp = tmp_path_factory.mktemp("seeded")
    store = new_store(Settings(data_dir=tmp / "data"))
    try:
        store.create("tanks0000000001", "tanks", "{}")
        store.set_status("tanks0000000001", JobStatus.RUNNING, started=True)
        store.add_progress("tanks0000000001", "subsystems", TANKS_STATES, TANKS_STATES, "")
        store.set_status("tanks0000000001", JobStatus.SUCCEEDED, figures=[], summary={
            "abstract_states": TANKS_STATES, "region_states": 17**10, "domain_states": FIRST_INEXACT,
            "audit_transitions": 1_000_000, "audit_violations": 0})
    finally:
        store.close()
    port = free_port()
    argv = ["compabs", "serve", "--host", "127.0.0.1", "--port", str(port), "--data", str(tmp / "data"), "--in-process"]
    proc = Proc("compabs serve", argv, clean_env(COMPABS_TOKEN=TOKEN), tmp, tmp / "serve.log")
    try:
        url = f"http://127.0.0.1:{port}"
        wait_http_ok(f"{url}/health", 120, [proc])
        yield Server(url, proc)
    finally:
        proc.stop()


@pytest.fixture
def closed_network(browser, seeded_server):
    """``closed_network(token=None)``: a fresh context in which only the server answers; every other request is
    aborted and recorded. After the test: no request left the server, no JavaScript error, no dialog."""
    contexts, errors, outside, dialogs = [], [], [], []

    def route(r):
        if r.request.url.startswith(seeded_server.url + "/"):
            r.continue_()
        else:
            outside.append(r.request.url)
            r.abort()

    def _open(token: str | None = None):
        context = browser.new_context()
        contexts.append(context)
        context.route("**/*", route)
        if token is not None:
            context.add_init_script(f"window.localStorage.setItem('compabs.token', {json.dumps(token)});")
        page = context.new_page()
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
        return page

    yield _open
    for context in contexts:
        context.close()
    assert not outside, f"requests beyond the server: {outside}"
    assert not errors, f"JavaScript errors on the page: {errors}"
    assert not dialogs, f"dialogs opened: {dialogs}"


@needs_chromium
def test_dashboard_shows_exact_integers(closed_network, seeded_server):
    """13,422,659,310,152,401 abstract states, not JavaScript's 13,422,659,310,152,400 (beyond 2^53)."""
    from playwright.sync_api import expect

    api = httpx.get(f"{seeded_server.url}/jobs/tanks0000000001", headers={"Authorization": f"Bearer {TOKEN}"})
    assert f'"abstract_states":{TANKS_STATES}' in api.text.replace(" ", "")
    page = closed_network(TOKEN)
    page.goto(f"{seeded_server.url}/")
    job = page.locator('[data-job-id="tanks0000000001"]')
    try:
        expect(job).to_have_attribute("data-status", "succeeded", timeout=30_000)
        expect(job.locator('dd[data-key="abstract_states"]')).to_have_text("13,422,659,310,152,401")
        expect(job.locator('dd[data-key="domain_states"]')).to_have_text("9,007,199,254,740,993")
        expect(job.locator('dd[data-key="region_states"]')).to_have_text("2,015,993,900,449")
        expect(job.locator('dd[data-key="audit_transitions"]')).to_have_text("1,000,000")
        expect(job.locator('[data-stage="subsystems"] .stage-message')).to_have_text(
            "13,422,659,310,152,401 / 13,422,659,310,152,401")
        expect(job.locator('[data-stage="subsystems"] .pct')).to_have_text("100%")
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{_shown(job)}\n{seeded_server.explain()}") from None


@needs_chromium
def test_swagger_ui_renders_offline_with_the_users_token(closed_network, seeded_server):
    """/docs on a closed network: Swagger UI from this server, the token typed into the page's form (nothing
    from the URL in the page: the ``?token=`` script injection does nothing), operations listed, "Try it out"
    authorised."""
    from playwright.sync_api import expect

    page = closed_network()
    page.goto(f"{seeded_server.url}/docs?token={XSS}")
    expect(page.locator("#docs-notice")).to_contain_text("401", timeout=30_000)
    page.fill("#token", TOKEN)
    page.press("#token", "Enter")
    expect(page.locator("#docs-notice")).to_be_hidden(timeout=30_000)
    ops = page.locator(".opblock")
    expect(ops.first).to_be_visible(timeout=30_000)
    paths = {t.strip() for t in page.locator(".opblock-summary-path").all_inner_texts()}
    assert {"/jobs", "/jobs/{job_id}", "/jobs/{job_id}/events", "/schema", "/health"} <= {
        p.replace("\u200b", "") for p in paths}, paths
    # "Try it out" on GET /jobs sends the token the user gave as the header
    get_jobs = page.locator(".opblock-get", has=page.locator('.opblock-summary-path[data-path="/jobs"]'))
    get_jobs.locator(".opblock-summary").click()
    get_jobs.locator("button.try-out__btn").click()
    get_jobs.locator("button.execute").click()
    expect(get_jobs.locator(".live-responses-table tbody .response-col_status").first).to_have_text(
        "200", timeout=30_000)
    expect(get_jobs.locator(".live-responses-table")).to_contain_text("tanks0000000001")


@needs_chromium
def test_redoc_renders_offline(closed_network, seeded_server):
    """/redoc on a closed network, with the dashboard's token: ReDoc from this server lists the operations."""
    from playwright.sync_api import expect

    page = closed_network(TOKEN)
    page.goto(f"{seeded_server.url}/redoc?token={XSS}")
    expect(page.get_by_role("heading", name="Submit Job")).to_be_visible(timeout=30_000)
    for op in ("List Jobs", "Cancel Job", "Job Events", "Spec Schema"):
        expect(page.get_by_role("heading", name=op)).to_be_attached()
    expect(page.locator("#docs-notice")).to_be_hidden()
