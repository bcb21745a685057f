"""The black-box map ``M`` sampled in batches, each value checked against its internal box (Definition intercon).

The map (all composed states -> all internal variables) is only ever evaluated through :class:`Sampler`. Every
value it returns is checked to lie in its declared internal box: node relations are clipped to the output
grids, which is sound for ``w_j`` only because the box holds every value of ``M_j`` (Definition intercon); a
map value outside the box is a :class:`SpecError`. :meth:`Sampler.column` evaluates one output alone where the
map's text allows it.

Sample counts that grow with the map (beyond the paper)
-------------------------------------------------------
The paper fixes ``N_I`` (200 in Sec. 5.1) whatever the number of coordinates. That cannot identify a map that
reads more coordinates than it has samples: at N = 512 the least-squares refit of 512 coefficients from 200
samples is underdetermined, and the joint support check (all coordinates outside the support redrawn at once)
sees a dependence on one coordinate of ``max(x)`` only when that coordinate becomes the largest, about
``2 / n`` of the draws. So the spec's counts are minimums and two counts grow with the ``n`` coordinates the map
may read (the support is not known before the fit, and it can be all of them):

* :func:`training_count`: ``N_I = max(samples, 2 (n + 1))``. ``n + 1`` samples determine ``n`` coefficients and
  an intercept (the paper's ``dim(U) dim(X)`` for a linear map); twice that leaves as many residual degrees of
  freedom, so the least-squares refit on the support is overdetermined rather than an interpolation.
* :func:`check_count`: the joint support check draws ``max(holdout, 8 n)`` states, so that a coordinate that
  matters on a fraction ``c / n`` of the box is seen with probability ``1 - exp(-8 c)`` whatever ``n``.

Both equal the spec's counts while ``n`` is small (``N_I = 200`` up to ``n = 99``, ``holdout = 1000`` up to
``n = 125``), so the random streams and results of the small cases are unchanged.
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Sequence

import numpy as np

from pipelines.blackbox import BlackBox
from pipelines.errors import SpecError
from pipelines.expressions.checks import parse_python
from pipelines.network import Network
from pipelines.spec.model import is_module_function

__all__ = ["Sampler", "EVAL_ROWS", "TRAINING_PER_COEFFICIENT", "CHECK_PER_COORDINATE", "training_count",
           "check_count"]

#: Points per call of the black box (bounds memory: a call holds ``(rows, n)`` and ``(rows, p)`` floats).
EVAL_ROWS = 400_000
#: Training samples per coefficient to identify (``n`` coefficients and an intercept): see the module docstring.
TRAINING_PER_COEFFICIENT = 2
#: States of the joint support check per coordinate the map may read: see the module docstring.
CHECK_PER_COORDINATE = 8


def training_count(samples: int, n: int) -> int:
    """``N_I`` for lasso and the refit: the spec's ``samples``, at least ``2 (n + 1)`` (module docstring)."""
    return max(int(samples), TRAINING_PER_COEFFICIENT * (int(n) + 1))


def check_count(holdout: int, n: int) -> int:
    """States of the joint support check: the spec's ``holdout``, at least ``8 n`` (module docstring)."""
    return max(int(holdout), CHECK_PER_COORDINATE * int(n))


class Sampler:
    """Evaluates ``M`` in batches and checks every value against the internal boxes (Definition intercon)."""

    def __init__(self, network: Network) -> None:
        self.network = network
        self.map = network.interconnection_map
        grid = network.composed_state_grid()
        self.lb = np.asarray(grid.lb)
        self.ub = np.asarray(grid.ub)
        self.centre = (self.lb + self.ub) / 2
        self.w_lb = np.array([g.lb[0] for g in network.internal_grids])
        self.w_ub = np.array([g.ub[0] for g in network.internal_grids])
        self.evaluations = 0

    def uniform(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Uniform random states in the composed box, shape (count, n)."""
        return rng.uniform(self.lb, self.ub, (count, self.lb.size))

    def __call__(self, x: np.ndarray, columns: Sequence[int] | None = None) -> np.ndarray:
        """``M(x)``, shape (B, p), after checking ``columns`` (default all) lie in their internal boxes."""
        out = np.empty((x.shape[0], self.w_lb.size))
        for start in range(0, x.shape[0], EVAL_ROWS):
            xs = x[start : start + EVAL_ROWS]
            out[start : start + xs.shape[0]] = self.map(xs)
        self.evaluations += x.shape[0]
        cols = range(self.w_lb.size) if columns is None else columns
        for j in cols:
            self._check_box(j, out[:, j], lambda r: x[r])
        return out

    def _check_box(self, j: int, values: np.ndarray, point: Callable[[int], np.ndarray]) -> None:
        bad = (values < self.w_lb[j]) | (values > self.w_ub[j])
        if bad.any():
            r = int(np.argmax(bad))
            raise SpecError(
                f"interconnection map: internal variable w{j} = {float(values[r])!r} at x = {point(r).tolist()} lies "
                f"outside its box [{self.w_lb[j]}, {self.w_ub[j]}] (interconnection.internal[{j}]); the map "
                "must take its values in the internal boxes: widen that box"
            )

    def column(self, j: int) -> tuple[Callable[[np.ndarray], np.ndarray], bool]:
        """An evaluator of output ``j`` alone on states given transposed, ``xt`` of shape ``(n, B)`` -> ``(B,)``.

        The values are checked like :meth:`__call__` (finite, inside internal box ``j``). Where the map is a
        list literal ``[e_0, e_1, ...]`` of elementwise entries, row ``j`` of the map is entry ``j`` evaluated
        alone (``pipelines.expressions`` stacks the entries' values, one row each, each computed by its own compiled
        closure), so entry ``j`` is compiled on its own (through the same expression compiler, with the
        map's constants) and the other outputs are not computed. It is also checked to give the map's row
        ``j`` bit for bit on a few states. Otherwise (a vector expression, a module function, nested lists,
        any doubt) the whole map is evaluated and column ``j`` kept.

        Returns ``(evaluator, alone)``; ``alone`` says whether entry ``j`` is evaluated by itself.
        """
        entry = self._entry(j)

        def whole(xt: np.ndarray) -> np.ndarray:
            return self(xt.T, columns=[j])[:, j]

        if entry is None:
            return whole, False

        def alone(xt: np.ndarray) -> np.ndarray:
            y = entry(xt.T)[:, 0]
            self.evaluations += y.shape[0]
            self._check_box(j, y, lambda r: xt[:, r])
            return y

        return alone, True

    def _entry(self, j: int) -> BlackBox | None:
        """Entry ``j`` of a list-literal map as a black box of its own, or ``None`` (see :meth:`column`)."""
        source = self.map.source
        if is_module_function(source):
            return None
        try:
            text = source.lstrip()
            tree = parse_python(text)  # one parse at a time (gh-106905)
            assert isinstance(tree, ast.Expression)
            body = tree.body
        except (SyntaxError, SyntaxWarning, DeprecationWarning, ValueError, RecursionError,
                MemoryError):  # pragma: no cover - the map compiled
            return None
        if not isinstance(body, (ast.List, ast.Tuple)) or len(body.elts) != self.w_lb.size:
            return None  # not one elementwise entry per output
        elt = body.elts[j]
        if isinstance(elt, (ast.List, ast.Tuple, ast.Starred)):
            return None
        segment = ast.get_source_segment(text, elt)
        if segment is None:  # pragma: no cover
            return None
        n = self.lb.size
        try:
            box = BlackBox(f"interconnection map (output w{j})", f"({segment})", {"x": n}, 1,
                           self.network.constants, ())
        except Exception:  # a vector entry (out_dim != 1), or anything unexpected: evaluate the whole map
            return None
        # Bit-for-bit agreement with the whole map on a few states (a local generator: the job's stream of
        # random numbers is not touched).
        probe = np.random.default_rng(j).uniform(self.lb, self.ub, (64, n))
        probe[0] = self.lb
        probe[1] = self.ub
        probe[2] = self.centre
        try:
            with np.errstate(all="ignore"):
                # the entry on states laid out as direct_node lays them out (transposed), the map as before
                same = np.array_equal(box(np.ascontiguousarray(probe.T).T)[:, 0], self.map(probe)[:, j])
        except Exception:  # e.g. a non-finite value at a probe: let the whole map report it
            return None
        return box if same else None
