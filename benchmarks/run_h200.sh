#!/usr/bin/env bash
# The H200 "no regression" run of issue #15's refactor, in ONE invocation of
# about 7 minutes on one H200 (benchmarks/RESULTS.md, "Current numbers"):
#   1. the cell list's rebuild, uniform rho = 1, rc = 2.5, N = 1e6, Dense:
#      cell[pallas] (the GPU kernel), cell[xla], bvh, jax-md   (neighbors.py)
#   2. the LJ MD step at N = 1e6: jax-md's default (OrderedSparse) and
#      Dense, jaxrt cell and bvh on Dense, the list-free fused cell (md_step.py)
#   3. the unit-sphere surface at N = 1e6 (k ~ 30, the seed's box 2 + 2C),
#      the same four methods                                   (neighbors.py)
#   4. the bvh rebuild and refit through jax.jit against Warp's HashGrid,
#      uniform N = 1e6                                         (rt_neighbors.py)
# then a compact table of the four CSVs. Every row runs in its own worker
# process (benchmarks/_harness.py): a row that runs out of memory or time
# is written with its status and the run goes on. Each part has a deadline
# (seconds since the start; time a part leaves unused goes to the next): no
# new row starts within 15 s of it, a row running at it is killed.
#
#   GIT_SHA=$(git rev-parse --short HEAD) bash benchmarks/run_h200.sh
#       CSVs under $OUT/h200/ (the device run's $OUT), else
#       benchmarks/results/h200/, named <part>_<sha>.csv
#   bash benchmarks/run_h200.sh --quick     # or QUICK=1: CPU smoke, N = 2000,
#       CSVs under $OUT/quick/, else /tmp/jaxrt-bench-quick/
# Environment: BUDGET (seconds, default 420; 900 with --quick) scales the
# deadlines; PYTHON (default python3).
set -uo pipefail
cd "$(dirname "$0")/.."
QUICK=${QUICK:-0}
[[ "${1:-}" == "--quick" ]] && QUICK=1
BUDGET=${BUDGET:-$([[ $QUICK == 1 ]] && echo 900 || echo 420)}
export XLA_PYTHON_CLIENT_PREALLOCATE=false
export GIT_SHA=${GIT_SHA:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
PY=${PYTHON:-python3}

if [[ $QUICK == 1 ]]; then
  DEST=${OUT:+$OUT/quick}; DEST=${DEST:-/tmp/jaxrt-bench-quick}
  N=2000; MD_N=1000; TAG=quick; CELL=(cell "cell[xla]")
  NB_REPS=(--repeats 3 --warmup 2); MD_REPS=(--repeats 2 --warmup 1 --steps 5)
else
  DEST=${OUT:+$OUT/h200}; DEST=${DEST:-benchmarks/results/h200}
  N=1000000; MD_N=1000000; TAG=1e6; CELL=("cell[pallas]" "cell[xla]")
  NB_REPS=(--repeats 10 --warmup 2); MD_REPS=(--repeats 5 --warmup 2 --steps 20)
fi
mkdir -p "$DEST"
echo "run_h200.sh: git $GIT_SHA, quick=$QUICK, budget ${BUDGET}s, CSVs in $DEST"

# part DEADLINE_PERCENT CSV_NAME SCRIPT ARGS...: run SCRIPT until the
# deadline (a share of BUDGET, counted from the start of this script).
FILES=()
part() {
  local deadline=$(( BUDGET * $1 / 100 )) name=$2 script=$3
  shift 3
  local left=$(( deadline - SECONDS ))
  local csv="$DEST/${name}_${GIT_SHA}.csv"
  FILES+=("$csv")
  echo; echo "== [$SECONDS s] $script -> $csv (until ${deadline}s)"
  if (( left < 20 )); then
    echo "   no time left: skipped"; return
  fi
  # timeout: a last resort if the driver itself hung (the harness kills its
  # rows at --hard-stop; the CSV is rewritten after every row).
  timeout $(( left + 60 )) "$PY" "$script" "$@" --timeout 150 \
    --budget $(( left - 15 )) --hard-stop "$left" --out "$csv"
  echo "   exit $?"
}

part 28 "neighbors_uniform_$TAG" benchmarks/neighbors.py --scenes uniform \
  --sizes "$N" --backends "${CELL[@]}" bvh "${NB_REPS[@]}"
part 58 "md_step_lj_$TAG" benchmarks/md_step.py --systems lj --n "$MD_N" \
  --only jax-md/OrderedSparse jax-md/Dense jaxrt:cell/Dense jaxrt:bvh/Dense \
  fused:cell \
  "${MD_REPS[@]}"
part 80 "neighbors_sphere_$TAG" benchmarks/neighbors.py --scenes sphere \
  --sphere-n "$N" --backends "${CELL[@]}" bvh "${NB_REPS[@]}"
part 97 "rt_neighbors_uniform_$TAG" benchmarks/rt_neighbors.py \
  --scenes uniform --sizes "$N" "${NB_REPS[@]}" --only \
  "bvh jit Dense (rebuild)" "bvh jit Dense (refit)" \
  "warp HashGrid build" "warp HashGrid query Dense"

echo; echo "== [$SECONDS s] summary"
"$PY" benchmarks/_harness.py --summary "${FILES[@]}"
echo "total ${SECONDS}s"
