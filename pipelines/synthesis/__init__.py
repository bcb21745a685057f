"""Controller synthesis on the symbolic abstraction (Section 4.3, Algorithm 5; docs/method.md §6).

Modules, by the paper's concepts:

* :mod:`.cpre` — :class:`~.cpre.ControllablePredecessor`: ``CPre(Z)`` with partitioned relations and early
  quantification (per-subsystem or shared internal inputs), and the policy for computing ``∃u.CPre`` in parts
  through an injected factory.
* :mod:`.at_state` — ``CPre`` at one state, what layered controllers evaluate cell by cell, and the chain's
  cofactors kept across the cells of a closed loop.
* :mod:`.symmetry` — interchangeable subsystems: ``∃u.CPre`` on one state per orbit, closed, and which sets are
  known invariant.
* :mod:`.partition` — where to cut the state space for ``∃u.CPre`` in parts, and why the parts are exact.
* :mod:`.local_games` — safety games on small groups of subsystems: a superset of the maximal controlled
  invariant that the safety fixed points start from.
* :mod:`.checkpoints` — what a safety fixed point asks of a store of its iterates (resuming a stopped job), and
  why resuming cannot make a controller unsound.
* :mod:`.domain_bound` — an outer bound of any specification's domain from the upstream-closed groups.
* :mod:`.quotient` — the game on blocks of ``2^k`` cells per coordinate: sound controllers when the exact fixed
  points are too large, domains that may be smaller than the maximal ones.
* :mod:`.fixed_points` — the fixed points of the specifications (safety, reachability, reach-avoid,
  reach-and-stay as co-Büchi and as Reach(Safe)) and :class:`~.fixed_points.SynthesisResult`.
* :mod:`.synthesize` — a job's synthesis: encode the abstraction, solve its specification, report.
"""
