"""Helpers for tests that run compabs's commands as real processes (the browser and compose tests).

Every process is started in its own session, so that stopping it stops its whole process group (the Dask nannies
and worker processes it spawned); its output goes to a log file whose tail failures quote.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import httpx

#: The environment variables compabs reads; tests set them explicitly and never inherit them.
COMPABS_ENV = ("COMPABS_TOKEN", "COMPABS_DATA_DIR", "COMPABS_DB_URL", "COMPABS_SCHEDULER", "COMPABS_TLS_CA",
               "COMPABS_TLS_CERT", "COMPABS_TLS_KEY", "COMPABS_INSECURE_SCHEDULER")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without compabs's variables, with the venv's scripts first on PATH."""
    env = {k: v for k, v in os.environ.items() if k not in COMPABS_ENV}
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


class Proc:
    """A command running in its own process group, logging to ``log``."""

    def __init__(self, name: str, argv: Sequence[str], env: Mapping[str, str], cwd: Path, log: Path) -> None:
        self.name = name
        self.argv = list(argv)
        self.log = log
        self._log_file = open(log, "wb")
        try:
            self.popen = subprocess.Popen(
                self.argv, env=dict(env), cwd=cwd, stdin=subprocess.DEVNULL, stdout=self._log_file,
                stderr=subprocess.STDOUT, start_new_session=True,
            )
        except BaseException:
            self._log_file.close()
            raise

    def tail(self, lines: int = 40, skip: str | None = None) -> str:
        """The log's last ``lines`` lines, without those containing ``skip``."""
        try:
            text = self.log.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        if skip:
            text = [line for line in text if skip not in line]
        return f"--- {self.name}: {' '.join(self.argv)} (last {lines} lines of {self.log})\n" + "\n".join(text[-lines:])

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, timeout: float = 15.0) -> None:
        """SIGTERM to the process group; SIGKILL to whatever is left of it after ``timeout`` seconds."""
        _signal_group(self.popen.pid, signal.SIGTERM)
        try:
            self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
        # The leader may be stuck, or gone while children it spawned (nannies, workers) linger.
        _signal_group(self.popen.pid, signal.SIGKILL)
        try:
            self.popen.wait(5)
        except subprocess.TimeoutExpired:
            pass
        self._log_file.close()


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


def wait_until(check: Callable[[], bool], timeout: float, what: str, procs: Sequence[Proc] = (),
               interval: float = 0.25) -> None:
    """Poll ``check`` until it is true; fail (quoting the logs) on timeout or when a process exits."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            if check():
                return
        except (httpx.HTTPError, OSError):
            pass
        dead = [p for p in procs if not p.alive()]
        if dead:
            raise AssertionError(f"{what}: {dead[0].name} exited with status {dead[0].popen.returncode}\n"
                                 + "\n".join(p.tail() for p in procs))
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout:g} s\n" + "\n".join(p.tail() for p in procs))
        time.sleep(interval)


def wait_http_ok(url: str, timeout: float, procs: Sequence[Proc] = ()) -> None:
    wait_until(lambda: httpx.get(url, timeout=5).status_code == 200, timeout, f"GET {url}", procs)
