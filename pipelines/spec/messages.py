"""The messages of a spec that does not validate: one line per field, named as the user wrote it.

pydantic's locations carry the members of unions (``lb.float``, ``internal.function-after[...]``), which are not
fields and are left out; a strict number field that got a boolean, a string or a non-finite number says what it
got (``not the string '100' (write it without quotes)``).
"""

from __future__ import annotations

import math
import re
from typing import Any

from pydantic import ValidationError

#: The names pydantic gives the members of a union in an error's location (``lb.float``, ``lb.list[float]``,
#: ``internal.function-after[_lengths(), GridSpec]``): not fields, left out of the field's name.
_UNION_TAG = re.compile(r"^(float|int|str|bool|none|constrained-str|[a-z-]+\[.*\]|[A-Z][A-Za-z]*(Spec|Region))$")


def _field_name(loc: tuple[int | str, ...], kind: str = "") -> str:
    """The field an error is about, without union tags. The last element of an ``extra_forbidden`` location is the
    user's own key (which may well be called ``none`` or ``float``), never a tag."""
    keep = len(loc) - 1 if kind == "extra_forbidden" else len(loc)
    parts = [str(p) for i, p in enumerate(loc)
             if i >= keep or not (isinstance(p, str) and _UNION_TAG.match(p) and (i == 0 or loc[i - 1] != "parameters"))]
    return ".".join(parts) or "(spec)"


def _strict_message(e: Any) -> str:
    """pydantic's message, saying what was given where a strict number field got something else."""
    given = e.get("input")
    if e["type"] not in ("int_type", "float_type"):
        return e["msg"]
    if isinstance(given, bool):
        return f"Input should be a number, not the boolean {str(given).lower()}"
    if isinstance(given, str):
        return f"Input should be a number, not the string {given[:40]!r} (write it without quotes)"
    if isinstance(given, float) and not math.isfinite(given):
        return "Input should be a finite number"
    if isinstance(given, float) and e["type"] == "int_type":
        return f"Input should be an integer, not {given:g}"
    return e["msg"]


def format_validation_error(err: ValidationError) -> str:
    """One line per field of a spec's validation errors, each naming the field (``subsystems.0.samples``)."""
    # One line per field; a union's members' complaints about the same field are joined with "or".
    messages: dict[str, list[str]] = {}
    for e in err.errors():
        said = messages.setdefault(_field_name(e["loc"], e["type"]), [])
        msg = _strict_message(e)
        if msg not in said:
            said.append(msg)
    return "invalid spec:\n  " + "\n  ".join(f"{loc}: {' or '.join(msgs)}" for loc, msgs in messages.items())
