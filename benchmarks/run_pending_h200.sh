#!/usr/bin/env bash
# What the H200 has not run yet of the code as it stands (each PART well
# inside one 10-minute device call; benchmarks/RESULTS.md says which rows
# they fill in):
#   tests     the compiled kernels changed since their last GPU test: seed
#             001's fused Warp kernels (tests/test_seed_fused.py), the
#             spheres/squares list kernels that gained the fused branch, the
#             fused cell kernel's launch options (tiles, unroll, across),
#             the squares ulp case xfailed on the GPU only
#   sph       list-free SPH (the cell kernel) against SPH on lists, side by
#             side: 2D N = 10^6 and 3D N = 10^5 (#18's 2x target)
#   accuracy  the accuracy sweep's settings the H200 has not measured:
#             pairs, spheres-epsilon, list-free (fused-pallas), N = 16 384
# Table 2 and its energy figures: benchmarks/run_table2_h200.sh; seed 001's
# study: benchmarks/seed_rt_study.py --part K/6 (RESULTS.md).
#
#   GIT_SHA=$(git rev-parse --short HEAD) bash benchmarks/run_pending_h200.sh PART
#
# Everything goes under $OUT/pending_<PART>/ (else
# benchmarks/results/h200/pending_<PART>/) and, on the device machine, into
# one tarball $OUT/pending_<PART>.tgz (a call brings back at most 8 files).
set -uo pipefail
cd "$(dirname "$0")/.."
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
export GIT_SHA=${GIT_SHA:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
PY=${PYTHON:-python3}
PART=${1:?usage: run_pending_h200.sh tests|sph|accuracy}
DEST=${OUT:+$OUT/pending_$PART}; DEST=${DEST:-benchmarks/results/h200/pending_$PART}
mkdir -p "$DEST/logs"
[[ -n ${OUT:-} ]] && trap 'tar czf "$OUT/pending_$PART.tgz" -C "$DEST" .' EXIT
START=$SECONDS
note() { echo "$1 [$(( SECONDS - START )) s]" | tee -a "$DEST/logs/summary.txt"; }
tests() {  # name timeout pytest-args...
  local name=$1 limit=$2; shift 2
  timeout "$limit" "$PY" -m pytest -q -n 0 -p no:cacheprovider "$@" \
    > "$DEST/logs/$name.log" 2>&1
  note "$name rc=$? $(tail -1 "$DEST/logs/$name.log")"
}
case $PART in
  tests)
    tests seed_fused 200 tests/test_seed_fused.py
    tests spheres_squares 150 tests/test_rt_spheres_squares.py -x
    tests fused_launches 120 tests/test_fused.py -m "slow or not slow" \
      -k "fine or tiles"
    tests cutoff_ulp 60 tests/stability/test_cutoff_ulp.py \
      -m "slow or not slow" -k squares ;;
  sph)
    timeout 280 "$PY" benchmarks/sph_step.py --n 1000000 --repeats 5 \
      --timeout 90 --budget 240 --only list:cell/Dense \
      list:cell/OrderedSparse "fused:cell[xla]" "fused:cell[pallas]" \
      --out "$DEST/sph_step_2d_1e6_$GIT_SHA.csv" > "$DEST/logs/sph_2d.log" 2>&1
    note "sph 2d rc=$?"
    timeout 250 "$PY" benchmarks/sph_step.py --n 100000 --dim 3 --repeats 5 \
      --timeout 90 --budget 210 --only list:cell/Dense \
      list:cell/OrderedSparse "fused:cell[pallas]" \
      --out "$DEST/sph_step_3d_1e5_$GIT_SHA.csv" > "$DEST/logs/sph_3d.log" 2>&1
    note "sph 3d rc=$?" ;;
  accuracy)
    timeout 540 "$PY" -m jaxrt accuracy --quick --n 16384 --steps 2000 \
      --budget 480 --knobs list-free,pairs,spheres-epsilon \
      --out "$DEST/accuracy_lj_$GIT_SHA" > "$DEST/logs/accuracy.log" 2>&1
    note "accuracy rc=$?" ;;
  *) echo "PART must be tests, sph or accuracy"; exit 2 ;;
esac
