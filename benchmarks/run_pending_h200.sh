#!/usr/bin/env bash
# What the H200 has not run yet of the code as it stands (each PART well
# inside one 10-minute device call; benchmarks/RESULTS.md says which rows
# they fill in):
#   tests     the compiled tests of the cell kernels and the Warp calls,
#             group after group, each with pytest-xdist workers (compiling
#             is CPU-bound): test_fused.py (all), the list kernel and the
#             periodic axes compacted across empty slabs, list-free SPH,
#             then bvh, policy, seed 001's fused kernels and the spheres /
#             squares
#   runs      #18's kernels: test_fused.py and test_periodic_gaps.py
#             compiled, then the LJ step and the roofline of the runs found
#             in the cell-start table, with newton (n), finer cells across
#             (a2), and stored runs (s)
#   step      #18's LJ step side by side (fused cell, jaxrt cell/Dense,
#             jax-md Dense), the roofline with the fused step's halves, and
#             the grid's stages (benchmarks/grid_stages.py)
#   profile   Nsight Compute on the two cell kernels (occupancy, issue
#             slots, stall reasons), if ncu is on the machine
#   overhead  where a Table 2 step's host time goes (step_overhead.py), then
#             Table 2 part 1 again (now with GPU-CELL-fused): does the fix
#             of the Warp calls' fixed cost hold on the GPU?
#   sph       list-free SPH (the cell kernel) against SPH on lists, side by
#             side: 2D N = 10^6 and 3D N = 10^5 (#18's 2x target); owed
#             since f6dc44e (SPH's barrier in reverse mode only: the
#             OrderedSparse rows at 0d9699f had it forward too)
#   radii     the radius classes (refusal at allocate, packed rows) on the
#             GPU: tests/test_radii.py (slow included), the radius tests
#             of the other files, then test_fused.py whole with a per-test
#             JUnit report (the runs part's 200 s did not reach its tail)
#   accuracy  the accuracy sweep's knobs last added to the H200 runs
#             (pairs, spheres-epsilon, list-free), N = 16 384; all ran at
#             e898c00, pairs owes a re-run that records missed_depth_ulps
#   owed      the tests of the edges written out before their scatters
#             (jaxrt.pairs, LJ, SPH; LJ and SPH passed at b9da909, but
#             tests/test_pairs.py skips itself where ASE is missing, as on
#             the staged GPU machine), then the accuracy sweep's format and
#             pairs knobs (ran at 0d9699f)
#   stability #21's suite compiled (tests/stability: the cell kernel and the
#             Warp calls where CI runs their portable or CPU paths), fast
#             part then slow part, after the edge tests that owed runs
#             (jaxrt.pairs and jax-md's acceptance tests need .gpu/extra)
#   layouts   #18's layouts target: the edge kernel (jaxrt/_edge_kernel.py)
#             and OrderedSparse's half rows compiled, the updates at
#             N = 10^6 side by side, the LJ step on every layout against
#             jax-md's default (ran at 6e87170 on Dense and OrderedSparse
#             alone: md_step.py took no Sparse setups then)
#   formats   where a list step's time goes per layout (list_forces.py:
#             update, Dense-to-Sparse conversion both ways, the energy
#             alone, the forces by reverse mode and with the scatter written
#             out, the edge reductions four ways) at #18's N = 10^6, k = 52,
#             then seed 003's r = 160 density (N = 50 000, k = 700), whose
#             OrderedSparse rows did not fit in 4f8087d's call
#   alloc     allocate's reuse of its compiled build (0ad79c5) on the GPU:
#             the list kernel's tests and tests/test_neighbors.py, then
#             benchmarks/neighbors.py at N = 10^6 with its reallocate_ms
#             column (uniform: cell, bvh, jax-md), then allocate's stages
#             at 2.1e6 sphere points (benchmarks/allocate_parts.py)
#   seed-rest seed 001's study: 16 of the 17 configurations that parts
#             1-4 at 497bb8b did not reach (sphere alpha = 128, p = 4 only
#             for cell and jax-md), smallest first; merge them with
#             --plot-only (RESULTS.md)
#   seed-big  the same study's largest rows: sphere alpha = 128, p = 16
#             (fused methods only; ran at 9db10e6) and part 5
#             (spheres-fused at N = 67M)
#   model     allocate's model check sorting on the GPU and lists past 2^26
#             entries rounded where the GPU has room (session 19): their
#             tests and test_neighbors.py, then allocate's stages at 2.1e6
#             sphere points (the check took 1.15-1.21 s at 9db10e6, cell's
#             build a 0.8 s compile per structure) and reallocate_ms at
#             10^6 uniform (cell 1 968 ms, jax-md 1 299 at 9db10e6)
#   table2-6p Table 2 part 6's periodic rows (U[1,160], n = 10^6; the
#             walled ones ran at 9db10e6), the cluster's Warp rows left
#             out (they timed out at 120 s with walls)
# Table 2 and its energy figures: benchmarks/run_table2_h200.sh; seed 001's
# study: benchmarks/seed_rt_study.py --part K/5 (RESULTS.md).
#
#   GIT_SHA=$(git rev-parse --short HEAD) bash benchmarks/run_pending_h200.sh PART
#
# (with carry [".gpu/p2", ".gpu/extra"] for the parts whose tests need ASE
# or netCDF4: benchmarks/gpu_extras.sh)
#
# Everything goes under $OUT/pending_<PART>/ (else
# benchmarks/results/h200/pending_<PART>/) and, on the device machine, into
# one tarball $OUT/pending_<PART>.tgz (a call brings back at most 8 files).
set -uo pipefail
cd "$(dirname "$0")/.."
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
export GIT_SHA=${GIT_SHA:-$(git rev-parse --short HEAD 2>/dev/null || echo unknown)}
PY=${PYTHON:-python3}
PART=${1:?usage: run_pending_h200.sh tests|radii|runs|step|profile|overhead|sph|accuracy|owed|stability|layouts|formats|alloc|seed-rest|seed-big|model|table2-6p}
DEST=${OUT:+$OUT/pending_$PART}; DEST=${DEST:-benchmarks/results/h200/pending_$PART}
mkdir -p "$DEST/logs"
[[ -n ${OUT:-} ]] && trap 'tar czf "$OUT/pending_$PART.tgz" -C "$DEST" .' EXIT
# Test-only wheels carried as .gpu/extra (benchmarks/gpu_extras.sh): ASE for
# tests/test_pairs.py, netCDF4 for tests/test_jax_md_acceptance.py.
if compgen -G ".gpu/extra/*.whl" > /dev/null; then
  "$PY" -m pip install -q --no-deps --no-index --target /tmp/site \
    .gpu/extra/*.whl > "$DEST/logs/extras.log" 2>&1
fi
START=$SECONDS
note() { echo "$1 [$(( SECONDS - START )) s]" | tee -a "$DEST/logs/summary.txt"; }
tests() {  # name timeout pytest-args...
  # Workers in parallel on the one GPU: compiling is CPU-bound (16 cores),
  # and test_fused.py took 85 s with -n 6 against over 250 s with -n 0.
  local name=$1 limit=$2; shift 2
  timeout "$limit" "$PY" -m pytest -q -n "${WORKERS:-6}" -p no:cacheprovider \
    -rfE --junitxml="$DEST/logs/$name.xml" "$@" > "$DEST/logs/$name.log" 2>&1
  note "$name rc=$? $(tail -1 "$DEST/logs/$name.log")"
}
case $PART in
  tests)
    tests cell 240 tests/test_fused.py -m "slow or not slow"
    tests list_kernel 200 tests/test_cell_kernel.py tests/test_neighbors.py \
      tests/test_periodic_gaps.py -m "slow or not slow"
    tests sph 150 tests/test_sph_fused.py -m "slow or not slow"
    tests warp 200 tests/test_bvh.py tests/test_policy.py \
      tests/test_seed_fused.py tests/test_rt_spheres_squares.py ;;
  radii)
    tests radii 170 tests/test_radii.py -m "slow or not slow"
    # 90 s reached 16 of these at e898c00
    tests radius_elsewhere 150 tests/test_periodic_gaps.py tests/test_accuracy.py \
      tests/test_fused.py tests/test_neighbors.py -m "slow or not slow" \
      -k "radi or radius"
    tests fused 180 tests/test_fused.py -m "slow or not slow" ;;
  runs)  # #18: runs found in the cell-start table, newton, finer cells
    tests fused 200 tests/test_fused.py tests/test_periodic_gaps.py \
      -m "slow or not slow"
    timeout 150 "$PY" benchmarks/md_step.py --n 1000000 --systems lj \
      --repeats 5 --timeout 40 --budget 140 --only fused:cell \
      "fused:cell[32x1n]" "fused:cell[32x1a2]" "fused:cell[32x1a2n]" \
      "fused:cell[32x1s]" jaxrt:cell/Dense jax-md/Dense \
      --out "$DEST/md_step_$GIT_SHA.csv" > "$DEST/logs/md_step.log" 2>&1
    note "md_step rc=$?"
    timeout 200 "$PY" benchmarks/roofline.py --n 1000000 --kernels auto \
      --parts --launches 32x1n 32x1a2n 32x1s --timeout 40 --budget 190 \
      --out "$DEST/roofline_$GIT_SHA.csv" > "$DEST/logs/roofline.log" 2>&1
    note "roofline rc=$?" ;;
  step)
    timeout 200 "$PY" benchmarks/md_step.py --n 1000000 --systems lj \
      --repeats 5 --timeout 60 --budget 170 --only fused:cell \
      jaxrt:cell/Dense jax-md/Dense \
      --out "$DEST/md_step_$GIT_SHA.csv" > "$DEST/logs/md_step.log" 2>&1
    note "md_step rc=$?"
    timeout 200 "$PY" benchmarks/roofline.py --n 1000000 --kernels auto \
      --parts --timeout 60 --budget 170 \
      --out "$DEST/roofline_$GIT_SHA.csv" > "$DEST/logs/roofline.log" 2>&1
    note "roofline rc=$?"
    timeout 120 "$PY" benchmarks/grid_stages.py --n 1000000 \
      --out "$DEST/grid_stages_$GIT_SHA.csv" > "$DEST/logs/grid_stages.log" 2>&1
    note "grid_stages rc=$?" ;;
  profile)
    NCU=$(command -v ncu || ls /usr/local/cuda*/bin/ncu 2>/dev/null | head -1)
    [[ -n $NCU ]] || { note "profile: no ncu on this machine"; exit 0; }
    timeout ${NCU_LIMIT:-400} "$NCU" --clock-control none --kernel-name regex:jaxrt_cell --launch-skip 2 \
      --launch-count 2 --section SpeedOfLight --section Occupancy \
      --section WarpStateStats --section SchedulerStats --section LaunchStats \
      --section ComputeWorkloadAnalysis --section MemoryWorkloadAnalysis \
      "$PY" benchmarks/profile_cell_kernels.py > "$DEST/logs/ncu.log" 2>&1
    note "profile rc=$?" ;;
  overhead)
    timeout 240 "$PY" benchmarks/step_overhead.py --n 64 50000 --budget 200 \
      --hard-stop 230 --out "$DEST/step_overhead_$GIT_SHA.csv" \
      > "$DEST/logs/step_overhead.log" 2>&1
    note "step_overhead rc=$?"
    OUT=$DEST BUDGET=250 HARD_STOP=290 ROW_TIMEOUT=120 timeout 300 \
      bash benchmarks/run_table2_h200.sh 1 > "$DEST/logs/table2_1.log" 2>&1
    note "table2 part 1 rc=$?" ;;
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
  stability)
    # 120 + 150 + 180 + 130 s: the part stays inside one 10-minute call.
    tests edges 120 tests/test_pairs.py tests/test_energy_lj.py \
      tests/test_energy_sph.py tests/test_jax_md_acceptance.py
    tests stability 150 tests/stability
    tests stability_slow 180 tests/stability -m "stability and slow" \
      -k "not long_nve"
    tests stability_nve 130 tests/stability/test_nve_drift.py \
      -m "stability and slow" -k long_nve ;;
  owed)
    tests edges 150 tests/test_pairs.py tests/test_energy_lj.py \
      tests/test_energy_sph.py tests/test_jax_md_acceptance.py
    timeout 380 "$PY" -m jaxrt accuracy --quick --n 16384 --steps 2000 \
      --budget 340 --knobs format,pairs \
      --out "$DEST/accuracy_lj_format_pairs_$GIT_SHA" > "$DEST/logs/accuracy.log" 2>&1
    note "accuracy format,pairs rc=$?" ;;
  layouts)
    # #18's Sparse / OrderedSparse within 1.2x of Dense: the edge kernel
    # and OrderedSparse's half rows compiled (their tests, and every
    # Sparse list of test_neighbors.py through them), the updates side by
    # side, then the LJ step on each layout against jax-md's default.
    tests layouts 110 tests/test_cell_kernel.py tests/test_neighbors.py \
      -k "rows_to_edges or ordered or sparse or Sparse"
    timeout 110 "$PY" benchmarks/list_forces.py --n 1000000 --k 52 \
      --stages update convert \
      --out "$DEST/list_forces_1e6_k52_$GIT_SHA.csv" > "$DEST/logs/lf_1e6.log" 2>&1
    note "list_forces 1e6 rc=$?"
    timeout 170 "$PY" benchmarks/md_step.py --n 1000000 --systems lj \
      --repeats 5 --timeout 60 --budget 160 --only jaxrt:cell/Dense \
      jaxrt:cell/OrderedSparse jaxrt:cell/Sparse jax-md/OrderedSparse \
      --out "$DEST/md_step_$GIT_SHA.csv" > "$DEST/logs/md_step.log" 2>&1
    note "md_step rc=$?" ;;
  formats)
    # 300 + 250 s: the part stays inside one 10-minute call.
    timeout 300 "$PY" benchmarks/list_forces.py --n 1000000 --k 52 \
      --out "$DEST/list_forces_1e6_k52_$GIT_SHA.csv" > "$DEST/logs/lf_1e6.log" 2>&1
    note "list_forces 1e6 rc=$?"
    timeout 250 "$PY" benchmarks/list_forces.py --n 50000 --k 700 --repeats 5 \
      --stages update forces convert \
      --out "$DEST/list_forces_5e4_k700_$GIT_SHA.csv" > "$DEST/logs/lf_5e4.log" 2>&1
    note "list_forces 5e4 rc=$?" ;;
  alloc)
    # ~480 s: the kernel's tests and allocate's (bucketed sizes run the
    # kernel at widths the list itself never has), then the rows.
    tests cell_kernel 90 tests/test_cell_kernel.py -m "slow or not slow"
    tests neighbors 150 tests/test_neighbors.py
    timeout 150 "$PY" benchmarks/neighbors.py --sizes 1000000 --scenes uniform \
      --backends cell bvh --repeats 10 --timeout 100 \
      --out "$DEST/neighbors_alloc_1e6_$GIT_SHA.csv" > "$DEST/logs/alloc.log" 2>&1
    note "neighbors 1e6 rc=$?"
    # Seed 001's init at 2.1e6 sphere points (AABB sorted 1.38 s at
    # 497bb8b with k = 9, against a 2.2 ms BVH build): which stage of
    # allocate is it? (neighbors.py's sphere, k ~ 30, at that N.)
    timeout 120 "$PY" benchmarks/allocate_parts.py --sizes 2097152 \
      --scenes sphere --backends cell bvh squares --timeout 100 \
      --out "$DEST/allocate_parts_2e6_$GIT_SHA.csv" > "$DEST/logs/parts.log" 2>&1
    note "allocate parts rc=$?" ;;
  seed-rest)
    # Guessed 364 s (parts 1-3 ran within 3 % of their guesses): 15
    # configurations of up to 1M particles with all ten methods (the small
    # ones share a worker), then the two list methods that the last call
    # did not reach at sphere alpha = 128, p = 4.
    timeout 400 "$PY" benchmarks/seed_rt_study.py --time-budget 340 \
      --hard-stop 380 --timeout 120 --configs uniform:2:4 uniform:4:2 \
      uniform:4:4 uniform:2:16 uniform:8:4 uniform:2:32 uniform:16:1 \
      uniform:4:32 sphere:8:2 sphere:8:4 uniform:16:4 sphere:16:4 \
      uniform:32:4 sphere:32:4 sphere:64:4 \
      --out "$DEST/seed_rt_rest_$GIT_SHA" > "$DEST/logs/seed_rest.log" 2>&1
    note "seed rest rc=$?"
    LEFT=$(( 560 - (SECONDS - START) ))
    timeout "$LEFT" "$PY" benchmarks/seed_rt_study.py \
      --time-budget $(( LEFT - 60 )) --hard-stop $(( LEFT - 15 )) --timeout 90 \
      --configs sphere:128:4 --methods cell jax-md \
      --out "$DEST/seed_rt_sa128p4_$GIT_SHA" > "$DEST/logs/seed_sa128p4.log" 2>&1
    note "seed sa128p4 rc=$?" ;;
  seed-big)
    # The fused methods at sphere alpha = 128: p = 16 (N = 33M, the list
    # methods refused), then part 5 (spheres-fused at N = 67M, past its
    # 150 s timeout at 65309c3; at p = 8 it refused near-coincident
    # particles, which it may do here too).
    timeout 200 "$PY" benchmarks/seed_rt_study.py --time-budget 150 \
      --hard-stop 190 --timeout 150 --configs sphere:128:16 \
      --out "$DEST/seed_rt_sa128p16_$GIT_SHA" > "$DEST/logs/seed_sa128p16.log" 2>&1
    note "seed sa128p16 rc=$?"
    LEFT=$(( 570 - (SECONDS - START) ))
    timeout "$LEFT" "$PY" benchmarks/seed_rt_study.py --part 5/5 \
      --time-budget 60 --hard-stop $(( LEFT - 10 )) --timeout $(( LEFT - 20 )) \
      --out "$DEST/seed_rt_part5_$GIT_SHA" > "$DEST/logs/seed_part5.log" 2>&1
    note "seed part 5 rc=$?" ;;
  model)
    tests model 150 tests/test_never_wrong.py tests/test_neighbors.py
    timeout 150 "$PY" benchmarks/allocate_parts.py --sizes 2097152 \
      --scenes sphere --backends cell bvh squares --timeout 130 \
      --out "$DEST/allocate_parts_2e6_$GIT_SHA.csv" > "$DEST/logs/parts.log" 2>&1
    note "allocate parts rc=$?"
    timeout 150 "$PY" benchmarks/neighbors.py --sizes 1000000 --scenes uniform \
      --backends cell --repeats 5 --timeout 130 \
      --out "$DEST/neighbors_alloc_1e6_$GIT_SHA.csv" > "$DEST/logs/alloc.log" 2>&1
    note "neighbors 1e6 rc=$?" ;;
  table2-6p)
    OUT=$DEST SCENES="lattice disordered" BOUNDARIES=periodic BUDGET=300 \
      HARD_STOP=380 ROW_TIMEOUT=120 timeout 390 bash benchmarks/run_table2_h200.sh 6 \
      > "$DEST/logs/table2_6_periodic.log" 2>&1
    note "table2 part 6 periodic rc=$?"
    LEFT=$(( 560 - (SECONDS - START) ))
    OUT=$DEST SCENES=cluster BOUNDARIES=periodic \
      METHODS="GPU-CELL GPU-CELL-fused CPU-CELL" BUDGET=$(( LEFT - 60 )) \
      HARD_STOP=$(( LEFT - 10 )) ROW_TIMEOUT=100 timeout "$LEFT" \
      bash benchmarks/run_table2_h200.sh 6 > "$DEST/logs/table2_6_cluster.log" 2>&1
    note "table2 part 6 periodic cluster rc=$?" ;;
  *) echo "PART must be tests, runs, step, profile, overhead, sph, radii, accuracy, owed, formats, alloc, seed-rest, seed-big, model or table2-6p"; exit 2 ;;
esac
