"""Settings of the REST service, from ``COMPABS_*`` environment variables or given to ``create_app``.

Every field ``name`` is read from the environment variable ``COMPABS_<NAME>`` (``COMPABS_TOKEN``,
``COMPABS_DATA_DIR``, ``COMPABS_MAX_CELLS``, ...); lists (``allowed_modules``) are comma-separated, booleans
are ``1/0``, ``true/false``, ``yes/no``. ``compabs serve`` options override the environment.

Caps (each refusal names the cap and its value, so a user knows what to change or whom to ask; the refusals are
:mod:`service.errors`, and ``service.app.ERROR_STATUS`` gives their HTTP status):

``max_body_bytes`` (1 MiB)
    Request bodies larger than this are refused before anything is parsed. The largest paper case spec is ~3 kB.
``max_concurrent_jobs`` (16)
    Queued plus running jobs; a submission beyond it is refused with ``QueueFull``.
``max_running`` (2)
    Jobs running at once, each in its own process tree (:mod:`service.supervisor`).
``default_time_limit`` (1 h), ``max_time_limit`` (4 h), ``stop_grace`` (3 s)
    A job's wall-time limit is ``options.time_limit``, else ``default_time_limit``; a spec asking for more than
    ``max_time_limit`` is refused (422). A job past its limit, or cancelled, gets ``SIGTERM`` and, ``stop_grace``
    seconds later, ``SIGKILL`` (its whole process group), and is marked failed (cancelled) with the reason.
``default_memory_limit`` (4096 MiB), ``max_memory_limit`` (16384 MiB)
    A job's memory limit is ``options.memory_limit``, else ``default_memory_limit``; a spec asking for more than
    ``max_memory_limit`` is refused (422). The limit holds for the job's whole process tree (the job process and
    every process it starts), measured as the sum of their proportional set sizes (shared pages split among the
    processes sharing them); a job over it is killed at once (``SIGKILL``: it would only grow in a grace period)
    and marked failed with the limit and the use measured (:mod:`service.supervisor`).
``token``, ``tokens``
    ``token`` is the operator's; ``tokens`` (``COMPABS_TOKENS``, comma-separated) are further tokens, one per user,
    each accepted like ``token``. Each user's token sees, reads, follows, downloads and cancels only the jobs it
    submitted: ``GET /jobs`` lists only those, and another user's job answers 404 exactly like an unknown id, so
    ids tell nothing about other users' jobs. The operator's ``token`` sees and may cancel every job (jobs stored
    before tokens were set belong to no user: only the operator sees them); without any token (127.0.0.1 only)
    every request sees every job. The queue is fair between tokens: the next job to start is taken round-robin
    over the tokens with queued jobs, oldest first within a token (:func:`service.manager.fair_order`).

``max_streams`` (64), ``max_streams_per_client`` (8), ``stream_idle_timeout`` (120 s)
    Open ``GET /jobs/{id}/events`` streams in all and per client address (a 429 beyond, :mod:`service.streams`);
    a stream with no event for ``stream_idle_timeout`` seconds is closed (``EventSource`` reconnects by itself).

The cost model's caps (:class:`pipelines.spec.costs.Caps`; what each counts: that module and docs/spec.md "Costs
and caps"), checked by :func:`service.manager.validate_spec` before a job is queued, each refusal a
``CapExceeded`` (422) naming the knob (the spec's field), its value and the cap:

``max_cells`` (10,000,000)
    ``(x, u, w)`` cell triples per subsystem: state cells x input points x internal cells, the size of one
    subsystem's relation (``Subsystem.triples``); the paper's cases need at most ~6,000.
``max_subsystems`` (256)
    Subsystems after ``replicate`` is expanded (checked before anything is built, so ``replicate: 1e9`` costs
    nothing).
``max_expression_length`` (2,000 characters)
    Each ``dynamics`` and the interconnection ``map``.
``max_evaluations`` (10^11)
    Black-box evaluations of the per-cell stage (triples x ``samples`` over the distinct subsystems, an ODE's
    sample counting ``4 x substeps``): a few
    minutes on two workers for a cheap expression (``examples/stress.yaml``: 1.6e10, ~40 s).
``max_tasks`` (10,000)
    Tasks of the per-cell stage (``options.chunk_cells``, or the default chunk), all submitted to the cluster at
    once (50,001 tasks take the API process from 0.3 to 1.25 GB).
``max_lipschitz_pairs`` (2,000,000)
    Pairs of one estimated Lipschitz constant (``batches x pairs x input points``, an ODE's pair counting
    ``4 x substeps``), drawn at once in this process (~90 bytes a pair for a scalar system: ~180 MB).
``max_sample_values`` (20,000,000) and ``max_interconnection_values`` (10^9)
    The interconnection stage's largest array of sampled states (160 MB) and its total work, in state values.
``max_audit_evaluations`` (10^8)
    Black-box evaluations of the audit (``options.audit_transitions`` per part, plus the composed ones; an ODE
    subsystem's transition counts ``4 x substeps``): a minute or two.
``max_closed_loop_steps`` (10,000,000)
    Subsystem steps of the closed loop (``(closed_loop_runs + initial_states) x closed_loop_steps x
    subsystems``, an ODE subsystem's step counting ``4 x substeps``): ~3 minutes, and the trajectories' ~200 MB.

``compabs run`` and ``compabs validate`` check the same model with ``Caps.local()`` (larger: hours of work at
most); :func:`local_caps` is that with each ``COMPABS_MAX_*`` variable that is set taking precedence.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pipelines.errors import SpecError
from pipelines.spec.costs import CAP_NAMES, Caps

#: Prefix of the environment variables.
ENV_PREFIX = "COMPABS_"
#: The cost model's default caps (the service's).
_CAPS = Caps()


class Settings(BaseModel):
    """Configuration of one API process (and its embedded Dask cluster)."""

    model_config = ConfigDict(extra="forbid")

    token: str | None = Field(
        default=None, repr=False,
        description="the operator's bearer token, which every route but /health requires (Authorization: Bearer "
        "<token>, or ?token=) and which sees every job; None: no authentication (bind to 127.0.0.1 only)",
    )
    tokens: list[str] = Field(
        default_factory=list, repr=False,
        description="further bearer tokens, one per user, each accepted like token (which must be set too) and "
        "each seeing only its own jobs; the queue is fair between tokens",
    )
    data_dir: Path = Field(default=Path("compabs-data"), description="jobs' directories are DATA/jobs/<id>/")
    db_url: str | None = Field(default=None, description="SQLAlchemy URL of the job store (default sqlite:///DATA/jobs.sqlite)")
    scheduler: str | None = Field(default=None, description="tls://HOST:PORT of a Dask scheduler (credentials from COMPABS_TLS_*); None: an embedded LocalCluster")
    workers: int = Field(default=2, ge=1, le=256, description="worker processes of the embedded cluster")
    in_process: bool = Field(default=False, description="no Dask: run the per-cell stage in the API process (tests, tiny jobs)")
    allowed_modules: list[str] = Field(
        default_factory=list, description="modules a module:function black box may come from (default: none)"
    )
    max_body_bytes: int = Field(default=1 << 20, ge=1, description="largest request body, bytes")
    max_cells: int = Field(default=_CAPS.max_cells, ge=1, description="largest (x, u, w) cell triples per subsystem")
    max_subsystems: int = Field(default=_CAPS.max_subsystems, ge=1, description="largest number of subsystems after replicate")
    max_expression_length: int = Field(
        default=_CAPS.max_expression_length, ge=1, description="longest dynamics or map expression, characters"
    )
    max_evaluations: int = Field(
        default=_CAPS.max_evaluations, ge=1, description="largest black-box evaluations of a job's per-cell stage"
    )
    max_tasks: int = Field(default=_CAPS.max_tasks, ge=1, description="largest number of per-cell tasks of a job")
    max_lipschitz_pairs: int = Field(
        default=_CAPS.max_lipschitz_pairs, ge=1,
        description="largest batches x pairs x input points of one estimated Lipschitz constant",
    )
    max_sample_values: int = Field(
        default=_CAPS.max_sample_values, ge=1,
        description="largest interconnection.samples (or holdout) x composed state dimension",
    )
    max_interconnection_values: int = Field(
        default=_CAPS.max_interconnection_values, ge=1,
        description="largest state values the interconnection stage evaluates or fits",
    )
    max_audit_evaluations: int = Field(
        default=_CAPS.max_audit_evaluations, ge=1, description="largest black-box evaluations of a job's audit"
    )
    max_closed_loop_steps: int = Field(
        default=_CAPS.max_closed_loop_steps, ge=1,
        description="largest (closed_loop_runs + initial states) x closed_loop_steps x subsystems",
    )
    max_concurrent_jobs: int = Field(default=16, ge=1, description="queued + running jobs beyond which POST /jobs is refused")
    max_running: int = Field(
        default=2, ge=1, le=64,
        description="jobs running at once, each in its own process tree (their cluster tasks share the workers)",
    )
    default_time_limit: float = Field(
        default=3600.0, gt=0, le=1e7,
        description="wall-time limit of a job that sets no options.time_limit, seconds; a job past its limit is "
        "stopped and marked failed",
    )
    max_time_limit: float = Field(
        default=4 * 3600.0, gt=0, le=1e7,
        description="largest options.time_limit a job may ask for, seconds (a larger one is refused with a 422)",
    )
    default_memory_limit: int = Field(
        default=4096, ge=64, le=1 << 24,
        description="memory limit of a job that sets no options.memory_limit, MiB, over its whole process tree; a "
        "job over its limit is killed and marked failed",
    )
    max_memory_limit: int = Field(
        default=16384, ge=64, le=1 << 24,
        description="largest options.memory_limit a job may ask for, MiB (a larger one is refused with a 422)",
    )
    stop_grace: float = Field(
        default=3.0, gt=0, le=600,
        description="seconds a stopped job's processes get to end on SIGTERM before they are killed (SIGKILL)",
    )
    max_resumes: int = Field(
        default=3, ge=0,
        description="times a job interrupted by an API stop is resumed before it is marked failed",
    )
    max_streams: int = Field(default=64, ge=1, description="open GET /jobs/{id}/events streams in all (429 beyond)")
    max_streams_per_client: int = Field(
        default=8, ge=1, description="open event streams per client address (429 beyond)",
    )
    stream_idle_timeout: float = Field(
        default=120.0, gt=0, le=86400,
        description="seconds an event stream stays open without an event (EventSource reconnects by itself)",
    )
    host: str = Field(default="127.0.0.1", description="address to bind; 127.0.0.1 unless told otherwise")
    port: int = Field(default=8000, ge=0, le=65535)

    @field_validator("allowed_modules", "tokens", mode="before")
    @classmethod
    def _split(cls, v: Any) -> Any:
        if isinstance(v, str):
            return [m.strip() for m in v.split(",") if m.strip()]
        return v

    @field_validator("token", "scheduler", "db_url", mode="before")
    @classmethod
    def _empty_is_none(cls, v: Any) -> Any:
        # An exported-but-empty variable (COMPABS_TOKEN=) must not mean "the token is the empty string".
        return None if isinstance(v, str) and not v.strip() else v

    @model_validator(mode="after")
    def _tokens_need_token(self) -> Settings:
        if self.tokens and self.token is None:
            # Without it, a server with only user tokens would look unauthenticated to serve's bind check.
            raise ValueError("tokens are set but token is not: set token (COMPABS_TOKEN) too, the operator's")
        if any(not t for t in self.tokens):
            raise ValueError("tokens: an empty token would accept an empty credential")
        return self

    @property
    def accepted_tokens(self) -> list[str]:
        """Every bearer token this server accepts (none: no authentication)."""
        return [t for t in (self.token, *self.tokens) if t is not None]

    @property
    def database_url(self) -> str:
        """The job store's SQLAlchemy URL: ``db_url``, else an SQLite file in ``data_dir``."""
        if self.db_url:
            return self.db_url
        return f"sqlite:///{(self.data_dir / 'jobs.sqlite').resolve()}"

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

    def caps(self) -> Caps:
        """The cost model's caps of this server."""
        return Caps(**{name: getattr(self, name) for name in CAP_NAMES})

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, **overrides: Any) -> Settings:
        """Settings from ``COMPABS_*`` variables, then ``overrides`` (those that are not ``None``).

        Raises
        ------
        ValueError
            Naming the environment variable (or option) whose value is invalid.
        """
        environ = os.environ if environ is None else environ
        values: dict[str, Any] = {}
        for name in cls.model_fields:
            key = ENV_PREFIX + name.upper()
            if key in environ:
                values[name] = environ[key]
        values.update({k: v for k, v in overrides.items() if v is not None})
        try:
            return cls.model_validate(values)
        except ValidationError as err:
            problems = []
            for e in err.errors():
                name = str(e["loc"][0]) if e["loc"] else "settings"
                source = f"{ENV_PREFIX}{name.upper()}" if name in values and name not in overrides else name
                # Never echo a secret: not a token, nor the whole input a check of several fields is given.
                shown = "" if name in ("token", "tokens", "settings") else f" (got {e.get('input')!r})"
                problems.append(f"{source}: {e['msg']}{shown}")
            raise ValueError("invalid service settings: " + "; ".join(problems)) from None


def token_owner(token: str | None) -> str:
    """Who submitted a job, as the job store keeps it: a hash of the token (the token itself is never stored);
    ``""`` on a server without tokens."""
    if token is None:
        return ""
    return hashlib.sha256(b"compabs-owner\0" + token.encode()).hexdigest()[:16]


def local_caps(environ: Mapping[str, str] | None = None) -> Caps:
    """The command line's caps: :meth:`Caps.local`, each overridden by its ``COMPABS_MAX_*`` variable if set.

    Raises
    ------
    SpecError
        Naming the variable whose value is not a positive integer.
    """
    environ = os.environ if environ is None else environ
    values: dict[str, int] = {}
    for name in CAP_NAMES:
        key = ENV_PREFIX + name.upper()
        text = environ.get(key, "").strip()
        if not text:
            continue
        try:
            value = int(text) if len(text) <= 30 else 0
        except ValueError:
            value = 0
        if value < 1:
            raise SpecError(f"{key}: must be a positive integer, got {text[:40]!r}")
        values[name] = value
    return Caps.local(env_hint=True, **values)
