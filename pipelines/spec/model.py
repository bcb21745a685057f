"""The job spec: one pydantic model, loaded from YAML or JSON, with a published JSON Schema.

A spec describes an interconnected system the way the paper does (Section 3): subsystems
``Xi_i = (X_i, U_i, W_i, f_i)`` given as black boxes, an interconnection map ``M`` that can only be sampled,
and a specification over the composed state. Dynamics and maps are safe expressions (:mod:`pipelines.expressions.compiler`)
or, for local runs, a ``module:function`` name.

Numbers that may vary between runs (the network size ``N``) are ``parameters``; they can be used in
expressions and in ``replicate`` counts (``N - 1``), and overridden from the command line (``--set N=16``).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)

from pipelines.errors import SpecError
from pipelines.spec.loader import load_yaml
from pipelines.spec.messages import format_validation_error
from pipelines.spec.reading import read_spec_text
from pipelines.temporal.automaton import MAX_STATES as MAX_AUTOMATON_STATES
from pipelines.temporal.formula import check_ltl_fields

Vector = float | list[float]
#: Longest ``reads`` expression, in characters.
MAX_READ_LENGTH = 200
MODULE_FUNCTION = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*$")


class _Model(BaseModel):
    # strict: a boolean is not a number (`substeps: true` was 1), a string is not a number (`samples: "100"`), a
    # float is not an integer; an integer is still a float. Only tuples (`centers`) also take a JSON/YAML list.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


class GridSpec(_Model):
    """A box ``[lb, ub]`` and its grid spacing ``eta`` (scalars broadcast over dimensions)."""

    lb: Vector = Field(description="lower bounds of the box")
    ub: Vector = Field(description="upper bounds of the box")
    eta: Vector = Field(description="grid spacing (cell width), > 0")
    origin: Vector | None = Field(default=None, description="grid origin, 0 by default (points are origin + k*eta)")

    @model_validator(mode="after")
    def _lengths(self):
        lists = {k: len(v) for k in ("lb", "ub", "eta", "origin") if isinstance(v := getattr(self, k), list)}
        if any(n == 0 for n in lists.values()):
            raise ValueError(f"empty list in {sorted(k for k, n in lists.items() if n == 0)}: give a number, or one per dimension")
        if len(set(lists.values())) > 1:
            raise ValueError(f"lists of different lengths {lists}: give one value per dimension in each")
        return self

    @property
    def dim(self) -> int:
        sizes = {len(v) for v in (self.lb, self.ub, self.eta) if isinstance(v, list)}
        if len(sizes) > 1:
            raise SpecError(f"lb, ub and eta have different lengths {sorted(sizes)}")
        return sizes.pop() if sizes else 1


#: A matrix of Lipschitz constants: one row per state component, one column per coordinate of the argument.
LipschitzMatrixSpec = Annotated[list[list[float]], Field(min_length=1, max_length=64)]


class LipschitzSpec(_Model):
    """Lipschitz constants of a map (Assumptions 1-2), given or estimated: a number in the infinity norm (it also
    bounds every entry), or a matrix ``L[i][j]`` bounding how fast component ``i`` of the successor moves along
    coordinate ``j`` of the argument, the others fixed (docs/method.md §3)."""

    x: float | LipschitzMatrixSpec | Literal["estimate"] = Field(
        description="L_x: a number (infinity norm, every entry), a matrix (row per state component, column per "
        "state coordinate), or 'estimate' (Algorithm 4, in the norm and per entry)"
    )
    w: float | LipschitzMatrixSpec | Literal["estimate"] = Field(
        default=0.0,
        description="L_w: a number, a matrix (row per state component, column per internal input read), or 'estimate'",
    )
    on_violation: Literal["fail", "raise"] = Field(
        default="fail",
        description="when the sampled data contradict a given constant: fail the job, or raise the constant "
        "to what the data show (and say so in the report)",
    )
    safety_factor: float = Field(default=1.1, ge=1.0, description="multiplies estimated constants")
    batches: int = Field(default=40, ge=3, description="J of Algorithm 4")
    pairs: int = Field(default=200, ge=2, description="L of Algorithm 4")
    delta: float | None = Field(default=None, gt=0, description="pair distance of Algorithm 4 (default: eta/10)")

    @field_validator("x", "w")
    @classmethod
    def _nonneg(cls, v):
        if isinstance(v, float) and not (v >= 0 and v < float("inf")):
            raise ValueError("a Lipschitz constant must be finite and >= 0")
        if isinstance(v, list):
            if len({len(row) for row in v}) != 1 or not v[0] or len(v[0]) > 64:
                raise ValueError(f"a matrix of Lipschitz constants has rows of one length, 1 to 64 entries each; "
                                 f"got rows of lengths {[len(row) for row in v]}")
            bad = [(i, j) for i, row in enumerate(v) for j, e in enumerate(row) if not (0 <= e < float("inf"))]
            if bad:
                i, j = bad[0]
                raise ValueError(f"entry [{i}][{j}] = {v[i][j]}: a Lipschitz constant must be finite and >= 0")
        return v


def _check_read_literals(text: str) -> str:
    """A ``reads`` expression computes an index: its numbers are integer literals of at most 9 digits (``1e999``,
    ``nan`` or a 100-digit number is refused here, before anything is built; names are checked with the
    parameters by :func:`pipelines.network.build_network`)."""
    import ast

    from pipelines.expressions.checks import parse_python

    if not text.strip() or len(text.strip()) > MAX_READ_LENGTH:
        return text  # the field's own check says what a reads entry may be
    try:
        tree = parse_python(text.strip())  # one parse at a time (gh-106905)
    except (SyntaxError, SyntaxWarning, DeprecationWarning, ValueError, RecursionError, MemoryError):
        raise ValueError(f"reads entry {text!r} is not an expression") from None
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and not (type(node.value) is int and abs(node.value) < 10**9):
            raise ValueError(f"reads entry {text!r}: {node.value!r} is not an integer of at most 9 digits (an index "
                             "expression uses integers, the copy index i and integer parameters)")
        if isinstance(node, ast.Name) and node.id in ("nan", "inf"):
            raise ValueError(f"reads entry {text!r}: {node.id} is not an index")
    return text


#: A ``reads`` entry given as an expression (checked per entry, so an error names ``reads.K``).
ReadExpression = Annotated[str, AfterValidator(_check_read_literals)]


class SubsystemSpec(_Model):
    """One subsystem ``Xi_i``, or ``replicate`` identical copies of it.

    Its dynamics are a discrete-time map (``dynamics``: ``x+ = f(x, u, w)``) or a continuous-time one (``ode``:
    ``dx/dt = f(x, u, w)``, sampled every ``sampling_time`` by ``substeps`` fixed steps of Runge-Kutta 4 with
    ``u`` and ``w`` held over the period, :mod:`pipelines.integrators`).
    """

    name: str = Field(min_length=1, max_length=64)
    replicate: int | Annotated[str, Field(min_length=1, max_length=MAX_READ_LENGTH)] = Field(
        default=1, description="number of copies: an integer, or an expression over the parameters (\"N - 1\")")
    state: GridSpec
    input: GridSpec
    reads: list[int | ReadExpression] = Field(
        default_factory=list,
        description="the internal variables w_j it reads, in order: indices, or integer expressions in the copy "
        "index i and the parameters (\"(i + 1) % N\"), evaluated per copy",
    )
    dynamics: str | None = Field(
        default=None, min_length=1, description="x+ = f(x, u, w): safe expression in x, u, w (vectors) or module:function"
    )
    ode: str | None = Field(
        default=None, min_length=1,
        description="dx/dt = f(x, u, w), instead of dynamics: safe expression or module:function; needs sampling_time",
    )
    sampling_time: float | None = Field(default=None, gt=0, description="tau of an ode: the sampled map is x(tau)")
    substeps: int = Field(default=5, ge=1, le=1000, description="Runge-Kutta 4 steps per sampling period (ode)")
    lipschitz: LipschitzSpec
    samples: int = Field(default=100, ge=1, le=100_000, description="N_C, samples per cell (x and w jointly)")
    growth_bound: Literal["lipschitz", "scp", "hull"] = "scp"
    scp_objective: Literal["paper", "radius"] = Field(
        default="paper", description="'paper' minimises 1'theta (Eq. 4.5); 'radius' the radius actually used"
    )

    @field_validator("reads")
    @classmethod
    def _reads(cls, v):
        for j in v:
            if isinstance(j, str) and not 0 < len(j.strip()) <= MAX_READ_LENGTH:
                raise ValueError(f"a reads entry is an index or an expression of 1 to {MAX_READ_LENGTH} characters, "
                                 f"got {j!r}")
        return v

    @model_validator(mode="after")
    def _time(self):
        if (self.dynamics is None) == (self.ode is None):
            raise ValueError("give either 'dynamics' (a discrete-time map x+ = f(x, u, w)) or 'ode' (dx/dt = f(x, u, w) "
                             "with sampling_time), " + ("not both" if self.ode is not None else "none is given"))
        if self.ode is not None and self.sampling_time is None:
            raise ValueError("an 'ode' needs 'sampling_time' (tau > 0, the period of the sampled map x(tau))")
        if self.dynamics is not None:
            given = [k for k in ("sampling_time", "substeps") if k in self.model_fields_set]
            if given:
                verb = "belong" if len(given) > 1 else "belongs"
                raise ValueError(f"{' and '.join(repr(k) for k in given)} {verb} to an 'ode'; 'dynamics' is already a "
                                 "discrete-time map")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # The ode fields are left out of a discrete-time subsystem's dump (and dynamics out of an ode's), so that
        # spec_hash and the subsystem keys of specs written before ode existed do not change.
        data = handler(self)
        drop = ("ode", "sampling_time", "substeps") if self.ode is None else ("dynamics",)
        return {k: v for k, v in data.items() if k not in drop}

    @property
    def source(self) -> str:
        """The text of ``dynamics`` or of ``ode``, whichever is given."""
        text = self.dynamics if self.ode is None else self.ode
        assert text is not None  # one of them is (checked above)
        return text

    @property
    def rhs_evaluations(self) -> int:
        """Evaluations of the user's function per sampled step: 1 for a map, ``4 x substeps`` for an ODE (one per
        Runge-Kutta 4 stage, :mod:`pipelines.integrators`); what the cost models multiply samples by."""
        return 1 if self.ode is None else 4 * self.substeps


class InterconnectionSpec(_Model):
    """The interconnection ``M`` (Section 4.2): sampled, learned by lasso, decomposed, certified."""

    map: str = Field(min_length=1, description="safe expression in x (all states, concatenated) or module:function")
    internal: GridSpec | list[GridSpec] = Field(description="grid of each internal variable w_j (one for all or a list)")
    samples: int = Field(default=100, ge=2, le=1_000_000, description="N_I, input-output samples for the lasso")
    alpha: float | Literal["cv"] = Field(default="cv", description="lasso penalty, or 'cv' for cross-validation")
    sigma: int = Field(default=4, ge=1, le=8, description="largest in-degree after MDec (Algorithm 2)")
    error: Literal["linear", "certify", "direct", "max", "min"] = Field(
        default="certify",
        description="linear: the map is declared linear; certify: Lipschitz margin on the support grid; "
        "direct: abstract each output straight from the black box on its support; max / min: each output is "
        "declared the largest / smallest of the coordinates it reads (checked on samples, abstracted exactly)",
    )
    lipschitz: float | None = Field(default=None, ge=0, description="L_M in the infinity norm (certify, direct)")
    intermediate_eta: float | None = Field(default=None, gt=0, description="spacing of intermediate variables z")
    samples_per_cell: int = Field(default=16, ge=1, le=10_000, description="direct mode: samples per support cell")
    holdout: int = Field(default=1000, ge=10, le=1_000_000, description="held-out samples for error bounds")

    @field_validator("alpha")
    @classmethod
    def _alpha(cls, v):
        if isinstance(v, float) and not v > 0:
            raise ValueError("alpha must be > 0 (or 'cv')")
        return v


class BoxRegion(_Model):
    lb: Vector
    ub: Vector


class ConsensusRegion(_Model):
    """``OR_{phi in centers} AND_i |x_i - phi| <= radius`` (the paper's consensus region, Sec. 5.2)."""

    centers: tuple[float, float, float] = Field(
        strict=False, description="(first, last, step) of the common values phi",
    )
    radius: float = Field(gt=0)


class Region(_Model):
    """A union of boxes over the composed state, approximated from inside by whole cells."""

    boxes: list[BoxRegion] = Field(default_factory=list, description="boxes over the composed state (scalars broadcast)")
    consensus: ConsensusRegion | None = None


class SpecificationSpec(_Model):
    """What the controller must achieve on the composed state (Algorithm 5; docs/method.md §6).

    ``safe`` is required for ``safe`` and optional for the other kinds, where it restricts every run to ``S``
    until (``reach``, ``reach_avoid``) or forever (``reach_and_stay``): "reach T while staying in S", "reach and
    stay in T while staying in S". A region the kind does not use is refused rather than ignored.

    ``ltl``: an LTLf formula over named regions (docs/spec.md, "Temporal-logic tasks"; its grammar is
    :mod:`pipelines.temporal.formula`'s), in place of ``target``, ``safe`` and ``avoid``.
    """

    kind: Literal["safe", "reach", "reach_avoid", "reach_and_stay", "ltl"]
    target: Region | None = Field(default=None, description="T for reach, reach_avoid; phi for reach_and_stay")
    safe: Region | None = Field(
        default=None, description="S: required for safe; optional for the other kinds, whose runs must then never "
        "leave S (reach: T is reached inside S; reach_and_stay: the run stays in S and ends in phi within S)",
    )
    avoid: Region | None = Field(default=None, description="A for reach_avoid (a union of boxes: the obstacles)")
    formula: str | None = Field(default=None, min_length=1, description="ltl: an LTLf formula over the names of "
                                "'regions' (F a & G !o; !, &, |, ->, <->, X, F, G, U), checked by compabs validate")
    regions: dict[str, Region] | None = Field(default=None, description="ltl: the formula's atoms, each a named "
                                              "region (a lower-case name; boxes and consensus as for target)")

    @model_validator(mode="after")
    def _regions(self):
        if self.kind == "ltl":  # no target, safe or avoid: they are written in the formula
            check_ltl_fields([k for k in ("target", "safe", "avoid") if getattr(self, k) is not None], self.formula,
                             self.regions)
            return self
        given = [k for k in ("formula", "regions") if getattr(self, k) is not None]
        if given:
            raise ValueError(f"{' and '.join(repr(k) for k in given)} belong to kind 'ltl'; a '{self.kind}' "
                             "specification takes 'target', 'safe' and 'avoid'")
        need = {"safe": "safe", "reach": "target", "reach_avoid": "target", "reach_and_stay": "target"}[self.kind]
        if getattr(self, need) is None:
            raise ValueError(f"a '{self.kind}' specification needs '{need}'")
        if self.kind == "reach_avoid" and self.avoid is None:
            raise ValueError("a 'reach_avoid' specification needs 'avoid'")
        # A region given but unused would be silently ignored: the user meant something else.
        if self.kind != "reach_avoid" and self.avoid is not None:
            raise ValueError(f"a '{self.kind}' specification has no 'avoid' set: 'avoid' belongs to kind "
                             "'reach_avoid' (or shrink 'safe' to leave it out)")
        if self.kind == "safe" and self.target is not None:
            raise ValueError("a 'safe' specification has no 'target': use kind 'reach' or 'reach_and_stay' with "
                             "'target' and 'safe' to reach a target while staying safe")
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # formula and regions are left out of the other kinds' dump, so that their spec_hash does not change.
        data = handler(self)
        drop = ("target", "safe", "avoid") if self.kind == "ltl" else ("formula", "regions")
        return {k: v for k, v in data.items() if k not in drop}


FixedPoint = Literal["cobuchi", "reach_safe", "contracts"]


def _both_fixed_points() -> list[FixedPoint]:
    return ["cobuchi", "reach_safe"]


class OptionsSpec(_Model):
    seed: int = Field(default=0, ge=0)
    audit_transitions: int = Field(default=1_000_000, ge=0, le=100_000_000)
    chunk_cells: int | None = Field(default=None, ge=1, description="cells per task (default: chosen from the work)")
    max_cells: int = Field(
        default=50_000_000, ge=1,
        description="the job's own cap on (x, u, w) triples per subsystem; a server's (or the command line's) "
        "max_cells applies too, and the smaller is named (pipelines.spec.costs)",
    )
    synthesis: bool = Field(default=True, description="synthesize a controller after the abstraction")
    controller: FixedPoint = Field(
        default="cobuchi", description="reach_and_stay: which fixed point's controller is saved as 'controller'"
    )
    fixed_points: list[FixedPoint] = Field(
        default_factory=_both_fixed_points, min_length=1,
        description="reach_and_stay: which fixed points to compute (co-Büchi can cost 20x Reach(Safe)); 'contracts' "
        "(networks whose target and safe set are products of per-subsystem sets; reach_and_stay and safe): one "
        "small game per subsystem, chained by assume-guarantee contracts (pipelines/synthesis/contracts.py), for "
        "networks whose exact game is too large; a sound controller whose domain, a product of per-subsystem "
        "sets, may be smaller than the maximal one",
    )
    initial_states: list[list[float]] = Field(
        default_factory=list, max_length=100, description="concrete initial states for closed-loop runs and figures"
    )
    closed_loop_runs: int = Field(default=100, ge=0, le=100_000, description="runs from random domain states")
    closed_loop_steps: int | None = Field(default=None, ge=1, le=100_000, description="steps per run (default: auto)")
    task_timeout: float | None = Field(
        default=600.0, gt=0, le=1e7,
        description="seconds one cluster task (a chunk of cells) may run before the job fails as hung; null: no "
        "limit. Not part of the spec's hash: changing it keeps the stored chunks (resume)",
    )
    time_limit: float | None = Field(
        default=None, gt=0, le=1e7,
        description="seconds of wall time the job may run under `compabs serve` before it is stopped and marked "
        "failed (null: the server's default_time_limit; at most its max_time_limit). Not part of the spec's hash",
    )
    memory_limit: int | None = Field(
        default=None, ge=64, le=1 << 24,
        description="MiB of memory the job's processes may use together under `compabs serve` before it is stopped "
        "and marked failed (null: the server's default_memory_limit; at most its max_memory_limit). Not part of "
        "the spec's hash",
    )
    synthesis_processes: int | Literal["auto"] = Field(
        default="auto",
        description="processes for the synthesis fixed points, this one included (the state space is split among "
        "them; results are identical): 'auto' = the CPUs this process may use, at most 4; 1 = one process; helper "
        "processes on this machine are at most one per core (a larger number is lowered to it). Not part of the "
        "spec's hash",
    )
    synthesis_on: Literal["auto", "cluster", "processes"] = Field(
        default="auto",
        description="where the parts of the synthesis fixed points run: 'cluster' = the job's Dask workers (a job "
        "run in process has none), 'processes' = helper processes on this machine, 'auto' = the cluster when the "
        "job has one. With the cluster, synthesis_processes 'auto' is one part per worker thread and an int the "
        "number of parts. Results are identical. Not part of the spec's hash",
    )
    synthesis_engine: Literal["auto", "cudd", "oxidd"] = Field(
        default="auto",
        description="the BDD engine of the synthesis's predecessor steps: 'oxidd' = in the job's process on one thread "
        "per core (synthesis_on must be 'auto'), 'cudd' = CUDD, split as synthesis_on says, 'auto' = oxidd where "
        "installed unless synthesis_on is set. Results are identical. Not part of the spec's hash",
    )
    synthesis_parallel_after: float = Field(
        default=1.0, ge=0, le=1e6,
        description="seconds one fixed-point step must take in one process before the parts start (starting them "
        "costs about a second; small games never need them); 0: from the first step on. Not part of the spec's hash",
    )
    synthesis_backend: Literal["auto", "explicit", "bdd"] = Field(
        default="auto",
        description="how the game is solved: 'explicit' = on the relation's boxes in memory (single systems without "
        "internal inputs: pipelines/synthesis/explicit.py; controllers as arrays), 'bdd' = BDDs (any network), "
        "'auto' = explicit where it applies and fits in half the available memory. Both give the same domain. Not "
        "part of the spec's hash",
    )

    synthesis_quotient: int = Field(
        default=0, ge=0, le=16,
        description="k > 0: solve the fixed points on the quotient that merges 2^k neighbouring cells per state "
        "coordinate (pipelines/synthesis/quotient.py): a sound controller in far less time and memory, whose domain "
        "may be smaller than the abstraction's maximal one (the report's synthesis.quotient and domain_bound say "
        "so); 0 = the exact fixed points. Not part of the spec's hash: the abstraction is the same",
    )
    synthesis_refine: int = Field(
        default=0, ge=0, le=100,
        description="with synthesis_quotient > 0: rounds of growing the quotient's safety invariant on the fine "
        "abstraction (safe and Reach(Safe)); each round a fine safety fixed point near the invariant, sound, "
        "slower than the quotient (the tanks at 1.25: 15 minutes, +79 %). Not part of the spec's hash",
    )

    max_automaton_states: int = Field(default=MAX_AUTOMATON_STATES, ge=1, le=MAX_AUTOMATON_STATES, description=(
        "ltl: the most states the formula's automaton may have (a larger one is refused, naming this cap); the "
        "product game has that many copies of the abstraction. Not part of the spec's hash"))

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # Left out at its default, so that the dump and spec_hash of specs written before 'ltl' do not change.
        data = handler(self)
        if data.get("max_automaton_states") == MAX_AUTOMATON_STATES:
            del data["max_automaton_states"]
        return data

    @field_validator("synthesis_processes")
    @classmethod
    def _processes(cls, v):
        if v != "auto" and not 1 <= v <= 64:
            raise ValueError(f"options.synthesis_processes must be 'auto' or 1 to 64, got {v}")
        return v

    @model_validator(mode="after")
    def _refine_needs_a_quotient(self):
        if self.synthesis_refine and not self.synthesis_quotient:
            raise ValueError(f"options.synthesis_refine is {self.synthesis_refine}, but it grows the invariant of a "
                             "quotient: set options.synthesis_quotient > 0 as well")
        return self

    @model_validator(mode="after")
    def _controller_is_computed(self):
        if self.controller not in self.fixed_points:
            raise ValueError(f"options.controller is '{self.controller}', which options.fixed_points {self.fixed_points} "
                             "does not compute")
        return self


class JobSpec(_Model):
    """A compabs job: an interconnected system, its interconnection (none for a single system), a specification
    and options."""

    name: str = Field(default="job", min_length=1, max_length=128)
    description: str = ""
    parameters: dict[str, float] = Field(default_factory=dict, description="named numbers (N, tau, ...)")
    subsystems: list[SubsystemSpec] = Field(min_length=1)
    interconnection: InterconnectionSpec | None = Field(
        default=None, description="omit for a single system, or subsystems that read no internal variable"
    )
    specification: SpecificationSpec
    options: OptionsSpec = OptionsSpec()

    @field_validator("parameters")
    @classmethod
    def _param_names(cls, v):
        import keyword

        from pipelines.expressions import FUNCTIONS

        reserved = {"x", "u", "w", "pi", "e"} | set(FUNCTIONS)
        for name in v:
            if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name) or name.startswith("__") or keyword.iskeyword(name):
                raise ValueError(f"parameter name {name!r} is not an identifier")
            if name in reserved:
                raise ValueError(f"parameter name {name!r} is reserved in expressions (variables x, u, w; "
                                 "constants pi, e; function names)")
        return v

    @model_validator(mode="after")
    def _reads_need_interconnection(self):
        if self.interconnection is None:
            reading = [f"subsystems[{k}] ('{s.name}')" for k, s in enumerate(self.subsystems) if s.reads]
            if reading:
                raise ValueError(f"{', '.join(reading)} read internal variables, which only an 'interconnection' "
                                 "defines: add one, or remove their 'reads'")
        if "i" in self.parameters and any(isinstance(j, str) for s in self.subsystems for j in s.reads):
            raise ValueError("parameter 'i' would hide the copy index i of the 'reads' expressions: rename it")
        return self


def json_schema() -> dict[str, Any]:
    """The JSON Schema of a job spec."""
    return JobSpec.model_json_schema()


def parse_spec(data: dict[str, Any] | str, overrides: dict[str, float] | None = None) -> JobSpec:
    """Validate a spec given as a dict, or as YAML/JSON text.

    Parameters
    ----------
    overrides
        Parameter values that replace those of the spec (``--set N=16``).

    Raises
    ------
    SpecError
        Naming every offending field.
    """
    if isinstance(data, str):
        try:
            data = load_yaml(data)  # anchors bounded, integers bounded (pipelines.spec.loader)
        except yaml.YAMLError as exc:
            raise SpecError(f"spec is neither valid YAML nor JSON: {exc}") from None
    if not isinstance(data, dict):
        raise SpecError(f"a spec is a mapping of fields, got {type(data).__name__}")
    if overrides:
        params = dict(data.get("parameters") or {})
        if not isinstance(params, dict):
            raise SpecError("parameters: must be a mapping of names to numbers")
        params.update(overrides)
        data = {**data, "parameters": params}
    try:
        return JobSpec.model_validate(data)
    except ValidationError as err:
        raise SpecError(format_validation_error(err)) from None


def _known(names: Sequence[str]) -> str:
    return f"its parameters: {', '.join(sorted(names))}" if names else "it has no parameters"


def check_overrides(spec: JobSpec, overrides: Mapping[str, float]) -> None:
    """Refuse a ``--set NAME=VALUE`` for a parameter the spec does not define, or a value that is not finite.

    Raises
    ------
    SpecError
        Naming the unknown parameters and the spec's own.
    """
    unknown = sorted(set(overrides) - set(spec.parameters))
    if unknown:
        which = ", ".join(repr(n) for n in unknown)
        raise SpecError(f"--set {which}: the spec '{spec.name}' has no such parameter ({_known(list(spec.parameters))})")
    for name, value in overrides.items():
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise SpecError(f"--set {name}: {value!r} is not a finite number")


def load_spec(path: str | Path, overrides: dict[str, float] | None = None) -> JobSpec:
    """Read and validate a YAML or JSON spec file (:func:`read_spec_text`).

    Parameters
    ----------
    overrides
        Parameter values that replace the spec's (``--set N=16``); each must name a parameter the spec defines.

    Raises
    ------
    SpecError
        The file cannot be read or is not text, the spec is invalid (naming the field), or an override names a
        parameter the spec does not have (naming those it has).
    """
    text = read_spec_text(path)
    try:
        spec = parse_spec(text)
        if overrides:
            check_overrides(spec, overrides)
            spec = parse_spec(text, overrides)
    except (ValueError, OverflowError, RecursionError) as exc:  # a parser's own limit, not a field: still the spec's
        raise SpecError(f"cannot parse spec {path}: {type(exc).__name__}: {exc}") from None
    return spec


def spec_hash(spec: JobSpec) -> str:
    """A stable hash of everything that determines the abstraction (used to refuse stale stores)."""
    import hashlib

    # Timing (a job that timed out must resume) and synthesis-only options: the stored abstraction is reused.
    timing_only = {"options": {"task_timeout", "time_limit", "memory_limit", "synthesis_processes", "synthesis_on",
                               "synthesis_engine", "synthesis_parallel_after", "synthesis_quotient",
                               "synthesis_refine", "synthesis_backend", "max_automaton_states"}}
    canonical = json.dumps(spec.model_dump(mode="json", exclude=timing_only), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def is_module_function(text: str) -> bool:
    """Whether a dynamics/map field names a Python ``module:function`` instead of an expression."""
    return bool(MODULE_FUNCTION.match(text.strip()))

