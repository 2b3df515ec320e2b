#!/usr/bin/env bash
# Seed 003's Table 2 on one H200, in parts of under 10 minutes each
# (benchmarks/table2.py; every row in a worker process, OOM / timeout rows
# kept with their reason, the CSV rewritten after every row).
#
#   GIT_SHA=$(git rev-parse --short HEAD) bash benchmarks/run_table2_h200.sh PART
#
# PART: 1-4 = n = 50 000 with r=1, U[1,160], LN[1,330], r=160;
#       5-8 = n = 1 000 000, same order; "tests" = tests/test_fused.py.
# CSVs: $OUT/h200/table2_<part>_<sha>.csv (the device run's $OUT), else
# benchmarks/results/h200/. Rows the budget did not reach are "skipped":
# re-run them with --scenes/--methods/--boundaries (see table2.py --help).
# Environment: BUDGET (seconds before no new row starts, default 480),
# HARD_STOP (default 570), ROW_TIMEOUT (default 200), PYTHON.
set -uo pipefail
cd "$(dirname "$0")/.."
export XLA_PYTHON_CLIENT_PREALLOCATE=false
export GIT_SHA=${GIT_SHA:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
PY=${PYTHON:-python3}
PART=${1:?usage: run_table2_h200.sh PART (1-8 or tests)}
if [[ $PART == tests ]]; then
  exec $PY -m pytest -q -n 0 tests/test_fused.py -m "slow or not slow"
fi
RADII=("r=1" "U[1,160]" "LN[1,330]" "r=160")
(( PART >= 1 && PART <= 8 )) || { echo "PART must be 1-8 or tests"; exit 2; }
N=$(( PART <= 4 ? 50000 : 1000000 ))
R=${RADII[$(( (PART - 1) % 4 ))]}
TAG=$(echo "${N}_${R}" | tr -d '[]=,' )
DEST=${OUT:+$OUT/h200}; DEST=${DEST:-benchmarks/results/h200}
mkdir -p "$DEST"
$PY benchmarks/table2.py --n "$N" --radii "$R" \
  --budget "${BUDGET:-480}" --hard-stop "${HARD_STOP:-570}" \
  --timeout "${ROW_TIMEOUT:-200}" --out "$DEST/table2_${TAG}_${GIT_SHA}.csv"
