"""Fixtures and helpers shared by the test modules.

* ``cluster`` / ``client``: one real embedded Dask cluster (two worker processes, :func:`workers.cluster.connect`)
  per test module that asks for it, brought back to two idle workers after every test, and replaced by a fresh
  one when that fails (a hung task, a worker that was not replaced), so that a fault one test leaves behind
  cannot block the tests after it.
* :func:`count_work` and :func:`assert_linear_compile`: operation counts (Python lines executed, texts handed to
  the parser), the load-independent stand-in for the wall-clock bounds tests must not assert.
"""

from __future__ import annotations

import ast
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
EXAMPLES = ROOT / "examples"


@pytest.fixture
def examples_dir() -> Path:
    return EXAMPLES


# ================================================================================================ time limits
#: pytest-timeout's limit for tests marked ``slow`` (the paper's cases, the benchmark, the end-to-end runs), which
#: on a loaded 2-core machine may legitimately take longer than the default ``timeout`` of pyproject.toml; a test
#: that sets ``@pytest.mark.timeout(N)`` keeps its own, and ``--timeout`` on the command line overrides both.
SLOW_TIMEOUT = 1800


def pytest_collection_modifyitems(config, items):
    if config.getoption("timeout", None) is not None:
        return
    for item in items:
        if item.get_closest_marker("slow") is not None and item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(SLOW_TIMEOUT))


def _hypothesis_without_clocks() -> None:
    """Hypothesis's time checks off for every test: the per-example ``deadline`` and the ``too_slow`` health check
    fail a test on a loaded machine, not on a wrong result. A test's own ``@settings`` overrides only what it sets."""
    try:
        from hypothesis import HealthCheck, settings
    except ImportError:  # pragma: no cover - hypothesis is in the test extra
        return
    settings.register_profile("compabs", deadline=None, suppress_health_check=[HealthCheck.too_slow])
    settings.load_profile("compabs")


_hypothesis_without_clocks()


# ================================================================================================ the cluster
#: Seconds the ``client`` fixture waits, after a test, for the cluster to have its two workers back and idle
#: (a killed worker's nanny starts a new process within seconds on an idle machine). Past it the cluster is
#: replaced and the test's teardown fails, naming what was wrong. Only a bound on a hang, not a speed requirement.
RECOVER_TIMEOUT = 180.0
#: Seconds the ``client`` fixture waits before a test for a cluster left unsettled (an interrupted teardown).
SETTLE_TIMEOUT = 60.0
#: distributed's LocalCluster gives the nanny of a worker that died ``distributed.deploy.lost-worker-timeout``
#: (15 s by default) to have a new worker process registered under the same name, and otherwise closes that
#: nanny for good: the cluster stays one worker short. On a loaded machine, or when a worker is killed again
#: while the previous kill's timer runs (test_worker_killed_in_every_runner_stage), the restart misses it; that
#: was "the killed worker was not replaced within 240 s". The shared cluster waits for its nannies' restarts.
LOST_WORKER_TIMEOUT = "1h"


def _scheduler_tasks(dask_scheduler) -> int:
    return len(dask_scheduler.tasks)


def _executing(dask_worker) -> int:
    return len(dask_worker.state.executing)


def _scheduler_pending(dask_scheduler) -> int:
    """Tasks the scheduler still has to run (held results, say in a failed test's traceback, do not count)."""
    return sum(1 for ts in dask_scheduler.tasks.values() if ts.state in ("waiting", "queued", "processing", "no-worker"))


def wait_idle(client, timeout: float = 60.0) -> None:
    """Until the scheduler holds no task and no worker runs one (cancelled tasks still finish running)."""
    deadline = time.monotonic() + timeout
    while True:
        tasks = client.run_on_scheduler(_scheduler_tasks)
        running = client.run(_executing, on_error="ignore")
        if tasks == 0 and not any(running.values()):
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"cluster still busy after {timeout:g} s: {tasks} tasks on the scheduler, "
                                 f"tasks executing per worker {running}")
        time.sleep(0.1)


class SharedCluster:
    """The embedded cluster of :func:`workers.cluster.connect` with ``workers`` worker processes.

    ``client`` and ``info`` are those of the current cluster: :meth:`replace` swaps in a fresh one, so a test
    always reads them through this object (or gets the client from the ``client`` fixture).
    """

    def __init__(self, workers: int = 2) -> None:
        import dask
        import distributed  # noqa: F401 - its defaults are in dask's config from here on

        self.workers = workers
        # Read by the LocalCluster (in this process) whenever a worker is removed: set for the cluster's lifetime,
        # put back by close().
        self._lost_worker_timeout = dask.config.get("distributed.deploy.lost-worker-timeout")
        dask.config.set({"distributed.deploy.lost-worker-timeout": LOST_WORKER_TIMEOUT})
        try:
            self._conn = self._connect()
        except BaseException:
            self._restore_config()
            raise

    def _restore_config(self) -> None:
        import dask

        dask.config.set({"distributed.deploy.lost-worker-timeout": self._lost_worker_timeout})

    def _connect(self):
        from workers.cluster import connect

        return connect(workers=self.workers)

    @property
    def client(self):
        return self._conn.client

    @property
    def info(self) -> dict[str, Any]:
        return self._conn.info

    def problem(self) -> str | None:
        """What keeps the cluster from being whole and idle now, or ``None``."""
        try:
            registered = len(self.client.scheduler_info(n_workers=-1)["workers"])
            answering = self.client.run(os.getpid, on_error="ignore")
            tasks = self.client.run_on_scheduler(_scheduler_pending)
            executing = self.client.run(_executing, on_error="ignore")
        except Exception as exc:  # a closed comm, a timeout: the cluster is not usable
            return f"the cluster does not answer: {type(exc).__name__}: {exc}"
        if registered != self.workers or len(answering) != self.workers:
            return f"{registered} workers registered and {len(answering)} answering, not {self.workers}"
        if tasks or any(executing.values()):
            return f"busy: {tasks} tasks to run on the scheduler, tasks executing per worker {executing}"
        return None

    def settle(self, timeout: float) -> str | None:
        """Wait up to ``timeout`` seconds for the cluster to be whole and idle; ``None`` once it is, else what
        was still wrong at the deadline."""
        deadline = time.monotonic() + timeout
        while True:
            problem = self.problem()
            if problem is None:
                return None
            if time.monotonic() > deadline:
                return problem
            time.sleep(0.2)

    def replace(self) -> None:
        """Close this cluster (its worker processes SIGKILLed first: a task blocked in C cannot be stopped
        otherwise) and start a fresh one."""
        import signal

        old = self._conn
        try:
            pids = old.client.run(os.getpid, on_error="ignore")
        except Exception:
            pids = {}
        for pid in pids.values():
            try:
                os.kill(pid, signal.SIGKILL)  # our own cluster's worker processes, by id
            except ProcessLookupError:
                pass
        try:
            old.client.close(timeout=60)
        except Exception:
            pass
        self._conn = self._connect()

    def close(self) -> None:
        try:
            self._conn.close()
        finally:
            self._restore_config()


@pytest.fixture(scope="session")
def tanks_job(tmp_path_factory) -> Path:
    """``compabs run examples/tanks.yaml --in-process`` once per session (its directory: report, controller, figures),
    for the tests that read what that run writes (the closed loop, the C export of its controller); each test reads
    it only. The run audits 10^5 stored transitions."""
    from service.cli import main

    out = tmp_path_factory.mktemp("tanks_job")
    args = ["run", str(EXAMPLES / "tanks.yaml"), "--out", str(out), "--quiet", "--in-process",
            "--audit-transitions", "100000"]
    assert main(args) == 0
    return out


@pytest.fixture(scope="module")
def cluster():
    """A real embedded Dask cluster with two worker processes, one per test module that asks for it; closed at
    the end of the module."""
    shared = SharedCluster(workers=2)
    try:
        yield shared
    finally:
        shared.close()


@pytest.fixture
def client(cluster):
    """The cluster's client. Before the test the cluster is whole and idle; after it, it is brought back to two
    idle workers (a fault test may have killed some, or left a task running) within :data:`RECOVER_TIMEOUT`
    seconds, or replaced by a fresh cluster and the test's teardown fails saying why."""
    if cluster.settle(SETTLE_TIMEOUT) is not None:
        cluster.replace()  # left unsettled by an interrupted teardown: start the test on a fresh cluster
    yield cluster.client
    problem = cluster.settle(RECOVER_TIMEOUT)
    if problem is not None:
        cluster.replace()
        pytest.fail(f"the test left the cluster unusable for {RECOVER_TIMEOUT:g} s ({problem}); it was replaced "
                    "by a fresh cluster", pytrace=False)


# ================================================================================================ counting work
@dataclass
class Work:
    """What a call did, counted rather than timed (counts do not depend on the machine's load)."""

    #: Python lines executed by the call in this thread (``sys.settrace``): the same count on every run of the
    #: same code on the same interpreter, however loaded the machine.
    lines: int = 0
    #: Lengths of the texts the call handed to :func:`ast.parse`, in order.
    parsed: list[int] = field(default_factory=list)
    result: Any = None
    error: BaseException | None = None


def count_work(fn: Callable[..., Any], *args: Any, catch: tuple[type[BaseException], ...] = (), **kwargs: Any) -> Work:
    """Call ``fn(*args, **kwargs)`` counting the Python lines it executes and the texts it parses; an exception of
    a type in ``catch`` is returned in :attr:`Work.error`, any other propagates."""
    work = Work()
    real_parse = ast.parse

    def parse(source, *a, **k):
        work.parsed.append(len(source))
        return real_parse(source, *a, **k)

    def tracer(frame, event, arg):
        if event == "line":
            work.lines += 1
        return tracer

    previous = sys.gettrace()
    ast.parse = parse
    sys.settrace(tracer)
    try:
        work.result = fn(*args, **kwargs)
    except catch as exc:
        work.error = exc
    finally:
        sys.settrace(previous)
        ast.parse = real_parse
    return work


#: Bound on the work of compiling an expression: at most ``LINES_FIXED + LINES_PER_CHARACTER * len(text)`` Python
#: lines. Measured (CPython 3.11, 2026-11-25): at most 35 lines per character on the 4000-character payloads of
#: the hostile lists (88,600 lines for the largest), 300-500 lines for short texts. A compile that is
#: quadratic in its text (16 million steps at 4000 characters) or unbounded by the node limit exceeds it many
#: times over, on any machine.
LINES_PER_CHARACTER = 100
LINES_FIXED = 1000


def bracket_depth(text: str) -> int:
    """The deepest nesting of ``([{`` in ``text``."""
    depth = deepest = 0
    for ch in text:
        if ch in "([{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in ")]}":
            depth = max(depth - 1, 0)
    return deepest


def assert_linear_compile(compile_expression: Callable[..., Any], text: str, *args: Any, max_length: int = 4000,
                          **kwargs: Any) -> Work:
    """Compile ``text`` with ``compile_expression(text, *args, **kwargs)`` and assert that the work done is bounded
    by the text's length, not by the machine's load:

    * the parser ran at most once, on a text of at most ``max_length`` characters whose brackets nest at most
      ``MAX_DEPTH`` deep: an over-long or over-nested text is refused before it is parsed;
    * at most ``LINES_FIXED + LINES_PER_CHARACTER * len(text)`` Python lines were executed.

    Returns the :class:`Work`: ``error`` is the :class:`~pipelines.errors.ExpressionError` raised, or ``None``
    and ``result`` the compiled expression.
    """
    from pipelines.errors import ExpressionError
    from pipelines.expressions import MAX_DEPTH

    work = count_work(compile_expression, text, *args, catch=(ExpressionError,), **kwargs)
    shown = repr(text[:60])
    assert len(work.parsed) <= 1, f"{shown}: parsed {len(work.parsed)} times"
    if len(text) > max_length or bracket_depth(text) > MAX_DEPTH:
        assert work.parsed == [], f"{shown} ({len(text)} characters) reached the parser instead of being refused"
        assert work.error is not None, f"{shown} was accepted"
    bound = LINES_FIXED + LINES_PER_CHARACTER * len(text)
    assert work.lines <= bound, f"{shown}: {work.lines} Python lines to compile {len(text)} characters (bound {bound})"
    return work


# The trust campaign's table (issue 7) at the end of the session, with or without -s.
from .trust_log import pytest_terminal_summary  # noqa: E402,F401
