"""The report's numbers of a fixed point's result, whichever way the game was solved (docs/method.md §6).

Both result types, the BDD one (:class:`~.fixed_points.SynthesisResult`) and the explicit one
(:class:`~.explicit.ExplicitResult`), report the same numbers first, so that a report reads the same for both
backends; then how the controller is kept and its size, which differ.
"""

from __future__ import annotations

from typing import Any

#: What every result reports first, in this order.
COMMON = ("kind", "domain_states", "iterations", "inner_iterations", "seconds")


def summary(result: Any, **form: Any) -> dict[str, Any]:
    """JSON-ready numbers of ``result``: its :data:`COMMON` attributes, then ``form`` (the controller's form and
    size), then its ``details``."""
    return {**{name: getattr(result, name) for name in COMMON}, **form, **result.details}
