"""compabs pipelines: the method of Ajeleye & Zamani, as pure functions over numpy arrays and BDDs.

Nothing here starts a process, knows a storage format or imports Dask, Zarr or FastAPI (``tests/test_layout.py``
checks it); running the method is :mod:`workers`'s job. One place per concept of the paper:

* :mod:`pipelines.grid` — uniform grids and cells (§4.1, docs/method.md §1);
* :mod:`pipelines.spec` — the job spec (``model``) and its regions on the grids (``regions``);
* :mod:`pipelines.expressions`, :mod:`pipelines.blackbox`, :mod:`pipelines.network` — the whitelisted dynamics,
  the black boxes and the interconnected system a spec describes;
* :mod:`pipelines.abstraction` — subsystem abstraction (Algorithm 1, Def. 4.2): growth bounds (Lemma 4.3,
  Theorem 4.4), the per-cell kernels, the relation type, Lipschitz constants (Algorithm 4);
* :mod:`pipelines.interconnection` — learning, certifying and decomposing the interconnection (Algorithms 2-3);
* :mod:`pipelines.symbolic` — BDDs (the only import of ``dd``): encoding, relations, counting, DDDMP files;
* :mod:`pipelines.synthesis` — the controllable predecessor and the fixed points (Algorithm 5);
* :mod:`pipelines.controller` — the refined controller (Theorem 4.2);
* :mod:`pipelines.verification` — the audit (Theorems 4.2, 4.7 on samples) and closed-loop runs;
* :mod:`pipelines.figures` — the figures of a run.
"""

from __future__ import annotations

from pathlib import Path


def load_controller(directory: str | Path, name: str = "controller"):
    """Load a controller saved by ``compabs run`` (see :func:`pipelines.controller_loading.load_controller`);
    imported on use, so that ``import pipelines.grid`` does not load CUDD."""
    from pipelines.controller_loading import load_controller as _load

    return _load(directory, name)


__all__ = ["load_controller"]
