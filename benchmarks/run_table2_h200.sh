#!/usr/bin/env bash
# Seed 003's Table 2 on one H200, in parts of under 10 minutes each
# (benchmarks/table2.py; every row in a worker process, OOM / timeout rows
# kept with their reason, the CSV rewritten after every row).
#
#   GIT_SHA=$(git rev-parse --short HEAD) bash benchmarks/run_table2_h200.sh PART
#
# PART: 1-4 = n = 50 000 with r=1, U[1,160], LN[1,330], r=160;
#       5-8 = n = 1 000 000, same order; "tests" = tests/test_fused.py;
#       "energy" = seed 003 §4.3's cases (Figs 11-12: lattice r=160,
#       disordered r=1, cluster LN; wall and periodic) at n = 50 000 with
#       --energy (NVML energy and power trace; CSV, *_power.csv and the two
#       figures); "energy-wall" / "energy-periodic": one boundary each, for
#       when the budget does not reach every row of "energy".
# Every part runs every method of table2.py (RT-REF, ORCS-forces,
# ORCS-persé, GPU-CELL, GPU-CELL-fused, CPU-CELL) unless METHODS names some.
# CSVs: $OUT/h200/table2_<part>_<sha>.csv (the device run's $OUT), else
# benchmarks/results/h200/. Rows the budget did not reach are "skipped":
# re-run them with --scenes/--methods/--boundaries (see table2.py --help).
# Environment: SCENES / BOUNDARIES (space-separated subsets, e.g.
# BOUNDARIES=periodic to finish a part whose wall rows ran; the CSV's name
# then names them), BUDGET (seconds before no new row starts, default 480),
# HARD_STOP (default 570), ROW_TIMEOUT (default 200), ENERGY_SECONDS
# (energy window per row, default 2), METHODS (space-separated, e.g.
# "GPU-CELL-fused ORCS-forces"; the CSV's name then names them),
# REPEATS / WARMUP (timed and untimed steps per row; parts 5-8 default to
# 1 and 1, the others to table2.py's 5 and 2),
# LIST_FORMAT (Dense, Sparse or OrderedSparse: the list methods' layout,
# default Dense; the CSV's name then names it),
# PYTHON.
set -uo pipefail
cd "$(dirname "$0")/.."
export XLA_PYTHON_CLIENT_PREALLOCATE=false
export GIT_SHA=${GIT_SHA:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
PY=${PYTHON:-python3}
PART=${1:?usage: run_table2_h200.sh PART (1-8, tests, energy[-wall|-periodic])}
if [[ $PART == tests ]]; then
  exec $PY -m pytest -q -n 0 tests/test_fused.py -m "slow or not slow"
fi
DEST=${OUT:+$OUT/h200}; DEST=${DEST:-benchmarks/results/h200}
# shellcheck disable=SC2206 # METHODS: words on purpose
MARGS=(${METHODS:+--methods $METHODS} ${LIST_FORMAT:+--list-format $LIST_FORMAT})
# shellcheck disable=SC2206 # SCENES, BOUNDARIES: words on purpose
SARGS=(${SCENES:+--scenes $SCENES} ${BOUNDARIES:+--boundaries $BOUNDARIES})
# The methods in the CSV's name, ASCII only (the device run returns no
# other file names).
MTAG=$(echo "${METHODS:+_$METHODS}${SCENES:+_$SCENES}${BOUNDARIES:+_$BOUNDARIES}${LIST_FORMAT:+_$LIST_FORMAT}" \
  | tr ' ' '-' | LC_ALL=C tr -cd 'A-Za-z0-9_-')
if [[ $PART == energy || $PART == energy-wall || $PART == energy-periodic ]]; then
  BCS="wall periodic"; [[ $PART != energy ]] && BCS=${PART#energy-}
  mkdir -p "$DEST"
  # shellcheck disable=SC2086 # BCS, SCENES: words on purpose
  exec $PY benchmarks/table2.py --n 50000 --cases paper-energy --energy \
    --boundaries $BCS --energy-seconds "${ENERGY_SECONDS:-2}" "${MARGS[@]}" \
    ${SCENES:+--scenes $SCENES} \
    --budget "${BUDGET:-480}" --hard-stop "${HARD_STOP:-570}" \
    --timeout "${ROW_TIMEOUT:-200}" \
    --out "$DEST/table2_${PART}${MTAG}_${GIT_SHA}.csv"
fi
RADII=("r=1" "U[1,160]" "LN[1,330]" "r=160")
[[ $PART =~ ^[1-8]$ ]] || { echo "PART must be 1-8, tests or energy[-wall|-periodic]"; exit 2; }
N=$(( PART <= 4 ? 50000 : 1000000 ))
R=${RADII[$(( (PART - 1) % 4 ))]}
TAG=$(echo "${N}_${R}" | tr -d '[]=,' )
mkdir -p "$DEST"
# At n = 10^6 the paper's steps take up to 79 s (cluster, ORCS-persé): one
# untimed and one timed step there (a fast row still takes as many as
# table2.py's --target-s asks for); parts 1-4 keep table2.py's 5 and 2.
if (( PART >= 5 )); then
  REPS=(--repeats "${REPEATS:-1}" --warmup "${WARMUP:-1}")
else
  REPS=(${REPEATS:+--repeats $REPEATS} ${WARMUP:+--warmup $WARMUP})
fi
$PY benchmarks/table2.py --n "$N" --radii "$R" "${MARGS[@]}" "${SARGS[@]}" "${REPS[@]}" \
  --budget "${BUDGET:-480}" --hard-stop "${HARD_STOP:-570}" \
  --timeout "${ROW_TIMEOUT:-200}" --out "$DEST/table2_${TAG}${MTAG}_${GIT_SHA}.csv"
