"""A Dask cluster's TLS credentials: the files, generating them, handing them to child processes, and removing
those a killed process left in the temporary directory (docs/security.md).

Whoever holds the key can run code on the cluster's workers: it is a password. :func:`write_credentials` writes a
fresh CA's certificate and one certificate and key that every member presents; :class:`Credentials` names the three
files and makes Dask's ``Security`` and configuration of them.
"""

from __future__ import annotations

import datetime
import logging
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from workers.errors import ClusterError

logger = logging.getLogger("workers.cluster")

#: Environment variables naming the cluster's TLS credentials (PEM files, as :func:`write_credentials` writes):
#: the CA certificate, and the certificate and private key every scheduler, worker and client presents.
TLS_ENV = {"ca": "COMPABS_TLS_CA", "cert": "COMPABS_TLS_CERT", "key": "COMPABS_TLS_KEY"}
#: The files :func:`write_credentials` writes into its directory.
CREDENTIAL_FILES = {"ca": "ca.pem", "cert": "cert.pem", "key": "key.pem"}


@dataclass(frozen=True)
class Credentials:
    """The TLS credentials of a cluster: PEM files of the CA certificate, and of the certificate and private key
    that the scheduler, the workers and the clients all present (each side requires the other's, signed by the
    CA). Whoever holds ``key`` can run code on the cluster: it is a password."""

    ca: Path
    cert: Path
    key: Path

    @classmethod
    def in_directory(cls, directory: str | os.PathLike[str]) -> Credentials:
        """The files :func:`write_credentials` wrote into ``directory``."""
        d = Path(directory)
        return cls(**{role: d / name for role, name in CREDENTIAL_FILES.items()})

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Credentials | None:
        """The credentials ``COMPABS_TLS_CA``, ``COMPABS_TLS_CERT`` and ``COMPABS_TLS_KEY`` name, or ``None`` when
        none of them is set.

        Raises
        ------
        ClusterError
            Some but not all are set, or a file they name is not readable.
        """
        environ = os.environ if environ is None else environ
        values = {role: environ.get(var) or "" for role, var in TLS_ENV.items()}
        if not any(values.values()):
            return None
        missing = [TLS_ENV[role] for role, v in values.items() if not v]
        if missing:
            raise ClusterError(f"{', '.join(missing)} not set: the cluster's TLS credentials need all of "
                               f"{', '.join(TLS_ENV.values())} (the files `compabs credentials DIR` writes)")
        creds = cls(**{role: Path(v) for role, v in values.items()})
        creds.check()
        return creds

    def check(self) -> None:
        """Raise :class:`ClusterError` unless every file is readable."""
        for role, path in self.files().items():
            try:
                with open(path, "rb"):
                    pass
            except OSError as exc:
                raise ClusterError(f"cannot read the cluster's TLS {role} file {path} ({TLS_ENV[role]}): "
                                   f"{exc.strerror}") from None

    def files(self) -> dict[str, Path]:
        return {"ca": self.ca, "cert": self.cert, "key": self.key}

    def env(self) -> dict[str, str]:
        """The environment variables that hand these credentials to another process (``connect()`` there reads
        them): ``subprocess.Popen(..., env={**os.environ, **conn.credentials.env()})``."""
        return {TLS_ENV[role]: str(path) for role, path in self.files().items()}

    def security(self) -> Any:
        """Dask's ``Security`` for every role (scheduler, worker, client), TLS required."""
        from distributed.security import Security

        ca, cert, key = str(self.ca), str(self.cert), str(self.key)
        return Security(require_encryption=True, tls_ca_file=ca, tls_client_cert=cert, tls_client_key=key,
                        tls_scheduler_cert=cert, tls_scheduler_key=key, tls_worker_cert=cert, tls_worker_key=key)

    def dask_config(self) -> dict[str, Any]:
        """The same as Dask configuration (dotted keys): what a ``Security()`` made without arguments reads."""
        ca, cert, key = str(self.ca), str(self.cert), str(self.key)
        out: dict[str, Any] = {"distributed.comm.require-encryption": True, "distributed.comm.tls.ca-file": ca}
        for role in ("client", "scheduler", "worker"):
            out[f"distributed.comm.tls.{role}.cert"] = cert
            out[f"distributed.comm.tls.{role}.key"] = key
        return out


def write_credentials(directory: str | os.PathLike[str], *, overwrite: bool = False,
                      valid_days: int = 3650) -> Credentials:
    """Generate a cluster's TLS credentials into ``directory`` (created 0700): ``ca.pem``, ``cert.pem``,
    ``key.pem`` (0600).

    A fresh CA (ECDSA P-256) signs one certificate for every member of the cluster, for both TLS server and
    client use; the CA's private key is never written, so no other certificate can be issued: a new cluster gets
    new credentials, and anyone with ``key.pem`` is a member. Needs ``cryptography``.

    Raises
    ------
    ClusterError
        The directory already holds credentials (unless ``overwrite``) or cannot be written.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    creds = Credentials.in_directory(directory)
    d = Path(directory)
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise ClusterError(f"cannot create the credentials directory {d}: {exc.strerror}") from None
    existing = [str(p) for p in creds.files().values() if p.exists()]
    if existing and not overwrite:
        raise ClusterError(f"{d} already holds cluster credentials ({', '.join(existing)}): keep them, or "
                           "replace them (then restart every scheduler, worker and API that uses them)")

    now = datetime.datetime.now(datetime.timezone.utc)
    start, end = now - datetime.timedelta(days=1), now + datetime.timedelta(days=valid_days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"compabs cluster CA {os.urandom(6).hex()}")])
    ca_cert = (
        x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                     crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "compabs-cluster")])
    cert = (
        x509.CertificateBuilder().subject_name(name).issuer_name(ca_name).public_key(key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=True, key_cert_sign=False,
                                     crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                       critical=False)
        .add_extension(x509.SubjectAlternativeName([x509.DNSName("compabs-cluster")]), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    pem = serialization.Encoding.PEM
    contents = {
        "ca": (ca_cert.public_bytes(pem), 0o644),
        "cert": (cert.public_bytes(pem), 0o644),
        "key": (key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()), 0o600),
    }
    try:
        for role, (data, mode) in contents.items():
            target = creds.files()[role]
            partial = target.with_name(target.name + ".partial")
            partial.unlink(missing_ok=True)
            fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)  # the key is never world-readable
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(partial, target)
    except OSError as exc:
        raise ClusterError(f"cannot write the cluster credentials into {d}: {exc.strerror}") from None
    return creds


#: Prefix of the temporary credentials directories: ``compabs-tls-<pid>-<random>`` in the temporary directory.
TLS_TMP_PREFIX = "compabs-tls-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def remove_stale_credentials(tmp: str | os.PathLike[str] | None = None) -> list[Path]:
    """Delete the temporary credentials directories (``compabs-tls-<pid>-*``) of this user whose process is gone:
    a process killed with ``SIGKILL`` (or out of memory) leaves its cluster's private key behind. Called when an
    embedded cluster starts; returns what it removed. A directory of a running process, another user's, or of
    the older form without a pid is left alone."""
    removed: list[Path] = []
    base = Path(tmp if tmp is not None else tempfile.gettempdir())
    try:
        entries = list(base.glob(TLS_TMP_PREFIX + "*"))
    except OSError:
        return removed
    for d in entries:
        pid_text = d.name[len(TLS_TMP_PREFIX):].split("-", 1)[0]
        try:
            st = d.lstat()
        except OSError:
            continue
        if not pid_text.isdigit() or not d.is_dir() or d.is_symlink() or st.st_uid != os.getuid():
            continue
        pid = int(pid_text)
        if pid == os.getpid() or _pid_alive(pid):
            continue
        shutil.rmtree(d, ignore_errors=True)
        if not d.exists():
            logger.info("removed stale cluster credentials %s (their process %d is gone)", d, pid)
            removed.append(d)
    return removed


def _temporary_credentials() -> tuple[Credentials, Path]:
    """Fresh credentials in a new private directory (``mkdtemp``: 0700, this user's only), named after this
    process, so that a later start can tell they are stale once it is gone (:func:`remove_stale_credentials`)."""
    remove_stale_credentials()
    directory = Path(tempfile.mkdtemp(prefix=f"{TLS_TMP_PREFIX}{os.getpid()}-"))
    try:
        return write_credentials(directory), directory
    except BaseException:
        shutil.rmtree(directory, ignore_errors=True)
        raise
