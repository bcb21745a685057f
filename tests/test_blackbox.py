"""BlackBox on batches of several axes: the same values as on the materialised (B, d) arrays, for expressions
(evaluated on the views) and module functions (given copies), and a non-finite value named at its row."""

import numpy as np
import pytest

from pipelines.blackbox import BlackBox
from pipelines.errors import BlackBoxError

EXPR = "32 / (1 + exp(-0.2 * (x[0] + u[0] + 0.1 * (x[0] - w[0]) - 16)))"
INPUTS = {"x": 1, "u": 1, "w": 1}


def _grid(rng):
    # (Sx, 1, B, 1) states, (B, 1) inputs, (Sw, B, 1) internal inputs: abstract_cells's sample layout
    return rng.uniform(0, 32, (4, 1, 6, 1)), rng.uniform(-2, 2, (6, 1)), rng.uniform(0, 32, (3, 6, 1))


@pytest.mark.parametrize("source", [EXPR, "tests.hostile_boxes:agent"])
def test_a_grid_of_views_gives_the_values_of_the_flat_arrays(source):
    box = BlackBox("agent", source, INPUTS, allowed_modules=None)
    x, u, w = _grid(np.random.default_rng(1))
    out = box(x, u, w)
    assert out.shape == (4, 3, 6, 1)
    flat = [np.broadcast_to(a, (4, 3, 6, 1)).reshape(-1, 1) for a in (x, u, w)]
    np.testing.assert_array_equal(out.reshape(-1, 1), box(*flat))


def test_an_expression_that_reads_only_some_axes_is_broadcast_to_the_batch():
    box = BlackBox("half", "0.5 * x[0]", INPUTS)
    x, u, w = _grid(np.random.default_rng(2))
    out = box(x, u, w)
    assert out.shape == (4, 3, 6, 1)
    np.testing.assert_array_equal(out[:, 1], 0.5 * x[:, 0])


@pytest.mark.parametrize("source", ["log(x[0] - 10)", "numpy:log"])
def test_a_nan_in_a_grid_is_named_at_its_row(source):
    box = BlackBox("log", source, INPUTS if source.startswith("log") else {"x": 1}, allowed_modules=None)
    x, u, w = _grid(np.random.default_rng(3))
    x[:] = 11.0 + x / 2  # log's argument > 0 everywhere ...
    x[2, 0, 4, 0] = 5.0 if source.startswith("log") else -5.0  # ... but at state sample 2 of triple 4
    args = (x, u, w) if source.startswith("log") else (x + 0 * w[None, :, :, :1],)  # the first bad row: (2, 0, 4)
    with pytest.raises(BlackBoxError, match=r"returned \[nan\] \(not finite\) at x=\[-?5\.\].*\(row 40\)"):
        box(*args, describe=lambda r: f"row {r}")
    assert np.ravel_multi_index((2, 0, 4), (4, 3, 6)) == 40


def test_batch_shapes_that_do_not_broadcast_are_a_clear_error():
    box = BlackBox("agent", EXPR, INPUTS)
    with pytest.raises(BlackBoxError, match="do not broadcast"):
        box(np.ones((4, 1)), np.ones((3, 1)), np.ones((4, 1)))
