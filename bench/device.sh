#!/usr/bin/env bash
# Issues 24's and 49's measurement on a lent 16-core machine in one device call (docs/benchmarks.md, "On 16 cores"):
# consensus synthesis in one CUDD process against Dask with 16 and 2 workers and oxidd on 1 and 16 threads, the same
# domain, each call's parts timed (parallel.per_call says when the last part of a call began and why a call waited).
#
#   here, once:      bash bench/device.sh prepare
#                    fills .whl/ with ../shared/tools/device-wheels.sh and keeps what bench/synthesis.py needs
#                    (about 27 MB; a device call carries at most 64 MiB)
#   on the device:   the `run` tool with command "bash bench/device.sh measure", carry [".whl"], timeout_s 480
#                    (N = 7: about 4 minutes there; N, WORKERS, PER_WORKER and PARALLEL_AFTER override the defaults)
#
# The results come back as $OUT/synthesis.json. Quote the ratios of one run, never a time from one machine against
# a time from another.
#
# An A/B of two commits on one machine (lent machines differ by up to 1.6x for the same code, so two leases'
# ratios do not separate a change from the machine):
#   here, once:      bash bench/device.sh prepare-ab REV      (REV's tree into .ab/, about 3 MB; carry it with .whl)
#   on the device:   command "bash bench/device.sh measure-ab", carry [".whl", ".ab"], timeout_s 580
#                    (N = 6 by default: REV and this tree in turn, ROUNDS times (default 2), each one process and
#                    WORKERS (default 16) workers; results $OUT/ab-REV-k.json and $OUT/ab-this-k.json)
set -euo pipefail
cd "$(dirname "$0")/.."

# On the device: the carried wheels into /tmp/site (it cannot download), and what the machine is.
install_wheels() {
  if ! ls .whl/*.whl > /dev/null 2>&1; then
    echo "error: no .whl/ here: run 'bash bench/device.sh prepare' on the development machine and carry .whl" >&2
    exit 2
  fi
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
  export PYTHONUNBUFFERED=1
  lscpu | grep -E '^CPU\(s\)|per core|Model name' || true
}

case "${1:-}" in
  prepare)
    bash ../shared/tools/device-wheels.sh
    # not imported by bench/synthesis.py (the API, the convex programs, the figures), or already on the machine
    (cd .whl && rm -f scs-* scipy-* sparsediffpy-* pillow-* bokeh-* sqlalchemy-* cvxpy-* clarabel-* osqp-* qdldl-* \
      highspy-* fastapi* starlette-* uvicorn-* python_multipart-* narwhals-* xyzservices-* networkx-* jinja2-* \
      markupsafe-* h11-* anyio-* idna-* annotated_doc-*)
    du -sh .whl
    ;;
  measure)
    install_wheels
    export PYTHONPATH=/tmp/site:$PWD
    python3 bench/synthesis.py --N "${N:-7}" --workers "${WORKERS:-16,2}" --per-worker "${PER_WORKER:-1}" \
      --processes 1 --parallel-after "${PARALLEL_AFTER:-1}" --json "${OUT:-/tmp}/synthesis.json"
    ;;
  prepare-ab)
    rev="${2:?usage: bash bench/device.sh prepare-ab REV}"
    rm -rf .ab && mkdir .ab
    git archive "$rev" | tar -x -C .ab
    git rev-parse --short "$rev" > .ab/REV
    du -sh .ab
    ;;
  measure-ab)
    if [ ! -f .ab/REV ]; then
      echo "error: no .ab/ here: run 'bash bench/device.sh prepare-ab REV' on the development machine and carry .ab" >&2
      exit 2
    fi
    install_wheels
    rev="$(cat .ab/REV)"
    for k in $(seq "${ROUNDS:-2}"); do
      for side in "$rev" this; do
        if [ "$side" = this ]; then tree="$PWD"; else tree="$PWD/.ab"; fi
        echo "== round $k: $side"
        (cd "$tree" && PYTHONPATH="/tmp/site:$tree" python3 bench/synthesis.py --N "${N:-6}" \
          --workers "${WORKERS:-16}" --processes 1 --json "${OUT:-/tmp}/ab-$side-$k.json")
      done
    done
    ;;
  *)
    echo "usage: bash bench/device.sh prepare|measure|prepare-ab REV|measure-ab" >&2
    exit 2
    ;;
esac
