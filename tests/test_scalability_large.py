"""The scalability example (paper Sec. 5.1, ``w = max(x)``) at large N: sample counts, supports, soundness.

At N = 512 the spec's 200 samples and the one-at-a-time dependence test on 1000 states left coordinates of
``max(x)`` out of the support (each changes the maximum on about ``2 / N`` of the draws), and the job was
refused. The counts now grow with N (``pipelines.interconnection.sampling``) and the joint check adds what
the dependence test missed (``pipelines.interconnection.learning.complete_support``); the abstraction must
still contain the cell of ``max(x)`` for every concrete ``x``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipelines.errors import CertificationError
from pipelines.interconnection import abstract_interconnection
from pipelines.interconnection.learning import complete_support, validate_support
from pipelines.interconnection.sampling import Sampler, check_count, training_count
from pipelines.network import Network, build_network
from pipelines.spec.model import load_spec
from tests.test_interconnection import both_cells

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def scalability(N: int) -> Network:
    return build_network(load_spec(EXAMPLES / "scalability.yaml", {"N": N}), allowed_modules=None)


def max_cells_violations(net: Network, ia, count: int, seed: int) -> int:
    """Draws ``x`` (uniform, some coordinates on cell boundaries and box edges, some states near the diagonal)
    whose ``max(x)`` has a cell (either one on a boundary) outside ``M̂`` of a cell of ``x``."""
    rng = np.random.default_rng(seed)
    grid = net.composed_state_grid()
    n = grid.dim
    x = rng.uniform(0, 32, (count, n))
    snap = rng.random(x.shape) < 0.2
    x = np.where(snap, np.clip(np.round(x) + rng.choice([-0.5, 0.0, 0.5], x.shape), 0, 32), x)
    near = rng.random(count) < 0.3  # states whose coordinates are close: max(x) near every coordinate
    x[near] = np.clip(rng.uniform(0, 32, (int(near.sum()), 1)) + rng.uniform(-1, 1, (int(near.sum()), n)), 0, 32)
    w = net.interconnection_map(x)
    x_up, x_low = both_cells(grid, x)
    w_up, w_low = both_cells(net.internal_grids[0], w[:, :1])
    bad = np.zeros(count, dtype=bool)
    for xi in (x_up, x_low):
        for wi in (w_up, w_low):
            bad |= ~ia.contains(xi, wi)
    return int(bad.sum())


def test_sample_counts_are_the_specs_while_n_is_small_and_grow_with_it():
    assert training_count(200, 4) == 200 and training_count(200, 99) == 200 and training_count(200, 100) == 202
    assert training_count(200, 1024) == 2050
    assert check_count(1000, 125) == 1000 and check_count(1000, 512) == 4096


def test_scalability_at_256_is_sound_with_the_full_support():
    net = scalability(256)
    ia = abstract_interconnection(net, np.random.default_rng(256))
    assert ia.supports == (tuple(range(256)),)
    assert ia.details["samples_used"]["training"] == 514 and ia.details["samples_used"]["joint_check"] == 2048
    assert np.isfinite(ia.error_bounds[0])
    assert max_cells_violations(net, ia, 3_000, seed=1) == 0
    # Negative control: one cell short at the top must be caught.
    short = dataclasses.replace(ia, nodes=tuple(dataclasses.replace(n, hi=(n.hi - 1).astype(np.int32)) for n in ia.nodes))
    assert max_cells_violations(net, short, 3_000, seed=1) > 0


def test_the_joint_check_completes_a_support_the_dependence_test_left_short():
    """max of 300 coordinates with a dependence test on 40 states: most coordinates are missed (each matters on
    about 2/300 of the draws); the joint check finds them by bisection and the support ends complete."""
    spec = load_spec(EXAMPLES / "scalability.yaml", {"N": 300})
    ic = spec.interconnection.model_copy(update={"holdout": 40})
    net = build_network(spec.model_copy(update={"interconnection": ic}), allowed_modules=None)
    ia = abstract_interconnection(net, np.random.default_rng(7))
    assert ia.supports == (tuple(range(300)),)
    assert len(ia.details["support_added_by_joint_check"][0]) > 100
    assert max_cells_violations(net, ia, 2_000, seed=2) == 0


def test_the_plain_joint_check_still_refuses_a_short_support():
    net = scalability(64)
    sample = Sampler(net)
    dep = np.zeros((64, 1), dtype=bool)
    with pytest.raises(CertificationError, match="w0 depends on the coordinates .* jointly"):
        validate_support(sample, 0, tuple(range(32)), dep, 2_000, np.random.default_rng(0))
    support, change, added = complete_support(sample, 0, tuple(range(32)), dep, 2_000, np.random.default_rng(0))
    assert support == tuple(range(64)) and change == 0.0 and sorted(added) == list(range(32, 64))


def test_a_coordinate_that_matters_on_a_sliver_is_found_by_bisection():
    """x5 moves the map only where it exceeds 31.5 (1/64 of its range); bisection pins it, x6 and x7 stay out."""
    spec = load_spec(EXAMPLES / "scalability.yaml", {"N": 8})
    ic = spec.interconnection.model_copy(update={"map": "0.9 * max(x[0:5]) + maximum(x[5] - 31.5, 0)"})
    net = build_network(spec.model_copy(update={"interconnection": ic}), allowed_modules=None)
    sample = Sampler(net)
    dep = np.zeros((8, 1), dtype=bool)
    support, _, added = complete_support(sample, 0, tuple(range(5)), dep, 4_000, np.random.default_rng(3))
    assert support == (0, 1, 2, 3, 4, 5) and added == [5]
