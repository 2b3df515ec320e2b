#!/usr/bin/env bash
# The H100 benchmark session behind benchmarks/results/h100/ (RESULTS.md).
# Each part fits one 10-minute command of the lent GPU machine; results go
# under $OUT (default benchmarks/results/h100). Run from the repository root
# after bringing Warp and jax-md (../shared/gpu/README.md):
#   bash benchmarks/run_h100.sh seed     # seed 001 §5 study (~9 min)
#   bash benchmarks/run_h100.sh lists    # lists, RT sweep, MD steps (~7 min)
#   bash benchmarks/run_h100.sh cell     # cell list vs jax-md and bvh (~8 min)
set -uo pipefail
OUT=${OUT:-benchmarks/results/h100}
export XLA_PYTHON_CLIENT_PREALLOCATE=false
mkdir -p "$OUT"
case "${1:-}" in
  seed)
    OUT=$OUT/seed_rt python benchmarks/seed_rt_study.py \
      --time-budget 420 --hard-stop 460 --timeout 100 ;;
  lists)
    timeout 130 python benchmarks/neighbors.py --sizes 100000 1000000 \
      --sphere-n 10000 --backends cell bvh --repeats 10 --out "$OUT"
    OUT=$OUT timeout 140 python benchmarks/rt_neighbors.py --sizes 1000000 \
      --repeats 10 --jit-clusters 8
    setups=(jax-md/OrderedSparse jax-md/Dense "jax-md list + jaxrt energy/Dense"
            jaxrt:bvh/Dense jaxrt:bvh/OrderedSparse jaxrt:cell/Dense
            jaxrt:squares/Dense jaxrt:cell/OrderedSparse)
    for n in 1000000 100000; do
      timeout 150 python benchmarks/md_step.py --n $n --repeats 5 --steps 20 \
        --only "${setups[@]}" --out "$OUT/md_step_$n.csv"
    done ;;
  cell)
    timeout 420 python benchmarks/neighbors.py --sizes 100000 1000000 \
      --sphere-n 10000 --backends cell cell:xla bvh --repeats 10 \
      --timeout 120 --out "$OUT"
    timeout 150 python benchmarks/md_step.py --n 1000000 --repeats 5 \
      --steps 20 --only jax-md/Dense jaxrt:cell/Dense jaxrt:bvh/Dense \
      --out "$OUT/md_step_cell_1e6.csv" ;;
  *) echo "usage: run_h100.sh seed|lists|cell" >&2; exit 2 ;;
esac
