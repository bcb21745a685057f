"""The interconnected system of a spec, resolved: grids, black boxes, who reads which internal variable.

``build_network`` turns a validated :class:`~pipelines.spec.model.JobSpec` into a :class:`Network` of
:class:`Subsystem` objects (``replicate`` expanded), the internal-variable grids and the interconnection
map ``M``. Everything a later stage needs comes from here, so there is one place where the spec is read.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from pipelines.blackbox import BlackBox, NoInternalVariables
from pipelines.errors import SpecError
from pipelines.grid import UniformGrid
from pipelines.integrators import SampledFlow
from pipelines.spec.model import MAX_READ_LENGTH, GridSpec, JobSpec, SubsystemSpec


@dataclass(frozen=True)
class Subsystem:
    """One subsystem ``Xi_i = (X_i, U_i, W_i, f_i)`` of the network.

    ``internal_grid`` is the product of the grids of the internal variables it reads (``None`` when it reads
    none). ``key`` identifies its abstraction: subsystems with equal keys share one (they are identical).
    """

    name: str
    index: int
    spec: SubsystemSpec
    state_grid: UniformGrid
    input_grid: UniformGrid
    internal_grid: UniformGrid | None
    reads: tuple[int, ...]
    dynamics: BlackBox
    state_offset: int
    key: str

    @property
    def n(self) -> int:
        return self.state_grid.dim

    @property
    def m(self) -> int:
        return self.input_grid.dim

    @property
    def p(self) -> int:
        return 0 if self.internal_grid is None else self.internal_grid.dim

    @property
    def n_w_cells(self) -> int:
        return 1 if self.internal_grid is None else self.internal_grid.size

    @property
    def triples(self) -> int:
        """Number of ``(x̂, û, ŵ)`` triples the abstraction ranges over."""
        return self.state_grid.size * self.input_grid.size * self.n_w_cells


@dataclass(frozen=True)
class Network:
    spec: JobSpec
    subsystems: tuple[Subsystem, ...]
    internal_grids: tuple[UniformGrid, ...]
    interconnection_map: BlackBox
    constants: dict[str, float] = field(default_factory=dict)

    @property
    def state_dim(self) -> int:
        return sum(s.n for s in self.subsystems)

    @property
    def abstract_states(self) -> int:
        """Number of abstract states of the composed system (exact)."""
        return math.prod(s.state_grid.size for s in self.subsystems)

    @property
    def state_grids(self) -> list[UniformGrid]:
        return [s.state_grid for s in self.subsystems]

    def composed_state_grid(self) -> UniformGrid:
        """The product of the subsystems' state grids as one grid (for region approximation)."""
        return UniformGrid.product(self.state_grids)

    def unique_subsystems(self) -> dict[str, list[Subsystem]]:
        """Subsystems grouped by identity: each group is abstracted once."""
        groups: dict[str, list[Subsystem]] = {}
        for s in self.subsystems:
            groups.setdefault(s.key, []).append(s)
        return groups


#: Largest ``replicate`` count (bounds what a spec can make this process allocate before any other check).
MAX_REPLICAS = 100_000


#: The most dimensions a box of numbers is broadcast over (beyond, lists say what is meant).
MAX_BROADCAST = 64


def _grid(g: GridSpec, name: str, kind: str, dim: int | None = None) -> UniformGrid:
    """The grid of a box; a box of numbers is broadcast over ``dim`` dimensions when given."""
    make = UniformGrid.covering if kind == "cover" else UniformGrid.inside

    def wide(v):
        return v if dim is None or v is None or isinstance(v, list) else [v] * dim

    return make(wide(g.lb), wide(g.ub), wide(g.eta), wide(g.origin), name=name)


def _listed_dim(g: GridSpec) -> int | None:
    """The length of the box's lists (equal: :class:`GridSpec`), ``None`` for a box of numbers."""
    lengths = [len(v) for v in (g.lb, g.ub, g.eta, g.origin) if isinstance(v, list)]
    return lengths[0] if lengths else None


def box_dims(s: SubsystemSpec, si: int, params: dict[str, float]) -> tuple[int, int]:
    """The dimensions of the state and input boxes of ``s`` (docs/spec.md, "Boxes and dimensions").

    A box with lists has their length. A box of numbers is broadcast over the dimension the dynamics use: for the
    state, the larger of the highest ``x[k]`` read plus one and the entries of a list ``[f1, ..., fn]``; for the
    input, the highest ``u[k]`` read plus one; 1 for a ``module:function`` (whose text says nothing).

    Raises
    ------
    SpecError
        A broadcast state whose dynamics give another number of components than the dimension they read, or
        more than :data:`MAX_BROADCAST` dimensions: naming the field and asking for a box per dimension.
    """
    from pipelines.errors import ExpressionError
    from pipelines.expressions import compile_expression
    from pipelines.expressions.dimensions import components_read, output_entries
    from pipelines.spec.model import is_module_function

    field = "ode" if s.ode is not None else "dynamics"
    where = f"subsystems[{si}] ('{s.name}')"
    text = s.source
    read = not is_module_function(text)
    n = _listed_dim(s.state) or (max(1, components_read(text, "x"), output_entries(text)) if read else 1)
    m = _listed_dim(s.input) or (max(1, components_read(text, "u")) if read else 1)
    for box, dim, var in (("state", n, "x"), ("input", m, "u")):
        if _listed_dim(getattr(s, box)) is None and dim > MAX_BROADCAST:
            raise SpecError(f"{where}.{box}: lb, ub and eta are numbers and {field} reads {var}[{dim - 1}]; a box of "
                            f"numbers is broadcast over at most {MAX_BROADCAST} dimensions: write a box per "
                            "dimension (lists for lb, ub and eta)")
    wanted = components_read(text, "w") if read else 0
    if wanted > len(s.reads):
        given = f"{len(s.reads)} ({', '.join(f'w[{k}]' for k in range(len(s.reads)))})" if s.reads else "none"
        raise SpecError(f"{where}.reads: {field} reads w[{wanted - 1}], but reads names {given} of the internal "
                        "variables: list one entry in reads for each w[k] the dynamics use")
    if _listed_dim(s.state) is None and n > 1 and read:
        try:
            out = compile_expression(text, {"x": n, "u": m, "w": max(len(s.reads), 1)}, params).output_dim()
        except ExpressionError:
            out = n  # the compiler's own message, when the network builds the black box
        if out != n:
            why = f"it reads x[{n - 1}]" if components_read(text, "x") == n else f"a list of {n} entries"
            raise SpecError(f"{where}.state: lb, ub and eta are numbers, so the box is broadcast over the {n} "
                            f"dimensions {field} uses ({why}), but {field} gives {out} component"
                            f"{'s' if out > 1 else ''}, not one per state dimension: write a box per dimension "
                            f"(lists for lb, ub and eta) or fix {field}")
    return n, m


def replicate_count(s: SubsystemSpec, params: dict[str, float]) -> float:
    """The number of copies ``replicate`` asks for, unchecked: a number, or an expression over the parameters
    (``N``, ``N - 1``) evaluated by the whitelisted compiler (:meth:`CompiledExpression.constant`).

    Raises
    ------
    SpecError
        The expression names an undefined parameter or is not a safe constant expression.
    """
    from pipelines.errors import ExpressionError
    from pipelines.expressions import compile_expression

    r = s.replicate
    if not isinstance(r, str):
        return r
    text = r.strip()
    if text.isidentifier() and text not in params:
        raise SpecError(f"subsystem '{s.name}': replicate names parameter '{text}', which is not defined")
    try:
        return compile_expression(text, {}, params, max_length=MAX_READ_LENGTH).constant()
    except ExpressionError as exc:
        raise SpecError(f"subsystem '{s.name}': replicate {text!r}: {exc}") from None


def _replicas(s: SubsystemSpec, params: dict[str, float]) -> int:
    r = replicate_count(s, params)
    given = "" if not isinstance(s.replicate, str) or s.replicate.strip() in params else f" ({s.replicate.strip()!r})"
    if isinstance(r, bool) or not math.isfinite(r) or r != int(r) or int(r) < 1:
        raise SpecError(f"subsystem '{s.name}': replicate{given} must be a positive integer, got {r:g}")
    if r > MAX_REPLICAS:
        raise SpecError(f"subsystem '{s.name}': replicate{given} = {r:g} copies; at most {MAX_REPLICAS} are supported")
    return int(r)


def _copy_reads(s: SubsystemSpec, si: int, copies: int, params: dict[str, float], p: int) -> list[tuple[int, ...]]:
    """The internal variables each copy of ``s`` reads: ``reads`` entries are indices, or integer expressions in
    the copy index ``i`` and the parameters, evaluated for all copies at once.

    Raises
    ------
    SpecError
        An expression that does not compile, is not an integer, or gives an index outside ``0..p-1`` (naming
        the copy); a copy reading a variable twice.
    """
    from pipelines.errors import ExpressionError
    from pipelines.expressions import compile_expression

    i = np.arange(copies, dtype=float)[None]  # (1, copies): the variable i of dimension 1
    columns = []
    for k, j in enumerate(s.reads):
        where = f"subsystems[{si}] ('{s.name}').reads[{k}]"
        if isinstance(j, int):
            values = np.full(copies, float(j))
        else:
            try:
                expr = compile_expression(j, {"i": 1}, params, max_length=MAX_READ_LENGTH)
                if expr.output_dim() != 1:
                    raise SpecError(f"{where}: {j!r} has {expr.output_dim()} components; an index is one number")
                with np.errstate(all="ignore"):  # a non-finite index is refused below, naming the copy
                    values = np.broadcast_to(np.asarray(expr(i=i), dtype=float), (1, copies))[0]
            except ExpressionError as exc:
                raise SpecError(f"{where}: {exc}") from None
        bad = ~(np.isfinite(values) & (values == np.round(values)) & (values >= 0) & (values < p))
        if bad.any():
            r = int(np.argmax(bad))
            copy = "" if s.replicate == 1 else f" for copy i = {r} ('{s.name}[{r}]')"
            what = f"internal variable {j}" if isinstance(j, int) else f"{j!r} gives {values[r]:g}{copy}; internal variable"
            raise SpecError(f"{where}: {what} does not exist ("
                            + (f"the map has {p} outputs, 0 to {p - 1})" if p else "the network has none)"))
        columns.append(values.astype(np.int64))
    table = np.stack(columns, axis=1) if columns else np.zeros((copies, 0), dtype=np.int64)
    ordered = np.sort(table, axis=1)
    repeated = (ordered[:, 1:] == ordered[:, :-1]).any(axis=1)
    if repeated.any():
        r = int(np.argmax(repeated))
        copy = "" if s.replicate == 1 else f" of copy i = {r} ('{s.name}[{r}]')"
        raise SpecError(f"subsystems[{si}] ('{s.name}').reads: repeated internal variable in {table[r].tolist()}"
                        f"{copy}")
    return [tuple(int(v) for v in row) for row in table.tolist()]


def _dynamics(s: SubsystemSpec, name: str, dims: dict[str, int], params: dict[str, float],
              allowed_modules: Sequence[str] | None) -> BlackBox:
    """The subsystem's map ``x+ = f(x, u, w)``: the given one, or the sampled map of its ``ode``."""
    if s.ode is None:
        assert s.dynamics is not None
        return BlackBox(f"subsystem '{name}' dynamics", s.dynamics, dims, dims["x"], params, allowed_modules)
    assert s.sampling_time is not None  # required with ode (SubsystemSpec)
    return SampledFlow(f"subsystem '{name}' ode", s.ode, dims, dims["x"], params, allowed_modules,
                       sampling_time=s.sampling_time, substeps=s.substeps)


def _internal(spec: JobSpec, n_total: int, params: dict[str, float], allowed_modules: Sequence[str] | None,
              ) -> tuple[BlackBox, list[UniformGrid]]:
    """The interconnection map and the grids of the internal variables (none without an interconnection)."""
    ic = spec.interconnection
    if ic is None:
        return NoInternalVariables(n_total), []
    imap = BlackBox("interconnection map", ic.map, {"x": n_total}, None, params, allowed_modules)
    p = imap.out_dim
    internal_specs = ic.internal if isinstance(ic.internal, list) else [ic.internal] * p
    if len(internal_specs) != p:
        raise SpecError(f"interconnection.internal: {len(internal_specs)} grids given, the map has {p} outputs")
    internal_grids = []
    for j, g in enumerate(internal_specs):
        if g.dim != 1:
            raise SpecError(f"interconnection.internal[{j}]: each internal variable is scalar, got dimension {g.dim}")
        internal_grids.append(_grid(g, f"interconnection.internal[{j}]", "cover"))
    return imap, internal_grids


def build_network(spec: JobSpec, allowed_modules: Sequence[str] | None = ()) -> Network:
    """Resolve a spec into grids and black boxes.

    Parameters
    ----------
    allowed_modules
        Modules a ``module:function`` may name; ``None`` allows any (the local command line), the default
        ``()`` allows none (the service passes its allowlist).

    Raises
    ------
    SpecError
        For an empty grid, an unknown internal variable, a dimension mismatch, a bad expression.
    """
    params = dict(spec.parameters)
    subsystems: list[Subsystem] = []
    offset = 0
    # Internal grids are known once the map's output dimension is; the map needs the state dimension.
    copies = [_replicas(s, params) for s in spec.subsystems]
    dims = [box_dims(s, si, params) for si, s in enumerate(spec.subsystems)]
    n_total = sum(n * r for (n, _), r in zip(dims, copies))
    imap, internal_grids = _internal(spec, n_total, params, allowed_modules)
    p = imap.out_dim

    index = 0
    for si, s in enumerate(spec.subsystems):
        reads = _copy_reads(s, si, copies[si], params, p)
        for r in range(copies[si]):
            name = s.name if s.replicate == 1 else f"{s.name}[{r}]"
            where = f"subsystems[{si}] ('{name}')"
            xg = _grid(s.state, f"{where}.state", "cover", dims[si][0])
            ug = _grid(s.input, f"{where}.input", "inside", dims[si][1])
            wg = None
            if reads[r]:
                wg = UniformGrid.product([internal_grids[j] for j in reads[r]])
            dyn = _dynamics(s, name, {"x": xg.dim, "u": ug.dim, "w": len(reads[r])}, params, allowed_modules)
            ident = {
                "spec": s.model_dump(mode="json", exclude={"name", "replicate", "reads"}),
                "w": None if wg is None else wg.describe(),
                "params": params,
            }
            key = hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()[:16]
            subsystems.append(
                Subsystem(name, index, s, xg, ug, wg, reads[r], dyn, offset, key)
            )
            offset += xg.dim
            index += 1
    return Network(spec, tuple(subsystems), tuple(internal_grids), imap, params)
