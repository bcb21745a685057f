"""Subsystem abstraction from data (Section 4.1, Algorithm 1, Definition 4.2; docs/method.md §2-3).

* :mod:`.relation` — the relation of one subsystem (successor index ranges and blocking flags) and its chunks;
* :mod:`.cells` — Algorithm 1 on a chunk of state cells (:class:`~.cells.CellTask`, the unit an executor runs);
* :mod:`.growth_bound` — the growth bounds behind one interface (:class:`~.growth_bound.GrowthBound`, passed to the
  per-cell stage): Lipschitz (Lemma 4.3), the corrected scenario program (Theorem 4.4) solved exactly in batches, and
  the hull bound, each per component;
* :mod:`.constants` — Lipschitz constants per component (:class:`~.constants.LipschitzMatrix`) and in the norm;
* :mod:`.kernels` — the compiled (numba) per-cell pass of scalar subsystems, bit-identical to the numpy path;
* :mod:`.lipschitz` — Lipschitz constants: estimated (Algorithm 4, per entry too), and checked against the data per
  entry.
"""
