"""A two-column table for people: a label column as wide as its longest label, and text that wraps beside it.

``compabs run``'s summary is laid out here (:func:`service.cli.summary_lines`): no column is aligned by hand,
so a long subsystem name or a large count can never run into the text beside it.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

__all__ = ["Row", "format_table"]

#: A row: its label and the parts of its text (joined by ", ", wrapped between parts only).
Row = tuple[str, Sequence[str]]

#: Joins the words of one part: textwrap breaks lines at ASCII whitespace only.
NBSP = "\u00a0"


def format_table(rows: Sequence[Row], width: int = 100, indent: int = 2, gap: int = 2, min_label: int = 12,
                 max_label: int = 40) -> list[str]:
    """Lay out ``rows`` as lines of at most ``width`` columns (a part longer than a line overflows it alone).

    Parameters
    ----------
    rows : sequence of (label, parts)
        The parts of a row are joined by ``", "``; a line breaks between parts only, so a number is never parted
        from its unit.
    indent, gap : int
        Spaces before the labels, and between the label column and the text (at least one).
    min_label, max_label : int
        Bounds of the label column's width: it is as wide as the longest label of at most ``max_label``
        characters. A longer label gets a line of its own, its text starting on the next line in the text column.

    Returns
    -------
    list of str
        One string per printed line, continuation lines indented to the text column.
    """
    labels = [label for label, _ in rows]
    column = max(min_label, max((len(label) for label in labels if len(label) <= max_label), default=0))
    lead = " " * indent
    text_at = indent + column + max(gap, 1)
    lines: list[str] = []
    for label, parts in rows:
        glued = ", ".join(part.replace(" ", NBSP) for part in parts)
        if len(label) > column:
            lines.append(lead + label)
            first = " " * text_at
        else:
            first = lead + label.ljust(text_at - indent)
        wrapped = textwrap.wrap(glued, max(width, text_at + 1), initial_indent=first, subsequent_indent=" " * text_at,
                                break_on_hyphens=False, break_long_words=False)
        lines.extend(line.replace(NBSP, " ") for line in wrapped or [first.rstrip()])
    return lines
