"""``python bench/run.py``: the benchmark's command line (:mod:`bench.suite` says what it runs and how).

Run from the repository root. As a script this file starts itself again as ``python -m bench`` (the same
interpreter, arguments and working directory), where ``bench`` is importable as the package it is; bench/__init__.py
says why that and not an edit of ``sys.path``.
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__":
    if not __package__:  # `python bench/run.py`
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        if not os.path.samefile(os.getcwd(), root):
            sys.exit(f"bench/run.py: run it from the repository root ({root}), or as python -m bench")
        os.execv(sys.executable, [sys.executable, "-m", "bench", *sys.argv[1:]])
    from bench.suite import main  # `python -m bench.run`

    sys.exit(main())
