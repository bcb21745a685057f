"""Child processes that run a module of this package (``python -m pipelines.<module>``).

The audit beside synthesis (:mod:`.audit_beside`) and the partitioned CPre's helpers (:mod:`.partitioned_cpre`)
run as such children. They must import the very package their parent runs, which need not be installed (a
checkout): its directory goes first on ``PYTHONPATH``, and the child starts in it, because ``python -m`` puts
its working directory on ``sys.path`` before ``PYTHONPATH`` (a parent sitting in a directory with another
``pipelines``, say an older checkout, would otherwise give its children that one).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])
"""The directory holding the ``pipelines`` and ``workers`` packages."""


def start_module(module: str, *args: str, **popen: Any) -> subprocess.Popen:
    """``python -m module args...`` as a child of this process, importing this package (module docstring).

    ``popen``: further :class:`subprocess.Popen` arguments (pipes, ``pass_fds``); not ``env`` or ``cwd``.
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([PACKAGE_ROOT, *filter(None, [env.get("PYTHONPATH")])])
    return subprocess.Popen([sys.executable, "-m", module, *args], env=env, cwd=PACKAGE_ROOT, **popen)
