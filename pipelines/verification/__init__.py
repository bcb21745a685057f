"""Checks of the guarantees against the concrete system.

* :mod:`.audit` — random concrete transitions checked against the subsystem relations (Theorem 4.2), the
  interconnection (Theorem 4.7) and their composition;
* :mod:`.closed_loop` — refinement in closed loop (Theorem 4.2): the concrete black boxes under a controller;
* :mod:`.empty_domain` — why a winning domain is empty, from the subsystem relations and the regions.
"""
