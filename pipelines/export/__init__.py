"""Controllers that leave the tool: determinized, minimised, written as JSON, CSV or C, and read back (issue 25).

* :mod:`.table` — the exported form of a determinized controller (a reduced BDD over the state bits as a node
  table, :mod:`pipelines.symbolic.node_table`, or an exact decision tree over the cell indices), and
  :class:`~.table.ExportedController` (the JSON read back, quantized as every controller is,
  :func:`pipelines.grid.quantize`).
* :mod:`.determinize` — one input per domain state, by a documented rule, as a BDD; its node table.
* :mod:`.decision_tree` — an exact axis-aligned decision tree over the cell indices (greedy, CART-like).
* :mod:`.emit` — the export (the smaller of the two forms) as JSON and CSV; its domain's cells listed, counted and
  sampled uniformly from the BDD table.
* :mod:`.c` — the export as a C99 header and source (``compabs_control``).
* :mod:`.memory`, :mod:`.memory_c` — an ``ltl`` job's controller with memory: the automaton, the atoms' boxes and
  per automaton state its determinized controller, as JSON, CSV and C (``compabs_step``).

This ``__init__`` imports nothing. The package sits above :mod:`pipelines.controller` (:mod:`.determinize` and
:mod:`.emit` import it, never the reverse); :mod:`pipelines.controller_loading` sits above both.
"""
