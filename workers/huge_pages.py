"""Transparent huge pages for the job's own process: glibc's malloc asked for them at startup.

CUDD walks its unique and computed tables at random, so its operations wait on TLB misses; where the kernel gives
transparent huge pages on request (``madvise``, a common setting), malloc asks only under
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` (glibc 2.35 on). The Dask workers get it from ``workers/dask.yaml``
(its ``pre-spawn-environ``: consensus synthesis about 8 % faster in one process, 11-13 % on two workers). glibc
reads the tunable once, when a process starts, so the command line starts itself again under it
(:func:`restart_with_huge_pages`) before its commands that build BDDs. ``COMPABS_HUGE_PAGES=0`` keeps the process
as started; elsewhere (not Linux, not glibc) nothing happens.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Mapping
from typing import NoReturn

TUNABLE = "glibc.malloc.hugetlb=1"
ENV = "COMPABS_HUGE_PAGES"
"""``0``: no restart. The restart itself sets it to ``1``, so that a process is started again at most once."""


def with_huge_pages(environ: Mapping[str, str]) -> dict[str, str]:
    """``environ`` with :data:`TUNABLE` among its ``GLIBC_TUNABLES`` (the other tunables kept; a ``hugetlb`` value
    already given wins)."""
    env = dict(environ)
    current = env.get("GLIBC_TUNABLES", "")
    if "glibc.malloc.hugetlb=" not in current:
        env["GLIBC_TUNABLES"] = f"{current}:{TUNABLE}" if current else TUNABLE
    return env


def restart_with_huge_pages() -> None:
    """Start this process again (``os.execve``, same PID, same command line) with :func:`with_huge_pages`, unless
    it runs so already, was started again already, ``COMPABS_HUGE_PAGES=0`` says not to, or the C library is not
    glibc on Linux. Returns only where it does not restart."""
    env = os.environ
    if env.get(ENV) in ("0", "1") or "glibc.malloc.hugetlb=" in env.get("GLIBC_TUNABLES", ""):
        return
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return
    restart_under({**with_huge_pages(env), ENV: "1"})


def restart_under(environ: Mapping[str, str]) -> NoReturn:
    """Start this process again under ``environ``: ``os.execve`` of the same interpreter with the same command line
    (``sys.orig_argv``: ``-m`` and ``-c`` included), so the PID and the open files stay; what was printed is
    flushed first."""
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], dict(environ))


__all__ = ["ENV", "TUNABLE", "restart_under", "restart_with_huge_pages", "with_huge_pages"]
