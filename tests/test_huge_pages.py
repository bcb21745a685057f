"""workers.huge_pages: the command line starts itself again with glibc's malloc asking for huge pages."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from workers.huge_pages import ENV, TUNABLE, with_huge_pages

ROOT = Path(__file__).resolve().parents[1]
SHOW = ("import os, sys; from workers.huge_pages import restart_with_huge_pages; print('before', os.getpid(), "
        "flush=True); restart_with_huge_pages(); print('after', os.getpid(), os.environ.get('GLIBC_TUNABLES'), "
        "os.environ.get('COMPABS_HUGE_PAGES'), sys.argv[1:])")


def run(env: dict[str, str]) -> list[list[str]]:
    out = subprocess.run([sys.executable, "-c", SHOW, "one", "two"], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=60, check=True)
    return [line.split(" ", 2) for line in out.stdout.splitlines()]


def test_the_tunable_joins_the_others():
    assert with_huge_pages({})["GLIBC_TUNABLES"] == TUNABLE
    assert with_huge_pages({"GLIBC_TUNABLES": "glibc.malloc.tcache_count=0"})["GLIBC_TUNABLES"] == \
        f"glibc.malloc.tcache_count=0:{TUNABLE}"
    assert with_huge_pages({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"})["GLIBC_TUNABLES"] == "glibc.malloc.hugetlb=0"


@pytest.mark.skipif(sys.platform != "linux" or platform.libc_ver()[0] != "glibc", reason="glibc on Linux only")
def test_a_process_starts_again_once_under_the_tunable_unless_told_not_to():
    base = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", ENV)}
    base["PYTHONPATH"] = str(ROOT)
    # started again: the same process (PID), the same arguments, the tunable set, once
    (b1, pid1), (b2, pid2), (a, pid3, rest) = run(base)
    assert (b1, b2, a) == ("before", "before", "after") and pid1 == pid2 == pid3
    assert rest == f"{TUNABLE} 1 ['one', 'two']"
    # told not to, or already under a hugetlb value: as started
    for extra, tunables in (({ENV: "0"}, "None"), ({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, "glibc.malloc.hugetlb=0")):
        lines = run({**base, **extra})
        assert [line[0] for line in lines] == ["before", "after"]
        assert lines[1][2].startswith(f"{tunables} ")
