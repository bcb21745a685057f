"""Grids and regions reproduce the paper's counts exactly (docs/method.md §1)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipelines.errors import SpecError
from pipelines.grid import UniformGrid
from pipelines.spec.model import Region
from pipelines.spec.regions import abstract_region, union_count


def test_paper_state_counts():
    assert UniformGrid.covering([0] * 8, [32] * 8, 1).size == 33**8 == 1_406_408_618_241
    assert UniformGrid.covering([1] * 10, [100] * 10, 2.5).size == 41**10 == 13_422_659_310_152_401


def test_paper_region_counts():
    g8 = UniformGrid.covering([0] * 8, [32] * 8, 1)
    consensus = Region(consensus={"centers": (0, 31, 1), "radius": 2.5})
    assert abstract_region(consensus, g8, "target").states == 9_493_117
    g10 = UniformGrid.covering([1] * 10, [100] * 10, 2.5)
    tanks = Region(boxes=[{"lb": 8.75, "ub": 51.25}])
    assert abstract_region(tanks, g10, "target").states == 17**10 == 2_015_993_900_449


def test_bounds_not_multiple_of_eta_are_snapped_relatively():
    # 0.3 / 0.1 is 2.9999999999999996 in floating point; an absolute or no tolerance mis-sizes the grid.
    g = UniformGrid.inside(0.0, 0.3, 0.1)
    assert g.shape == (4,)
    g = UniformGrid.covering(0.05, 0.35, 0.1)  # bounds exactly on cell boundaries
    assert g.shape == (3,)
    assert g.k_lo == (1,) and g.k_hi == (3,)


def test_input_grid_holds_points_inside():
    g = UniformGrid.inside(0, 10, 1.5)
    assert np.allclose(g.axis_points(0), [0, 1.5, 3, 4.5, 6, 7.5, 9])


@pytest.mark.parametrize("lb,ub,eta,msg", [(1, 0, 1, "empty box"), (0, 1, 0, "positive"), (0.2, 0.3, 1, "empty grid")])
def test_bad_grids_are_rejected(lb, ub, eta, msg):
    make = UniformGrid.inside if msg == "empty grid" else UniformGrid.covering
    with pytest.raises(SpecError, match=msg):
        make(lb, ub, eta)


def test_empty_region_is_rejected():
    g = UniformGrid.covering([0, 0], [10, 10], 1)
    with pytest.raises(SpecError, match="no whole grid cell"):
        abstract_region(Region(boxes=[{"lb": 0.6, "ub": 1.4}]), g, "specification.target")


@settings(max_examples=200, deadline=None)
@given(
    lb=st.floats(-50, 50, allow_nan=False),
    width=st.floats(0.0, 30, allow_nan=False),
    eta=st.floats(0.05, 5, allow_nan=False),
    xs=st.lists(st.floats(0, 1), min_size=1, max_size=20),
)
def test_covering_cells_cover_the_box(lb, width, eta, xs):
    """Every concrete point of the box lies in a cell of the grid; no cell misses the box."""
    ub = lb + width
    g = UniformGrid.covering(lb, ub, eta)
    x = lb + np.asarray(xs)[:, None] * width
    for tie in ("upper", "lower"):
        idx, inside = g.cell_of(np.clip(x, lb, ub), tie)
        lo, hi = g.clipped_cells(np.clip(idx, 0, g.size - 1))
        covered = inside & (lo[:, 0] <= x[:, 0]) & (x[:, 0] <= hi[:, 0])
        # a point is covered by its tie-broken cell, or (on a boundary) by the other one
        other, other_in = g.cell_of(np.clip(x, lb, ub), "lower" if tie == "upper" else "upper")
        assert np.all(covered | other_in)
    lo, hi = g.clipped_cells(g.unravel(np.arange(g.size)))
    assert np.all(lo <= hi)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6), st.integers(0, 6), st.integers(0, 6)), min_size=1, max_size=6))
def test_union_count_matches_enumeration(raw):
    boxes = []
    for a, b, c, d in raw:
        boxes.append((np.array([min(a, b), min(c, d)]), np.array([max(a, b), max(c, d)])))
    grid = np.zeros((7, 7), dtype=bool)
    for lo, hi in boxes:
        grid[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1] = True
    assert union_count(boxes) == int(grid.sum())


def test_avoid_sets_are_approximated_from_outside():
    g = UniformGrid.covering([0, 0], [10, 10], 1)
    region = Region(boxes=[{"lb": 0.4, "ub": 1.4}])
    outer = abstract_region(region, g, "specification.avoid", outer=True)
    assert outer.states == 4  # cells 0..1 in each dimension meet [0.4, 1.4]
    with pytest.raises(SpecError):
        abstract_region(region, g, "specification.target")  # no whole cell inside
    assert outer.contains(np.array([[1, 1], [0, 1], [2, 2]])).tolist() == [True, True, False]


@pytest.mark.parametrize("make", [UniformGrid.covering, UniformGrid.inside])
@pytest.mark.parametrize("lb,ub,eta", [(-1e308, 1e308, 1e-300), (0.0, 1e308, 1e-10), (-1e300, 0.0, 1e-300)])
def test_a_grid_whose_point_count_overflows_is_a_clear_error_without_warnings(make, lb, ub, eta):
    """(ub - lb) / eta beyond float range: the SpecError says to use a larger eta, and numpy's overflow
    warnings (which a library user would see on stderr before it) are not emitted."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SpecError, match="too fine.*use a larger eta"):
            make(lb, ub, eta)


def test_boxes_beyond_every_index_are_clamped_not_wrapped():
    """A box bound of ±1e308 over a spacing of 0.25 is an infinite index: numpy casts it to -2^63, which made the
    box [-1e308, 1e308] (all of the grid) an empty region and a successor at 1e308 a cell below the grid."""
    import warnings

    g = UniformGrid(origin=(0.0,), eta=(0.25,), k_lo=(0,), k_hi=(10,), lb=(0.0,), ub=(2.5,))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "invalid value encountered in cast" is the symptom
        first, last = g.inner_range([-1e308], [1e308])
        assert (first.tolist(), last.tolist()) == ([0], [10])
        first, last = g.inner_range([0.0], [1e308])
        assert (first.tolist(), last.tolist()) == ([1], [10])  # cell 0 reaches below 0
        first, last = g.inner_range([1e308], [np.inf])
        assert first[0] > last[0]  # empty: the box lies above the grid
        lo, hi = g.cells_touching(np.array([[-1e308]]), np.array([[1e308]]))
        assert lo[0, 0] < 0 and hi[0, 0] > 10  # reaches out of the grid on both sides
        idx, inside = g.cell_of(np.array([[1e308], [-np.inf]]))
        assert idx[0, 0] > 10 and idx[1, 0] < 0 and not inside.any()


@pytest.mark.parametrize("tie", ["upper", "lower"])
def test_cell_of_equals_its_numpy_expression(tie):
    """The compiled cell_of against the expression it fuses (snap, floor or ceil, clamp) on random points, cell
    boundaries within rounding, far and infinite points; NaN is off the grid."""
    from pipelines.grid import _index, _snap

    rng = np.random.default_rng(4)
    g = UniformGrid.covering([-3.0, 0.1, 1e6], [5.0, 2.2, 1e6 + 40], [0.25, 0.3, 1.5])
    edges = np.asarray(g.origin) + (np.arange(-2, 40)[:, None] - 0.5) * g.eta_array
    x = np.concatenate([
        rng.uniform(g.lb, g.ub, (500, 3)),
        edges, edges * (1 + 1e-12), edges * (1 - 1e-12), edges + 1e-7,
        [[1e308, -1e308, 0.0], [np.inf, -np.inf, 1e6], [-1e300, 2.0, np.inf]],
    ])
    idx, inside = g.cell_of(x, tie)
    with np.errstate(over="ignore", invalid="ignore"):
        r = _snap((x - np.asarray(g.origin)) / g.eta_array + 0.5)
    expect = _index(np.floor(r) if tie == "upper" else np.ceil(r) - 1) - np.asarray(g.k_lo, dtype=np.int64)
    np.testing.assert_array_equal(idx, expect)
    np.testing.assert_array_equal(inside, g.on_grid(expect))
    assert 0 < inside.sum() < len(x)
    nan_idx, nan_inside = g.cell_of(np.array([[np.nan, 1.0, 1e6 + 1]]), tie)
    assert not nan_inside[0] and nan_idx.shape == (1, 3)
    assert g.cell_of(x[0], tie)[0].shape == (3,)
