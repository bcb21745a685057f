"""docker-compose.yml without Docker: each service's command runs as a local process, and a job submitted to
the API runs on the two compose workers.

No Docker engine exists here, so the test reads docker-compose.yml and starts what it says: the same argv, the
environment it sets (``${VAR:-default}`` / ``${VAR:?message}`` interpolated as compose does), with the
container world mapped onto this machine: every service is 127.0.0.1, every listening port a free port
(``--port``, ``--dashboard-address``), a published host port the mapped port of its service, each named volume
a temporary directory (``data``: ``data_dir``). Each service's healthcheck command is run with the same mapping.
The one-shot ``credentials`` service runs first and must exit 0 (compose's ``service_completed_successfully``):
the cluster it sets up is TLS only, and a client without its credentials is refused.
"""

from __future__ import annotations

import re
import secrets
import shlex
import subprocess
import time
from pathlib import Path

import httpx
import pytest
import yaml

from .conftest import EXAMPLES, ROOT
from .processes import Proc, clean_env, free_port, wait_http_ok, wait_until

COMPOSE = ROOT / "docker-compose.yml"
TOKEN = "compose-test-" + secrets.token_hex(8)
#: The small example takes ~15 s alone on this 2-core machine; allow for a loaded one.
JOB_TIMEOUT = 300.0
START_ORDER = ("credentials", "scheduler", "worker1", "worker2", "api")
#: The compose file's TLS credential files (in the volume ``tls``) and the dask CLI flags that name them.
TLS_FLAGS = {"--tls-ca-file": "/tls/ca.pem", "--tls-cert": "/tls/cert.pem", "--tls-key": "/tls/key.pem"}


# ------------------------------------------------------------------------------------------------ compose model
def interpolate(value: str, variables: dict[str, str]) -> str:
    """Compose's variable interpolation: ``$$``, ``$VAR``, ``${VAR}``, ``${VAR:-default}``, ``${VAR-default}``,
    ``${VAR:?message}``, ``${VAR?message}``."""

    def sub(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name = m.group("braced") or m.group("plain")
        op, arg = m.group("op"), m.group("arg") or ""
        value = variables.get(name)
        if op in (":-", ":?"):
            missing = not value
        else:
            missing = value is None
        if op in (":-", "-"):
            return arg if missing else value
        if op in (":?", "?"):
            if missing:
                raise AssertionError(f"compose needs {name}: {arg}")
            return value
        return value or ""

    pattern = r"\$\$|\$\{(?P<braced>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?[-?])(?P<arg>[^}]*))?\}|\$(?P<plain>[A-Za-z_][A-Za-z0-9_]*)"
    return re.sub(pattern, sub, value)


def as_argv(command) -> list[str]:
    return shlex.split(command) if isinstance(command, str) else [str(a) for a in command]


def as_env(environment) -> dict[str, str]:
    if environment is None:
        return {}
    if isinstance(environment, list):
        return dict(item.split("=", 1) if "=" in item else (item, "") for item in environment)
    return {k: "" if v is None else str(v) for k, v in environment.items()}


class LocalCompose:
    """The services of a compose file, mapped onto this machine."""

    def __init__(self, compose: dict, data_dir: Path, variables: dict[str, str]) -> None:
        self.services: dict[str, dict] = compose["services"]
        self.data_dir = data_dir
        self.variables = variables
        #: (service, container port) -> local port, for every port a service listens on.
        self.ports: dict[tuple[str, int], int] = {}
        for name, svc in self.services.items():
            argv = as_argv(svc["command"])
            for flag, value in zip(argv, argv[1:]):
                if flag in ("--port", "--dashboard-address"):
                    self.ports[(name, int(value.rsplit(":", 1)[-1]))] = free_port()
        #: published host port -> (service, container port), from ``ports: ["[IP:]HOST:CONTAINER"]``.
        self.published: dict[int, tuple[str, int]] = {}
        for name, svc in self.services.items():
            for entry in svc.get("ports", []):
                parts = interpolate(str(entry), variables).split(":")
                self.published[int(parts[-2])] = (name, int(parts[-1].split("/")[0]))
        #: volume mount targets -> the local directory (one per named volume; ``data`` is ``data_dir``)
        self.mounts: dict[str, Path] = {}
        for svc in self.services.values():
            for v in svc.get("volumes", []):
                volume, target = str(v).split(":")[:2]
                self.mounts[target] = data_dir if volume == "data" else data_dir.parent / f"volume-{volume}"
        for local in self.mounts.values():
            local.mkdir(exist_ok=True)  # docker creates a named volume before its first container starts

    def local(self, service: str, port: int) -> int:
        return self.ports[(service, port)]

    def _map_paths(self, s: str) -> str:
        for target, local in self.mounts.items():
            if s == target or s.startswith(target + "/"):
                return str(local) + s[len(target):]
        return s

    def volume(self, target: str) -> Path:
        """The local directory of the volume mounted at ``target``."""
        return self.mounts[target]

    def _map_text(self, service: str, s: str, host_view: bool) -> str:
        """Hostnames and ports in ``s``: ``<service>:<port>`` of any service; ``127.0.0.1|localhost|0.0.0.0:<port>``
        (and a bare ``:<port>`` of a listening option) as seen from inside ``service`` or, with ``host_view``,
        from the docker host (its published ports)."""

        def other(m: re.Match) -> str:
            key = (m.group(1), int(m.group(2)))
            return f"127.0.0.1:{self.ports[key]}" if key in self.ports else m.group(0)

        names = "|".join(re.escape(n) for n in self.services)
        s = re.sub(rf"\b({names}):(\d+)\b", other, s)

        def own(m: re.Match) -> str:
            port = int(m.group(2))
            key = self.published.get(port) if host_view else (service, port)
            return f"127.0.0.1:{self.ports[key]}" if key in self.ports else m.group(0)

        return re.sub(r"(127\.0\.0\.1|localhost|0\.0\.0\.0|^):(\d+)\b", own, s)

    def argv(self, service: str) -> list[str]:
        argv = [interpolate(a, self.variables) for a in as_argv(self.services[service]["command"])]
        out = []
        for i, arg in enumerate(argv):
            if i > 0 and argv[i - 1] == "--host":
                arg = "127.0.0.1"  # inside a container 0.0.0.0 is the container; here it would be the machine
            elif i > 0 and argv[i - 1] == "--port":
                arg = str(self.local(service, int(arg)))
            else:
                arg = self._map_paths(self._map_text(service, arg, host_view=False))
            out.append(arg)
        return out

    def env(self, service: str) -> dict[str, str]:
        env = as_env(self.services[service].get("environment"))
        return {k: self._map_paths(self._map_text(service, interpolate(v, self.variables), host_view=True))
                for k, v in env.items()}

    def healthcheck(self, service: str) -> list[str] | None:
        hc = self.services[service].get("healthcheck")
        if not hc or hc.get("disable"):
            return None
        test = hc["test"]
        if isinstance(test, str):
            return ["sh", "-c", self._map_text(service, test, host_view=False)]
        kind, *rest = test
        if kind == "CMD-SHELL":
            return ["sh", "-c", self._map_text(service, rest[0], host_view=False)]
        assert kind == "CMD", test
        return [self._map_text(service, a, host_view=False) for a in rest]


# ------------------------------------------------------------------------------------------------ the file itself
def _flag(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def test_compose_file_shape():
    """One image for all, the shared /data volume, healthchecks, the scheduler CLI that distributed installs, and a
    closed cluster: TLS credentials written at deployment by a one-shot service, every Dask process and the API on
    them."""
    compose = yaml.safe_load(COMPOSE.read_text())
    services = compose["services"]
    assert set(START_ORDER) <= set(services)
    images = {svc.get("image") for svc in services.values()}
    assert len(images) == 1, images
    for name, svc in services.items():
        assert svc.get("build") in (".", {"context": "."}), name
        if name == "credentials":
            continue
        assert any(str(v).split(":")[1] == "/data" for v in svc.get("volumes", [])), f"{name} lacks /data"
        assert svc.get("healthcheck", {}).get("test"), f"{name} lacks a healthcheck"
        # Every long-running service reads the credentials, read-only, and runs only after they were written.
        assert "tls:/tls:ro" in svc.get("volumes", []), f"{name} lacks the credentials volume"
        assert svc["environment"]["DASK_DISTRIBUTED__COMM__REQUIRE_ENCRYPTION"] == "True", name
    # The credentials: a one-shot service writes them into the volume, at deployment, never into the image.
    creds = services["credentials"]
    assert as_argv(creds["command"]) == ["compabs", "credentials", "/tls"]
    assert creds["restart"] == "no" and creds["volumes"] == ["tls:/tls"]
    assert "tls" in compose["volumes"]
    assert services["scheduler"]["depends_on"]["credentials"] == {"condition": "service_completed_successfully"}
    sched = as_argv(services["scheduler"]["command"])
    assert sched[:2] == ["dask", "scheduler"] and _flag(sched, "--protocol") == "tls"
    assert all(_flag(sched, f) == v for f, v in TLS_FLAGS.items()), sched
    assert not any(str(p).endswith(":8786") for p in services["scheduler"].get("ports", [])), "8786 published"
    for w in ("worker1", "worker2"):
        argv = as_argv(services[w]["command"])
        assert argv[:3] == ["dask", "worker", "tls://scheduler:8786"], argv
        assert _flag(argv, "--nworkers") == "1" and _flag(argv, "--nthreads") == "1"
        assert all(_flag(argv, f) == v for f, v in TLS_FLAGS.items()), argv
    api = as_argv(services["api"]["command"])
    assert api[:2] == ["compabs", "serve"] and _flag(api, "--scheduler") == "tls://scheduler:8786"
    assert _flag(api, "--data") == "/data"
    api_env = services["api"]["environment"]
    assert [api_env[k] for k in ("COMPABS_TLS_CA", "COMPABS_TLS_CERT", "COMPABS_TLS_KEY")] == list(TLS_FLAGS.values())
    # The API is not exposed unauthenticated: the file refuses to start without a token.
    with pytest.raises(AssertionError, match="COMPABS_TOKEN"):
        interpolate(services["api"]["environment"]["COMPABS_TOKEN"], {})
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert dockerfile.startswith("#") and "FROM python:3.11-slim" in dockerfile
    assert re.search(r"^USER (?!root)\S+", dockerfile, re.M), "the image must not run as root"
    # No key in the image: nothing copied or generated at build time.
    instructions = [line for line in dockerfile.splitlines() if not line.lstrip().startswith("#")]
    assert not any(".pem" in line or "credentials" in line or "openssl" in line for line in instructions), \
        "the image must not hold TLS credentials"


# ------------------------------------------------------------------------------------------------ running it
@pytest.fixture
def stack(tmp_path):
    compose = yaml.safe_load(COMPOSE.read_text())
    data = tmp_path / "data"
    data.mkdir()
    lc = LocalCompose(compose, data, {"COMPABS_TOKEN": TOKEN})
    procs: dict[str, Proc] = {}

    def start(name: str) -> Proc:
        argv = lc.argv(name)
        procs[name] = Proc(name, argv, clean_env(**lc.env(name)), tmp_path, tmp_path / f"{name}.log")
        return procs[name]

    def healthy(name: str) -> bool:
        argv = lc.healthcheck(name)
        run = subprocess.run(argv, env=clean_env(), cwd=tmp_path, capture_output=True, timeout=30)
        return run.returncode == 0

    lc.start, lc.healthy, lc.procs = start, healthy, procs
    try:
        yield lc
    finally:
        for name in reversed(list(procs)):
            procs[name].stop()


def _security(directory: Path):
    from workers.cluster import Credentials

    return Credentials.in_directory(directory).security()


@pytest.mark.slow
def test_compose_services_run_a_job_on_the_two_workers(stack):
    lc = stack
    t0 = time.monotonic()
    creds = lc.start("credentials")
    assert creds.popen.wait(60) == 0, creds.tail()
    tls_dir = lc.volume("/tls")
    assert sorted(p.name for p in tls_dir.iterdir()) == ["ca.pem", "cert.pem", "key.pem"]
    assert (tls_dir / "key.pem").stat().st_mode & 0o077 == 0, "the key must be private"
    key = (tls_dir / "key.pem").read_bytes()
    again = lc.start("credentials")  # a later `up` keeps the credentials the running cluster has
    assert again.popen.wait(60) == 0 and (tls_dir / "key.pem").read_bytes() == key, again.tail()

    scheduler = lc.start("scheduler")
    wait_until(lambda: lc.healthy("scheduler"), 60, "scheduler healthcheck", [scheduler])
    workers = [lc.start("worker1"), lc.start("worker2")]
    scheduler_address = f"tls://127.0.0.1:{lc.local('scheduler', 8786)}"

    from distributed import Client

    with Client(scheduler_address, timeout=30, security=_security(tls_dir)) as client:
        client.wait_for_workers(2, timeout=120)
        assert len(client.nthreads()) == 2
        assert set(client.nthreads().values()) == {1}
        assert all(a.startswith("tls://") for a in client.nthreads()), client.nthreads()  # workers listen on TLS
    # Without the credentials the scheduler refuses: plain TCP, and TLS with a certificate of its own making.
    from distributed.security import Security

    with pytest.raises(OSError):
        Client(scheduler_address.replace("tls://", "tcp://"), timeout=5)
    with pytest.raises(OSError):
        Client(scheduler_address, timeout=5, security=Security.temporary())
    for name in ("worker1", "worker2"):
        wait_until(lambda name=name: lc.healthy(name), 60, f"{name} healthcheck", [scheduler, *workers])

    api = lc.start("api")
    all_procs = [scheduler, *workers, api]
    url = f"http://127.0.0.1:{lc.local('api', 8000)}"
    wait_http_ok(f"{url}/health", 120, all_procs)
    wait_until(lambda: lc.healthy("api"), 30, "api healthcheck", all_procs)
    print(f"compose services up: {time.monotonic() - t0:.1f} s")
    health = httpx.get(f"{url}/health", timeout=10).json()
    assert health["workers"] == 2 and "scheduler" not in health and "8786" not in str(health), health

    spec = (EXAMPLES / "small.yaml").read_text()
    yaml_type = {"Content-Type": "application/yaml"}
    # The compose file sets COMPABS_TOKEN: without it the API refuses.
    assert httpx.post(f"{url}/jobs", content=spec, headers=yaml_type, timeout=30).status_code == 401
    auth = {"Authorization": f"Bearer {TOKEN}"}
    r = httpx.post(f"{url}/jobs", content=spec, headers={**yaml_type, **auth}, timeout=30)
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]

    t1 = time.monotonic()
    job = {}

    def finished() -> bool:
        job.update(httpx.get(f"{url}/jobs/{job_id}", headers=auth, timeout=10).json())
        return job["status"] in ("succeeded", "failed", "cancelled")

    wait_until(finished, JOB_TIMEOUT, f"job {job_id} to finish", all_procs, interval=1.0)
    print(f"small example on the compose services: {time.monotonic() - t1:.1f} s")
    assert job["status"] == "succeeded", f"{job}\n" + "\n".join(p.tail() for p in all_procs)

    report = httpx.get(f"{url}/jobs/{job_id}/report", headers=auth, timeout=10).json()
    runner = report["runner"]
    # Run on the compose scheduler and its two workers, not on an embedded cluster of the API.
    assert runner["workers"] == 2, runner
    assert runner["embedded"] is False, runner
    assert runner["scheduler"] == scheduler_address, runner
    assert report["audit"]["violations"] == 0
    assert report["abstract_states"] == 33 ** 2
    # The relation store is on the shared volume, which the workers wrote.
    assert str(runner["store"]).startswith(str(lc.data_dir)), runner
    assert list(lc.data_dir.rglob("relations.zarr")), "no relation store under /data"
    # The dashboard link handed to browsers is the published one (DASK_DISTRIBUTED__DASHBOARD__LINK).
    assert job.get("dask_dashboard") == f"http://127.0.0.1:{lc.local('scheduler', 8787)}/status", job
