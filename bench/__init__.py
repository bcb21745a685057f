"""compabs's benchmarks: the paper's cases end to end, scalability in N, the baselines of the method's kernels, the
synthesis modes, the distributed runner's overhead and the trust campaign.

Run them from the repository root, with compabs installed (``pip install -e .``)::

    python bench/run.py [--quick] [--cases tanks,scp,...] [--json OUT]    # or: python -m bench ...
    python bench/synthesis.py [--N 8] [--rounds R] ...                    # or: python -m bench.synthesis ...
    python bench/runner.py [--stress K] [--overhead-only]                 # or: python -m bench.runner ...
    python bench/trust.py [--fast] [--json OUT]                           # or: python -m bench.trust ...

**Why no module edits ``sys.path``.** ``bench`` is a package of the repository root, not of the installed
distribution. ``python -m bench`` finds it because ``-m`` puts the working directory first on the module path;
``python bench/run.py`` puts ``bench/`` there instead, where ``import bench`` fails. So the scripts that import the
package (``run.py``, ``synthesis.py``, ``trust.py``) start themselves again as ``python -m bench...`` (``os.execv``:
the same interpreter, arguments and working directory) before they import any of it, and the children of a case
run as ``python -m bench --child KIND`` with the repository root as their working directory. ``runner.py`` imports
only the installed packages and runs as it is. No module here may be named like a package it or its dependencies
import (``workers``, ``pipelines``, ``service``, ``tests``): ``python bench/runner.py`` would import it instead.

**Modules.** :mod:`bench.suite` is the command line of ``run.py``: the cases in order, the table, the targets and
the JSON. :mod:`bench.harness` holds what the cases share: running and measuring a child process, the records,
the table's formatting. One module per case, each with ``run(args)`` (the parent side: the children it starts and
its record), ``lines(record)`` (its lines in the table), ``targets(record, put)`` and ``CHILDREN`` (what runs in
the child processes): :mod:`bench.end_to_end` (``tanks``, ``tanks_fine``, ``consensus``, through
:func:`workers.job.run_job`), :mod:`bench.scalability`, :mod:`bench.floor`, :mod:`bench.scp`,
:mod:`bench.two_workers` (the ``workers`` case), :mod:`bench.bdd`, :mod:`bench.general` and :mod:`bench.synthesis`
(its own command line too). The case modules import the harness and nothing of each other; the suite imports them
all: no import cycle (``tests/test_layout.py``).
"""
