#!/usr/bin/env bash
# One device call: the Warp engine's tests on the GPU first (kernels are
# tested where they run), then the timings that use what time is left,
# each step bounded by `timeout` so that the call ends inside the device's
# limit (the bounds add up to 560 s at scale 1). CSVs and logs go to $OUT. Run after `.gpu/p2/boot.sh install`
# with PYTHONPATH and GIT_SHA set; the first argument scales every bound.
set -u
o=$OUT
scale=${1:-1}
t() { local s=$1; shift; timeout "$(python3 -c "print(int($s * $scale))")" "$@"; }
t 130 python3 -m pytest -q -p no:cacheprovider -n 4 -x \
  tests/energy/test_fused_warp.py tests/energy/test_fused_warp_cluster.py \
  tests/lists/test_warp_rows.py tests/energy/test_sph_fused_warp.py \
  tests/backends/test_warp_grid.py > $o/tests.txt 2>&1
tail -6 $o/tests.txt
t 110 python3 benchmarks/md_step.py --n 1000000 --systems lj --steps 20 \
  --repeats 5 --warmup 2 --timeout 40 --only "fused:cell[pallas]" \
  "fused:cell[warp]" "fused:cell[warp-r11-c8]" "fused:cell[warp-r21-c8]" \
  "fused:cell[warp-r11-n8]" "fused:cell[warp-r21-n8]" \
  --out $o/md_step_lj_1e6.csv > $o/md.log 2>&1
tail -9 $o/md.log
t 60 python3 benchmarks/neighbors.py --sizes 1000000 --scenes uniform \
  --no-jax-md --timeout 40 --backends "cell[warp]" "cell[pallas]" \
  --out $o/neighbors_uniform_1e6.csv > $o/nb.log 2>&1
tail -4 $o/nb.log
t 60 python3 benchmarks/sph_step.py --n 100000 --dim 3 --repeats 5 \
  --timeout 40 --only list:cell/Dense "fused:cell[pallas]" \
  "fused:cell[warp]" --out $o/sph_step_3d_1e5.csv > $o/sph.log 2>&1
tail -6 $o/sph.log
t 50 python3 benchmarks/pairs.py --gpu --sizes 1000 1000000 --batches 256x32 \
  --timeout 40 --out $o/pairs_gpu.csv > $o/pairs.log 2>&1
tail -10 $o/pairs.log
# The Dense list step at 1e6 and 1e7 with the particles numbered x-major
# (md_step's lattice), shuffled, and along a Hilbert curve: does the list
# step's growth from 1e6 to 1e7 follow the numbering's memory locality?
t 50 python3 benchmarks/md_step.py --n 1000000 --systems lj --steps 10 \
  --repeats 3 --warmup 1 --timeout 25 --only jaxrt:cell/Dense \
  --order lattice random hilbert --out $o/md_step_order_1e6.csv > $o/order6.log 2>&1
tail -5 $o/order6.log
t 100 python3 benchmarks/md_step.py --n 10000000 --systems lj --steps 10 \
  --repeats 3 --warmup 1 --timeout 45 --only jaxrt:cell/Dense \
  --order lattice random hilbert --out $o/md_step_order_1e7.csv > $o/order7.log 2>&1
tail -5 $o/order7.log
