"""Hostile ``module:function`` black boxes for the trust campaign (``tests/test_trust_cluster.py``).

Each is small.yaml's agent dynamics, shapes ``(B, 1) -> (B, 1)``, except where it misbehaves. The misbehaviour
is confined to batches of more than one row, so that the one-row probe a :class:`~pipelines.blackbox.BlackBox`
makes when the spec is built passes and the failure happens where a job meets it: in a cluster task.
"""

from __future__ import annotations

import time

import numpy as np


def agent(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """small.yaml's agent."""
    return 32 / (1 + np.exp(-0.2 * (x + u + 0.1 * (x - w) - 16)))


def nan_above_20(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """NaN where x > 20."""
    out = agent(x, u, w)
    if x.shape[0] > 1:
        out = np.where(x > 20, np.nan, out)
    return out


def inf_above_20(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """+inf where x > 20."""
    out = agent(x, u, w)
    if x.shape[0] > 1:
        out = np.where(x > 20, np.inf, out)
    return out


def wrong_shape(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Two columns instead of one for a batch."""
    out = agent(x, u, w)
    return np.hstack([out, out]) if x.shape[0] > 1 else out


def flat_shape(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """A flat (B,) array instead of (B, 1) for a batch."""
    out = agent(x, u, w)
    return out[:, 0] if x.shape[0] > 1 else out


def raises(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Raises for a batch with a state above 20."""
    if x.shape[0] > 1 and np.any(x > 20):
        raise RuntimeError("the simulator crashed")
    return agent(x, u, w)


def hangs(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Blocks (in C, where no exception reaches it) for an hour on a batch with a state above 20."""
    if x.shape[0] > 1 and np.any(x > 20):
        time.sleep(3600)
    return agent(x, u, w)


def spins(x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Loops forever in Python on a batch with a state above 20 (an asynchronous exception can stop it)."""
    if x.shape[0] > 1 and np.any(x > 20):
        while True:
            pass
    return agent(x, u, w)
