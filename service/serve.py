"""``compabs serve``: the REST API and dashboard in one uvicorn process.

One process only (never ``uvicorn --workers N``): each process would start its own Dask cluster and its own job
processes over the same job store. Each job runs in a process tree of its own (:mod:`service.supervisor`); its
tasks run on the embedded two-worker ``LocalCluster`` unless ``--scheduler`` (or ``COMPABS_SCHEDULER``) names one. The token is read from an environment variable
(``COMPABS_TOKEN``, or the one ``--token-env`` names), never from the command line, where ``ps`` shows it.

``compabs credentials DIR`` (:func:`add_credentials_parser`) writes a cluster's TLS credentials for a deployment: the
compose file's init service, or an operator before starting ``dask scheduler`` and ``dask worker`` with them
(docs/security.md).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import TYPE_CHECKING

from pipelines.errors import SpecError

if TYPE_CHECKING:  # every `compabs` command builds this parser: keep pydantic out of its start-up
    from types import FrameType

    from service.settings import Settings

#: Seconds uvicorn waits for open connections (event streams never end by themselves) before stopping.
GRACEFUL_SECONDS = 3


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    """Add the ``serve`` subcommand to ``compabs``'s parser."""
    s = sub.add_parser("serve", help="run the REST API and dashboard (one process, embedded Dask cluster)")
    s.add_argument("--host", default=None, help="address to bind (default 127.0.0.1, or COMPABS_HOST)")
    s.add_argument("--port", type=int, default=None, help="port (default 8000, or COMPABS_PORT)")
    s.add_argument("--data", default=None, help="data directory: jobs.sqlite and jobs/<id>/ (or COMPABS_DATA_DIR)")
    s.add_argument("--db-url", default=None, help="SQLAlchemy URL of the job store (default sqlite:///DATA/jobs.sqlite)")
    s.add_argument("--scheduler", default=None,
                   help="tls://HOST:PORT of a Dask scheduler (or COMPABS_SCHEDULER); its credentials from "
                        "COMPABS_TLS_CA, COMPABS_TLS_CERT, COMPABS_TLS_KEY")
    s.add_argument("--workers", type=int, default=None, help="worker processes of the embedded cluster (default 2)")
    s.add_argument("--in-process", action="store_true", default=None, help="no Dask: run jobs in the API process")
    s.add_argument("--token-env", default="COMPABS_TOKEN", metavar="VAR",
                   help="environment variable holding the API token (default COMPABS_TOKEN; unset: no token)")
    s.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    s.set_defaults(func=cmd_serve)
    return s


def add_credentials_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> argparse.ArgumentParser:
    """Add the ``credentials`` subcommand (the TLS credentials of a deployment's Dask cluster)."""
    c = sub.add_parser("credentials", help="write new TLS credentials for a Dask cluster (ca.pem, cert.pem, key.pem)",
                       description="Write new TLS credentials for a Dask cluster into DIR (0700; key.pem 0600): the "
                                   "scheduler, the workers and the API all use the same three files. Existing "
                                   "credentials are kept unless --replace. See docs/security.md.")
    c.add_argument("dir", help="directory to write ca.pem, cert.pem and key.pem into")
    c.add_argument("--replace", action="store_true",
                   help="replace existing credentials (restart every process of the cluster afterwards)")
    c.add_argument("--days", type=int, default=3650, help="validity of the certificates in days (default 3650)")
    c.set_defaults(func=cmd_credentials)
    return c


def cmd_credentials(args: argparse.Namespace) -> int:
    from workers.cluster import Credentials, write_credentials

    if args.days < 1:
        raise SpecError(f"--days must be >= 1, got {args.days}")
    existing = Credentials.in_directory(args.dir)
    if not args.replace and all(p.exists() for p in existing.files().values()):
        print(f"{args.dir}: cluster credentials exist; kept (--replace writes new ones)")
        return 0
    creds = write_credentials(args.dir, overwrite=True, valid_days=args.days)
    print(f"{args.dir}: new cluster credentials: {creds.ca.name}, {creds.cert.name}, {creds.key.name} "
          "(key.pem lets its holder run code on the cluster: keep it private)")
    return 0


def settings_from_args(args: argparse.Namespace, environ: dict[str, str] | None = None) -> Settings:
    """Settings from the environment, overridden by the command line.

    Raises
    ------
    SpecError
        An invalid setting, naming the variable or option.
    """
    from service.settings import Settings

    environ = dict(os.environ if environ is None else environ)
    if args.token_env != "COMPABS_TOKEN" and args.token_env not in environ:
        raise SpecError(f"--token-env {args.token_env}: that environment variable is not set; export the token in it")
    token = environ.get(args.token_env) or None
    try:
        return Settings.from_env(
            environ, token=token, host=args.host, port=args.port, data_dir=args.data, db_url=args.db_url,
            scheduler=args.scheduler, workers=args.workers, in_process=args.in_process,
        )
    except ValueError as exc:
        raise SpecError(str(exc)) from None


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from service.app import create_app

    settings = settings_from_args(args)
    if settings.token is None and settings.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: serving on {settings.host} without a token: anyone who can reach it can submit jobs; "
              f"set {args.token_env}", file=sys.stderr)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    app = create_app(settings)

    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            # Stop running jobs at once, not after the graceful wait: the signal may also have reached the Dask
            # workers (a process group, `docker stop`), and a job failing for that must be re-queued, not failed.
            manager = getattr(app.state, "manager", None)
            if manager is not None:
                manager.begin_shutdown()
            super().handle_exit(sig, frame)

    # The app object, not an import string: uvicorn then cannot fork workers or reload (one cluster, one queue).
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=args.log_level,
                            timeout_graceful_shutdown=GRACEFUL_SECONDS)
    Server(config).run()
    return 0
