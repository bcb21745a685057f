"""The cluster is closed: a process without its TLS credentials cannot run anything on it (issue 23, defect 1).

Whoever can talk to a Dask scheduler, worker or nanny can run code on the workers (``Client(address).run(...)``).
The embedded cluster of :func:`workers.cluster.connect` runs on TLS with client certificates generated for it, so
here a separate process (an attacker on the same machine, who knows the address) tries to run code on it with a
plain client, over ``tcp://``, and with certificates of its own, and fails within a bounded time with nothing run;
with the cluster's credentials (handed over as ``COMPABS_TLS_*``) it succeeds. Every listening address of the
cluster (scheduler, workers, nannies) refuses a TLS handshake without the cluster's certificate before it sends a
single byte of Dask's protocol. External schedulers: ``tcp://`` is refused unless explicitly accepted, ``tls://``
needs credentials. ``/health`` no longer tells where the cluster is.
"""

from __future__ import annotations

import os
import socket
import ssl
import subprocess
import sys
from pathlib import Path

import pytest

from workers.cluster import (
    INSECURE_ENV,
    SCHEDULER_ENV,
    TLS_ENV,
    Credentials,
    connect,
    credentials_env,
    write_credentials,
)
from workers.errors import ClusterError

from .conftest import ROOT

#: Seconds an attacker's client may try before giving up; the subprocess must end well within ATTACK_TIMEOUT.
CLIENT_TIMEOUT = 10
ATTACK_TIMEOUT = 120

#: An attacker: connect to the address (argv[1]) as argv[3] says and have the workers create the file argv[2].
ATTACK = r"""
import os, sys
from distributed import Client
from distributed.security import Security

address, marker, mode = sys.argv[1:4]
kwargs = {}
if mode == "wrong":  # a CA and certificate like the cluster's, but not the cluster's
    d = sys.argv[4]
    kwargs["security"] = Security(require_encryption=True, tls_ca_file=f"{d}/ca.pem", tls_client_cert=f"{d}/cert.pem",
                                  tls_client_key=f"{d}/key.pem")
elif mode == "temporary":  # Dask's own throw-away self-signed certificate
    kwargs["security"] = Security.temporary()
elif mode == "credentials":  # the cluster's credentials, from the environment, as compabs hands them on
    from workers.cluster import connect

    conn = connect(address)
    client = conn.client
try:
    if mode != "credentials":
        client = Client(address, timeout=CLIENT_TIMEOUT, **kwargs)
    client.run(lambda: open(marker, "w").write(str(os.getuid())))
    print("RAN", client.submit(sum, [1, 2]).result(timeout=30))
except Exception as exc:
    print("REFUSED", type(exc).__name__, str(exc)[:300])
    sys.exit(3)
""".replace("CLIENT_TIMEOUT", str(CLIENT_TIMEOUT))


def _clean_env(**extra: str) -> dict[str, str]:
    """This environment without compabs's or Dask's settings (no credentials inherited)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("COMPABS_", "DASK_"))}
    env.update(extra)
    return env


def _attack(address: str, marker: Path, mode: str, *extra: str, env: dict[str, str] | None = None):
    return subprocess.run([sys.executable, "-c", ATTACK, address, str(marker), mode, *extra], cwd=ROOT,
                          env=env or _clean_env(), capture_output=True, text=True, timeout=ATTACK_TIMEOUT)


@pytest.fixture(scope="module")
def embedded():
    conn = connect(workers=1)
    try:
        yield conn
    finally:
        conn.close()


def _addresses(conn) -> dict[str, str]:
    """Every address the cluster listens on for Dask's protocol."""
    info = conn.client.scheduler_info(n_workers=-1)
    out = {"scheduler": conn.info["scheduler"]}
    for i, (addr, w) in enumerate(sorted(info["workers"].items())):
        out[f"worker {i}"] = addr
        if w.get("nanny"):
            out[f"nanny {i}"] = w["nanny"]
    return out


# ------------------------------------------------------------------------------------------------ the embedded cluster
def test_embedded_cluster_is_tls_only(embedded):
    client, info = embedded
    assert info["embedded"] and info["scheduler"].startswith("tls://127.0.0.1:")
    addresses = _addresses(embedded)
    assert len(addresses) == 3 and all(a.startswith("tls://127.0.0.1:") for a in addresses.values()), addresses
    assert client.security.require_encryption and client.cluster.security.require_encryption
    creds = embedded.credentials
    assert creds is not None and str(creds.ca) == client.security.tls_ca_file
    # Generated for this cluster into a private directory; the key readable by this user only.
    assert (creds.key.parent.stat().st_mode & 0o777) == 0o700
    assert (creds.key.stat().st_mode & 0o077) == 0
    assert credentials_env(client) == creds.env()


@pytest.mark.parametrize("mode", ["plain", "tcp", "wrong", "temporary"])
def test_a_process_without_the_credentials_runs_nothing(embedded, tmp_path, mode):
    address = embedded.info["scheduler"]
    marker = tmp_path / "pwned"
    extra = []
    if mode == "tcp":
        address = address.replace("tls://", "tcp://")
    if mode == "wrong":
        extra = [str(write_credentials(tmp_path / "other").ca.parent)]
    # The cluster's own addresses in the environment mean nothing without the files.
    run = _attack(address, marker, "plain" if mode == "tcp" else mode, *extra,
                  env=_clean_env(**{SCHEDULER_ENV: embedded.info["scheduler"]}))
    assert run.returncode == 3 and "REFUSED" in run.stdout, (run.stdout, run.stderr[-3000:])
    assert "RAN" not in run.stdout
    assert not marker.exists(), "a process without the credentials ran code on the workers"
    # The cluster is untouched.
    assert embedded.client.submit(sum, [2, 3]).result(timeout=60) == 5


def test_a_process_with_the_credentials_runs(embedded, tmp_path):
    marker = tmp_path / "ran"
    run = _attack(embedded.info["scheduler"], marker, "credentials", env=_clean_env(**embedded.credentials.env()))
    assert run.returncode == 0 and "RAN 3" in run.stdout, (run.stdout, run.stderr[-3000:])
    assert marker.read_text() == str(os.getuid())


def _handshake(address: str, ctx: ssl.SSLContext | None) -> bytes:
    """Connect to ``address`` (TLS with ``ctx``, or plain TCP) and read what the server sends first: Dask's
    handshake once a connection is accepted; nothing (``b""``) when it refuses one."""
    host, port = address.split("://", 1)[1].rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=CLIENT_TIMEOUT) as raw:
        if ctx is None:
            raw.sendall(b"\x00" * 64)  # a Dask frame header over plain TCP
            try:
                return raw.recv(1024)
            except (ConnectionError, TimeoutError):
                return b""
        try:
            with ctx.wrap_socket(raw) as tls:
                tls.settimeout(CLIENT_TIMEOUT)
                return tls.recv(1024)
        except (ssl.SSLError, ConnectionError, TimeoutError):
            return b""


def _client_context(creds: Credentials | None) -> ssl.SSLContext:
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE  # the attacker does not care who the server is
    if creds is not None:
        ctx.load_cert_chain(creds.cert, creds.key)
    return ctx


def test_every_listener_refuses_a_handshake_without_the_cluster_certificate(embedded, tmp_path):
    """Scheduler, workers and nannies alike (a worker also runs code it is sent): plain TCP, TLS without a client
    certificate, TLS with another CA's certificate: the connection is closed before any of Dask's protocol."""
    other = write_credentials(tmp_path / "other")
    for name, address in _addresses(embedded).items():
        for label, ctx in (("plain tcp", None), ("no certificate", _client_context(None)),
                           ("another CA's certificate", _client_context(other))):
            assert _handshake(address, ctx) == b"", f"{name} {address} accepted {label}"
        # The control: with the cluster's certificate, Dask's handshake comes.
        assert _handshake(address, _client_context(embedded.credentials)) != b"", f"{name} {address}"


def test_generated_credentials_are_removed_on_close(tmp_path):
    conn = connect(workers=1)
    directory = conn.credentials.key.parent
    try:
        assert directory.is_dir() and directory != tmp_path
    finally:
        conn.close()
    assert not directory.exists()


# ------------------------------------------------------------------------------------------------ external schedulers
def test_a_tcp_scheduler_is_refused_unless_accepted(monkeypatch):
    from workers import cluster as cluster_mod

    monkeypatch.delenv(INSECURE_ENV, raising=False)
    for address in ("tcp://127.0.0.1:9", "127.0.0.1:9"):
        with pytest.raises(ClusterError, match=rf"refusing the Dask scheduler at {address}.*{INSECURE_ENV}=1"):
            connect(address)
    monkeypatch.setenv(SCHEDULER_ENV, "tcp://127.0.0.1:9")
    with pytest.raises(ClusterError, match="refusing"):
        connect()
    # The operator's explicit opt-in: then it is only a scheduler that is not there.
    monkeypatch.setattr(cluster_mod, "CONNECT_TIMEOUT", 1.0)
    monkeypatch.setenv(INSECURE_ENV, "1")
    with pytest.raises(ClusterError, match="cannot reach the Dask scheduler at tcp://127.0.0.1:9"):
        connect("tcp://127.0.0.1:9")


def test_a_tls_scheduler_needs_credentials(monkeypatch, tmp_path):
    from workers import cluster as cluster_mod

    for var in TLS_ENV.values():
        monkeypatch.delenv(var, raising=False)
    with pytest.raises(ClusterError, match="needs TLS credentials: set COMPABS_TLS_CA"):
        connect("tls://127.0.0.1:9")
    monkeypatch.setenv(TLS_ENV["ca"], str(tmp_path / "ca.pem"))
    with pytest.raises(ClusterError, match="COMPABS_TLS_CERT, COMPABS_TLS_KEY not set"):
        connect("tls://127.0.0.1:9")
    for role, var in TLS_ENV.items():
        monkeypatch.setenv(var, str(tmp_path / f"{role}.pem"))
    with pytest.raises(ClusterError, match="cannot read the cluster's TLS ca file"):
        connect("tls://127.0.0.1:9")
    creds = write_credentials(tmp_path / "tls")
    for var, value in creds.env().items():
        monkeypatch.setenv(var, value)
    monkeypatch.setattr(cluster_mod, "CONNECT_TIMEOUT", 1.0)
    with pytest.raises(ClusterError, match="cannot reach the Dask scheduler at tls://127.0.0.1:9"):
        connect("tls://127.0.0.1:9")


# ------------------------------------------------------------------------------------------------ the credentials
def test_write_credentials(tmp_path):
    d = tmp_path / "tls"
    creds = write_credentials(d)
    assert sorted(p.name for p in d.iterdir()) == ["ca.pem", "cert.pem", "key.pem"]
    assert d.stat().st_mode & 0o777 == 0o700 and creds.key.stat().st_mode & 0o777 == 0o600
    assert b"PRIVATE KEY" in creds.key.read_bytes() and b"PRIVATE KEY" not in creds.ca.read_bytes()
    # The certificate chains to the CA, for a server and for a client (both ends of every Dask connection).
    for purpose in (ssl.Purpose.SERVER_AUTH, ssl.Purpose.CLIENT_AUTH):
        ctx = ssl.create_default_context(purpose, cafile=str(creds.ca))
        ctx.load_cert_chain(creds.cert, creds.key)
    # Never overwritten by accident; fresh ones on request are new keys.
    key = creds.key.read_bytes()
    with pytest.raises(ClusterError, match="already holds cluster credentials"):
        write_credentials(d)
    assert creds.key.read_bytes() == key
    assert write_credentials(d, overwrite=True).key.read_bytes() != key
    assert not list(d.glob("*.partial"))


def test_compabs_credentials_command(tmp_path, capsys):
    from service.cli import main

    d = tmp_path / "tls"
    assert main(["credentials", str(d)]) == 0
    key = (d / "key.pem").read_bytes()
    assert main(["credentials", str(d)]) == 0 and (d / "key.pem").read_bytes() == key  # kept
    assert "kept" in capsys.readouterr().out
    assert main(["credentials", str(d), "--replace"]) == 0 and (d / "key.pem").read_bytes() != key


# ------------------------------------------------------------------------------------------------ /health
def test_health_does_not_locate_the_cluster(tmp_path):
    """With a real embedded cluster behind it, ``/health`` (no token) says how many workers, not where."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.models import Health
    from service.settings import Settings

    assert set(Health.model_fields) == {"status", "workers", "jobs_running", "jobs_queued"}
    app = create_app(Settings(data_dir=tmp_path / "data", workers=1, token="t0ken"))
    with TestClient(app) as http:
        body = http.get("/health").json()
        cluster = app.state.manager.cluster
    assert body == {"status": "ok", "workers": 1, "jobs_running": 0, "jobs_queued": 0}
    scheduler_port = cluster["scheduler"].rsplit(":", 1)[1]
    text = str(body)
    assert "tls://" not in text and "127.0.0.1" not in text and scheduler_port not in text
