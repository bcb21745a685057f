import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
EXAMPLES = ROOT / "examples"


@pytest.fixture
def examples_dir() -> Path:
    return EXAMPLES


@pytest.fixture(scope="module")
def cluster():
    """A real local Dask cluster with two worker processes, one per test module that asks for it."""
    from workers.cluster import connect

    with connect(workers=2) as conn:
        yield conn


@pytest.fixture
def client(cluster):
    """The cluster's client; afterwards, waits for two workers again (a fault test may have killed some)."""
    yield cluster.client
    cluster.client.wait_for_workers(2, timeout=240)


# The trust campaign's table (issue 7) at the end of the session, with or without -s.
from .trust_log import pytest_terminal_summary  # noqa: E402,F401
