#!/usr/bin/env bash
# Seed 003's Figure 8 on one H200 at n = 140 000, periodic, in three parts
# of under 8 minutes each (benchmarks/figure8.py; each scene in a worker,
# stopped after its steps or SCENE_SECONDS of wall time, whichever comes first).
#
#   GIT_SHA=$(git rev-parse --short HEAD) bash benchmarks/run_figure8_h200.sh PART
#
# PART: A = r=160 (Lattice, Disordered; Cluster is refused as a list),
#       B = LN[1,330] (all three scenes; Cluster refused),
#       C = U[1,160] (all three; Cluster refused), then r = 1 (all three,
#           2000 steps);
#       merge DIR... = join the parts' folders (on any machine) into
#           benchmarks/results/h200/figure8_140k_<sha>/ (or $DEST).
# Large radii run 300 steps (STEPS), r = 1 2000. Output of a part:
# $OUT/figure8_<part>/ (the device run's $OUT), else /tmp/figure8_<part>/.
# Environment: STEPS, SCENE_SECONDS (wall cap per scene: A 200, B 200,
# C 120), PYTHON.
set -uo pipefail
cd "$(dirname "$0")/.."
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
export GIT_SHA=${GIT_SHA:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
PY=${PYTHON:-python3}
PART=${1:?usage: run_figure8_h200.sh A|B|C|merge DIR...}
if [[ $PART == merge ]]; then
  shift
  DEST=${DEST:-benchmarks/results/h200/figure8_140k_${GIT_SHA}}
  exec $PY benchmarks/figure8.py --merge "$@" --out "$DEST"
fi
ROOT=${OUT:-/tmp}
STEP_ARGS=(${STEPS:+--steps $STEPS})
run() {  # folder, wall cap per scene, radii...
  local dir=$ROOT/figure8_$1 cap=$2
  shift 2
  mkdir -p "$dir"
  $PY benchmarks/figure8.py --n 140000 --radii "$@" "${STEP_ARGS[@]}" \
    --seconds "$cap" --hard-stop 560 --out "$dir"
}
case $PART in
  A) run A "${SCENE_SECONDS:-200}" "r=160" ;;
  B) run B "${SCENE_SECONDS:-200}" "LN[1,330]" ;;
  C) run C "${SCENE_SECONDS:-120}" "U[1,160]" "r=1" ;;
  *) echo "PART must be A, B, C or merge"; exit 2 ;;
esac
