import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
EXAMPLES = ROOT / "examples"


@pytest.fixture
def examples_dir() -> Path:
    return EXAMPLES


# The trust campaign's table (issue 7) at the end of the session, with or without -s.
from .trust_log import pytest_terminal_summary  # noqa: E402,F401
