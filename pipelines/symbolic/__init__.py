"""The symbolic layer: the abstraction as BDDs (Algorithm 5, Section 4.3; docs/method.md §5). The only package that
imports ``dd`` and ``oxidd``.

Modules, by the paper's concepts:

* :mod:`.model` — :class:`~.model.SymbolicModel`: one CUDD manager, the binary encoding of grid cells as
  digits and bits, interval comparators and domain constraints, ``x -> x'`` renaming; :data:`~.model.Function`
  and :func:`~.model.and_exists` for the synthesis.
* :mod:`.order` — the variable order (``interleaved`` / ``shared_top``) and the order of the subsystems' blocks.
* :mod:`.tree` — bulk construction of BDDs from arrays as Shannon trees (docs/method.md §5: never one point at a time).
* :mod:`.relations` — the subsystem relations ``T_i`` and non-blocking sets ``NB_i`` (Definition 4.2), the
  interconnection relation ``M̂ = ∃z. ∧ R_node`` (Section 4.2, Theorem 4.7), regions and sets of states.
* :mod:`.counting` — exact counts, uniform sampling and listing of the cells of a BDD.
* :mod:`.node_table` — a BDD over the state bits as a node table, evaluated on many cells at once.
* :mod:`.files` — DDDMP files with a JSON header (controllers, helper-process transport).
* :mod:`.oxidd_mirror` — oxidd beside CUDD over the same variables, for the synthesis's ``∃u.CPre`` on several
  threads; :mod:`.engines` — both engines on problems read from files (``bench/engines.py``).
"""
