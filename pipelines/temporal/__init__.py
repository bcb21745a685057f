"""Temporal-logic specifications: LTLf formulas over named regions, their automata, and the cells' labels.

* :mod:`.formula`: the grammar (``ltlf2dfa``'s parser), the fragment, the atoms, and the MONA program;
* :mod:`.automaton`: the deterministic finite automaton read from MONA's answer;
* :mod:`.labels`: which letters a cell can carry (an atom holds on a cell only if it holds on all of it).

The product game with the abstraction is :mod:`pipelines.synthesis.product`; MONA itself runs outside the method
(:mod:`workers.automata`).
"""
