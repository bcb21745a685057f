"""Settings of the REST service, from ``COMPABS_*`` environment variables or given to ``create_app``.

Every field ``name`` is read from the environment variable ``COMPABS_<NAME>`` (``COMPABS_TOKEN``,
``COMPABS_DATA_DIR``, ``COMPABS_MAX_CELLS``, ...); lists (``allowed_modules``) are comma-separated, booleans
are ``1/0``, ``true/false``, ``yes/no``. ``compabs serve`` options override the environment.

Caps (each refusal names the cap and its value, so a user knows what to change or whom to ask; the refusals are
:mod:`service.errors`, and ``service.app.ERROR_STATUS`` gives their HTTP status):

``max_body_bytes`` (1 MiB)
    Request bodies larger than this are refused before anything is parsed. The largest paper case spec is ~3 kB.
``max_cells`` (10,000,000)
    ``(x, u, w)`` cell triples per subsystem: state cells x input points x internal cells, the size of one
    subsystem's relation (``Subsystem.triples``). The per-cell stage evaluates the black box ``samples`` times per
    triple, so 10^7 triples at 100 samples is 10^9 evaluations, minutes on two workers, and a relation of
    ~100 MB; the paper's cases need at most ~6,000 triples per subsystem. ``CapExceeded`` when exceeded.
``max_subsystems`` (256)
    Subsystems after ``replicate`` is expanded (checked before anything is built, so ``replicate: 1e9`` costs
    nothing). ``CapExceeded``.
``max_expression_length`` (2,000 characters)
    Each ``dynamics`` and the interconnection ``map``. ``CapExceeded``.
``max_concurrent_jobs`` (16)
    Queued plus running jobs; a submission beyond it is refused with ``QueueFull``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

#: Prefix of the environment variables.
ENV_PREFIX = "COMPABS_"


class Settings(BaseModel):
    """Configuration of one API process (and its embedded Dask cluster)."""

    model_config = ConfigDict(extra="forbid")

    token: str | None = Field(
        default=None, repr=False,
        description="bearer token every route but /health requires (Authorization: Bearer <token>, or ?token=); "
        "None: no authentication (bind to 127.0.0.1 only)",
    )
    data_dir: Path = Field(default=Path("compabs-data"), description="jobs' directories are DATA/jobs/<id>/")
    db_url: str | None = Field(default=None, description="SQLAlchemy URL of the job store (default sqlite:///DATA/jobs.sqlite)")
    scheduler: str | None = Field(default=None, description="tcp://HOST:PORT of a Dask scheduler; None: an embedded LocalCluster")
    workers: int = Field(default=2, ge=1, le=256, description="worker processes of the embedded cluster")
    in_process: bool = Field(default=False, description="no Dask: run the per-cell stage in the API process (tests, tiny jobs)")
    allowed_modules: list[str] = Field(
        default_factory=list, description="modules a module:function black box may come from (default: none)"
    )
    max_body_bytes: int = Field(default=1 << 20, ge=1, description="largest request body, bytes")
    max_cells: int = Field(default=10_000_000, ge=1, description="largest (x, u, w) cell triples per subsystem")
    max_subsystems: int = Field(default=256, ge=1, description="largest number of subsystems after replicate")
    max_expression_length: int = Field(default=2000, ge=1, description="longest dynamics or map expression, characters")
    max_concurrent_jobs: int = Field(default=16, ge=1, description="queued + running jobs beyond which POST /jobs is refused")
    max_running: int = Field(
        default=1, ge=1, le=64,
        description="jobs running at once (each on the shared cluster; synthesis of each runs in this process)",
    )
    max_resumes: int = Field(
        default=3, ge=0,
        description="times a job interrupted by an API stop is resumed before it is marked failed",
    )
    host: str = Field(default="127.0.0.1", description="address to bind; 127.0.0.1 unless told otherwise")
    port: int = Field(default=8000, ge=0, le=65535)

    @field_validator("allowed_modules", mode="before")
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

    @property
    def database_url(self) -> str:
        """The job store's SQLAlchemy URL: ``db_url``, else an SQLite file in ``data_dir``."""
        if self.db_url:
            return self.db_url
        return f"sqlite:///{(self.data_dir / 'jobs.sqlite').resolve()}"

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

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
                name = str(e["loc"][0]) if e["loc"] else "?"
                source = f"{ENV_PREFIX}{name.upper()}" if name in values and name not in overrides else name
                shown = "" if name == "token" else f" (got {e.get('input')!r})"  # never echo a secret
                problems.append(f"{source}: {e['msg']}{shown}")
            raise ValueError("invalid service settings: " + "; ".join(problems)) from None
