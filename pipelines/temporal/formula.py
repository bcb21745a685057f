"""An LTLf formula over named regions: parsed, checked against its fragment and its atoms, written for MONA.

The grammar is ``ltlf2dfa``'s (a maintained LTLf-to-DFA library): atoms are region names (a lower-case letter,
then lower-case letters, digits and ``_``), ``true``/``false``, and the operators below, with the usual
precedence (``!``, ``X``, ``F``, ``G`` bind tightest, then ``U``, ``&``, ``|``, ``->``, ``<->``) and parentheses.

========  ==================  ==========================================================
operator  also written        meaning on a finite trace
========  ==================  ==========================================================
``!``     ``~``               not
``&``     ``&&``              and
``|``     ``||``              or
``->``    ``=>``              implies
``<->``   ``<=>``             equivalent
``X``                         strong next: there is a next instant and it holds there
``F``                         eventually (now or later)
``G``                         always (now and at every later instant of the trace)
``U``                         ``a U b``: ``b`` holds at some instant and ``a`` at every one before it
========  ==================  ==========================================================

Outside the fragment, and refused with the operator named: ``R`` (release), ``WX`` (weak next) and ``last``; the
fragment is the one a co-safe task needs (docs/spec.md, "Temporal-logic tasks").

The translation to an automaton is MONA's (through ``ltlf2dfa``'s encoding of LTLf in monadic second-order logic,
:func:`mona_program`); :mod:`.automaton` reads MONA's answer.
"""

from __future__ import annotations

import re
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any

from pipelines.errors import SpecError

#: A region name usable as an atom (``ltlf2dfa``'s symbols: upper case is reserved for its operators).
ATOM = re.compile(r"[a-z][a-z0-9_]*\Z")
#: Words of the grammar that cannot name a region.
RESERVED = frozenset({"true", "false", "last", "end"})
#: The longest formula accepted (characters): MONA's time grows at least exponentially with the formula.
MAX_FORMULA_CHARS = 2000
#: Operators outside the fragment, by the class ``ltlf2dfa`` parses them into.
_OUTSIDE = {"LTLfRelease": "'R' (release)", "LTLfWeakNext": "'WX' (weak next)", "LTLfLast": "'last'",
            "LTLfEnd": "'end'"}

_parser: Any = None


def _parse(text: str) -> Any:
    global _parser
    if _parser is None:  # lark builds its tables once (tenths of a second)
        from ltlf2dfa.parser.ltlf import LTLfParser

        _parser = LTLfParser()
    return _parser(text)


@dataclass(frozen=True)
class Formula:
    """A checked LTLf formula.

    Attributes
    ----------
    text : str
        As the user wrote it.
    atoms : tuple of str
        The region names it uses, sorted (the automaton's letters are bit vectors over them in this order).
    tree : object
        ``ltlf2dfa``'s formula object.
    """

    text: str
    atoms: tuple[str, ...]
    tree: Any

    def mona_program(self) -> str:
        """The MONA program whose automaton accepts exactly the finite traces satisfying the formula."""
        from ltlf2dfa.base import MonaProgram

        return str(MonaProgram(self.tree).mona_program())


def check_region_name(name: str, where: str) -> None:
    """Refuse a region name that cannot be an atom of a formula.

    Raises
    ------
    SpecError
    """
    if not ATOM.match(name) or name in RESERVED:
        raise SpecError(f"{where}: region name {name!r} cannot be an atom of a formula: use a lower-case letter "
                        "followed by lower-case letters, digits or '_' (not true, false, last or end)")


def check_ltl_fields(others: list[str], formula: str | None, regions: Collection[str] | None) -> None:
    """The fields of an ``ltl`` specification (``pipelines.spec.model.SpecificationSpec``): a formula, at least one
    region, each name an atom, none of ``others`` (the given ``target``/``safe``/``avoid``: a safe set ``s`` is
    written ``G s``, an obstacle ``o`` ``G !o``). The formula itself is parsed by :func:`parse_formula`.

    Raises
    ------
    ValueError
        For the spec model to name the field.
    """
    if others:
        raise ValueError(f"an 'ltl' specification has no {' or '.join(repr(k) for k in others)}: name the region in "
                         "'regions' and write it in the formula (a safe set s: G s; a target t: F t; an obstacle o: "
                         "G !o)")
    if formula is None or not regions:
        missing = "'formula'" if formula is None else "'regions' (at least one named region)"
        raise ValueError(f"an 'ltl' specification needs {missing}")
    for name in regions:
        try:
            check_region_name(name, f"specification.regions.{name}")
        except SpecError as exc:
            raise ValueError(str(exc).split(": ", 1)[1]) from None


def parse_formula(text: str, regions: Collection[str], where: str = "specification.formula") -> Formula:
    """Parse ``text`` and check it: inside the fragment, every atom one of ``regions``.

    Raises
    ------
    SpecError
        Naming the token and its position (1-based column) where the formula does not parse, the operator outside
        the fragment, or the atom that names no region.
    """
    if not isinstance(text, str) or not text.strip():
        raise SpecError(f"{where}: an empty formula")
    if len(text) > MAX_FORMULA_CHARS:
        raise SpecError(f"{where}: {len(text)} characters; a formula has at most {MAX_FORMULA_CHARS}")
    from lark.exceptions import LarkError, UnexpectedCharacters, UnexpectedEOF, UnexpectedToken

    try:
        tree = _parse(text)
    except UnexpectedCharacters as exc:
        at = exc.pos_in_stream or 0
        raise SpecError(f"{where}: unexpected {text[at]!r} at position {at + 1}: {_pointer(text, at)}") from None
    except UnexpectedEOF:
        raise SpecError(f"{where}: the formula ends too early: {_pointer(text, len(text))}") from None
    except UnexpectedToken as exc:
        token = str(exc.token)
        if exc.token.type == "$END" or not token:
            raise SpecError(f"{where}: the formula ends too early: {_pointer(text, len(text))}") from None
        pos = exc.token.start_pos if exc.token.start_pos is not None else 0
        raise SpecError(f"{where}: unexpected {token!r} at position {pos + 1}: {_pointer(text, pos)}") from None
    except (LarkError, RecursionError, ValueError) as exc:
        raise SpecError(f"{where}: the formula does not parse ({type(exc).__name__})") from None
    _check_fragment(tree, where)
    atoms = tuple(sorted({str(a) for a in tree.find_labels()}))
    known = set(regions)
    for atom in atoms:
        if atom not in known:
            have = ", ".join(sorted(known)) or "none"
            raise SpecError(f"{where}: atom {atom!r} names no region (the regions are: {have})")
    return Formula(text, atoms, tree)


def _check_fragment(tree: Any, where: str) -> None:
    stack = [tree]
    while stack:
        node = stack.pop()
        name = type(node).__name__
        if name in _OUTSIDE:
            raise SpecError(f"{where}: {_OUTSIDE[name]} is outside the supported fragment (!, &, |, ->, <->, X, F, "
                            "G, U)")
        stack.extend(getattr(node, "formulas", ()) or ())
        if hasattr(node, "f"):
            stack.append(node.f)


def _pointer(text: str, pos: int) -> str:
    """The formula with a marker before position ``pos`` (0-based), on one line."""
    return f"{text[:pos]}⟨here⟩{text[pos:]}".replace("\n", " ")
