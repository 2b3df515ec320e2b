#!/usr/bin/env bash
# Seed 004 on one H200: the Delaunay backend's Warp engine against its XLA
# engine, jaxrt's cell list and jax-md (benchmarks/delaunay.py), Boids and
# random walks, k = 8 and 64, per-step update time with maintenance.
#
#   GIT_SHA=$(git rev-parse --short HEAD) bash benchmarks/run_delaunay_h200.sh MODE
#
# MODE: tests       the Warp engine's tests on the GPU
#                   (tests/backends/test_delaunay_warp.py) and the XLA
#                   engine's tests
#       1e4, 1e5    N = 10^4 / 10^5, all four methods, both motions
#       1e6-boids   N = 10^6, Boids: warp engine, cell, jax-md (the XLA
#                   engine did not finish 10^6 inside a 10-minute call)
#       1e6-random  N = 10^6, random walk: the same methods
#       1e6         N = 10^6, both motions, k = 8 first (then 64): the
#                   rows in the order of their worth when the time is short
#       smoke       N = 400, every method, 3 steps: the pipeline end to end
# Each mode stays under ~9 minutes (--hard-stop). CSV:
# benchmarks/results/<device>/ by default, or $OUT/delaunay_<mode>/ when $OUT
# is set (the device run's output folder). Environment: STEPS, REPEATS,
# PYTHON, METHODS (overrides the methods), NEIGHBOURS (default "8 64"),
# HARD_STOP (seconds, default 540), SIZES (overrides N: a CPU check of a
# mode end to end, e.g. SIZES=500) and REUSE=1 (one worker for the rows
# while they succeed: its start-up is paid once).
set -uo pipefail
cd "$(dirname "$0")/.."
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
export GIT_SHA=${GIT_SHA:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
PY=${PYTHON:-python3}
MODE=${1:?usage: run_delaunay_h200.sh tests|smoke|1e4|1e5|1e6|1e6-boids|1e6-random}
ALL=(delaunay "delaunay[engine=warp]" cell jax-md)
BIG=("delaunay[engine=warp]" cell jax-md)
run() {  # name, sizes, motions, timeout per row, methods...
  local name=$1 sizes=$2 motions=$3 row_timeout=$4
  shift 4
  local methods=("$@")
  if [[ -n ${METHODS:-} ]]; then read -r -a methods <<< "$METHODS"; fi
  local out=()
  if [[ -n ${OUT:-} ]]; then out=(--out "$OUT/delaunay_$name"); fi
  $PY benchmarks/delaunay.py --name "delaunay_$name.csv" --sizes ${SIZES:-$sizes} \
    --motions $motions --neighbours ${NEIGHBOURS:-8 64} \
    --methods "${methods[@]}" \
    --steps "${STEPS:-20}" --repeats "${REPEATS:-5}" \
    --timeout "$row_timeout" --hard-stop "${HARD_STOP:-540}" "${out[@]}" \
    ${REUSE:+--reuse-worker}
}
case $MODE in
  tests)
    $PY -m pytest -q -n 0 -p no:cacheprovider \
      tests/backends/test_delaunay_warp.py tests/backends/test_delaunay.py ;;
  1e4) run 1e4 10000 "boids random" 240 "${ALL[@]}" ;;
  1e5) run 1e5 100000 "boids random" 240 "${ALL[@]}" ;;
  1e6-boids) run 1e6_boids 1000000 boids 400 "${BIG[@]}" ;;
  1e6-random) run 1e6_random 1000000 random 400 "${BIG[@]}" ;;
  1e6) run 1e6 1000000 "boids random" 400 "${BIG[@]}" ;;
  smoke)
    $PY benchmarks/delaunay.py --smoke --name delaunay_smoke.csv \
      --out "${OUT:-/tmp}/delaunay_smoke" ;;
  *) echo "unknown mode $MODE" >&2; exit 2 ;;
esac
