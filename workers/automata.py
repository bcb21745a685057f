"""Running MONA: an LTLf formula's automaton (:mod:`pipelines.temporal`), under a time cap, in a private folder.

MONA (Debian's ``mona``) decides the monadic second-order program that ``ltlf2dfa`` writes for the formula and
prints the minimal DFA; :func:`pipelines.temporal.automaton.from_mona` reads it. MONA's time and memory can grow
non-elementarily with the formula, so it runs as a child process with a wall-time limit and an address-space cap,
and its automaton is refused above the state cap.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from pipelines.errors import SpecError
from pipelines.temporal.automaton import MAX_STATES, Automaton, from_mona
from pipelines.temporal.formula import Formula, parse_formula

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.spec.model import SpecificationSpec

#: Seconds MONA may take for one formula.
TIME_LIMIT = 30.0
#: Address space MONA may use (bytes).
MEMORY_LIMIT = 2 << 30


def mona_path() -> str:
    """The ``mona`` executable.

    Raises
    ------
    SpecError
        MONA is not installed.
    """
    path = shutil.which("mona")
    if path is None:
        raise SpecError("an 'ltl' specification needs MONA to translate its formula: install Debian's package "
                        "'mona' (apt-get install mona)")
    return path


def _limit_memory() -> None:  # pragma: no cover - runs in the child
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def translate(formula: Formula, max_states: int = MAX_STATES, time_limit: float = TIME_LIMIT) -> Automaton:
    """The automaton of ``formula``: its finite traces (non-empty, each letter the atoms that hold) are accepted
    iff they satisfy it.

    Raises
    ------
    SpecError
        MONA missing, over its time or memory limit, or an automaton over ``max_states`` states.
    """
    exe = mona_path()
    with tempfile.TemporaryDirectory(prefix="compabs-mona-") as folder:
        program = Path(folder) / "formula.mona"
        program.write_text(formula.mona_program())
        try:
            done = subprocess.run([exe, "-q", "-u", "-w", str(program)], capture_output=True, text=True,
                                  timeout=time_limit, preexec_fn=_limit_memory, cwd=folder,
                                  env={"PATH": os.environ.get("PATH", "/usr/bin:/bin")})
        except subprocess.TimeoutExpired:
            raise SpecError(f"specification.formula: its translation to an automaton took more than {time_limit:g} s "
                            "(MONA's limit here); split the task or simplify the formula") from None
    if done.returncode != 0 or "Automaton has" not in done.stdout:
        lines = (done.stderr or done.stdout).strip().splitlines()
        reason = lines[-1] if lines else f"exit status {done.returncode}"
        raise SpecError(f"specification.formula: MONA could not translate it ({reason}); it may be over MONA's "
                        f"memory limit of {MEMORY_LIMIT >> 20} MiB")
    return from_mona(done.stdout, formula.atoms, max_states)


def spec_automaton(specification: SpecificationSpec, max_states: int = MAX_STATES) -> Automaton:
    """The automaton of an ``ltl`` specification's formula (parsed against its regions, then :func:`translate`).

    Raises
    ------
    SpecError
        As :func:`~pipelines.temporal.formula.parse_formula` and :func:`translate`.
    """
    if specification.kind != "ltl" or specification.formula is None:
        raise SpecError(f"a '{specification.kind}' specification has no formula to translate")
    return translate(parse_formula(specification.formula, specification.regions or {}), max_states)
