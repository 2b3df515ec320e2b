"""Seed 001 §5 reproduced: ray-tracing-style neighbour search against grids.

Entry point: ``benchmarks/seed_rt_study.py``. This package holds its three
parts: `seed_rt.plan` (which configurations, in which order), `seed_rt.worker`
(one job, measured in a `_harness` worker process) and `seed_rt.report`
(speed-ups, headline table, plots).

Scenes (float32, free space with walls as in the seed;
`jaxrt.seed_distributions`):
  uniform  §5.2: ``N = p·β³`` particles uniform in the unit box, cutoff
           ``C = 1/β``; β ∈ {2, 4, 8, 16, 32}, p ∈ {1, 2, 4, 8, 16, 32}.
  sphere   §5.3 / Code 2: ``N = p·α³`` particles uniform on the unit sphere,
           cutoff for ≈ 9·p neighbours (``sphere_surface_cutoff``);
           α ∈ {8, 16, 32, 64, 128}, p ∈ {1, …, 32}. Points shifted by
           ``1 + C`` into ``[0, 2 + 2C)³``.

Methods (every one through jax-md's ``neighbor_list`` interface, Dense
layout, ``dr_threshold = 0`` so every ``update`` searches again,
``capacity_multiplier = 1.25``, ``mask_self = True``; every one gets
``space.free()`` and the seed's box, 1.0 (uniform) or ``2 + 2C`` (sphere)):
  aabb-unsorted  jaxrt ``Bvh(sort=False)`` (Warp custom-AABB BVH, input order)
  aabb-sorted    jaxrt ``"bvh"``            (the same, Morton-sorted)
  spheres        jaxrt ``"spheres"``        (seed's sphere + ray method)
  squares        jaxrt ``"squares"``        (seed's double-squares method)
  cell           jaxrt ``"cell"``           (pure-JAX cell list)
  jax-md         ``jax_md.partition.neighbor_list`` (its dense cell list)
  Speed-ups in the tables and on the plots are over "jax-md", the grid
  method (the seed's CUDA grid of cells), by total time.

What ``update`` redoes in the compute step: spheres, squares, cell and
jax-md rebuild their structure (BVH / grid) on every call. The two aabb
methods keep one BVH per compiled call site (`jaxrt.rt.ffi`) and *refit* it,
because the inputs differ by 1e-3·C, below the rebuild threshold (0.2·C);
their compute step is refit + rays, closer to the seed's compute step (which
excludes the build) than the grid methods' update is.

Columns (three rotating input sets: the scene plus two copies jittered by
1e-3·C, clipped to the box; each timed call reads the next set, so no call
repeats the previous input):
  init_ms     median wall time of ``allocate(R)``: builds the search
              structure on the host path, measures the exact capacity and
              allocates the Dense ``(N, capacity)`` buffer (the seed's
              "initialization step").
  compute_ms  median wall time of one jitted call
              ``f(R, nbrs) = (update(R, nbrs), lj_forces(R, idx))``: the
              list search plus an LJ-like force accumulation over the pairs
              found (σ = C/2, ε = 1, r² clamped at (σ/10)², summed over each
              Dense row: a gather + reduction in JAX, the same code for
              every method). The seed's "computation step".
  search_ms   the same with ``update`` alone (no forces), for reference
              (empty with ``--no-search``, or when compute_ms is above
              ``--search-limit-ms``; search_reps is then 0).
  total_ms    init_ms + compute_ms (what the bars stack).
  *_min_ms, *_max_ms, *_reps
              min and max of the timed calls behind each median, and their
              number. Every measurement makes one untimed warm-up call
              (compilation, first BVH build, lazy loads), then timed calls;
              the first timed call's time t sets their number,
              ``clamp(ceil(--target-s / t), --min-repeats, --max-repeats)``,
              so large N gets few repeats and small N many. compute and
              search are compiled together, in two threads, before either
              is timed.
  k_mean (= k) mean neighbours per particle (from the allocate'd list).
  capacity    Dense row width; overflow: did any timed compute call's list
              overflow.
  tier        the configuration's priority (below); 0 for --configs.
  status, failed
              ``ok``, or why a row has no times (`_harness.STATUSES`):
              ``oom`` (XLA's RESOURCE_EXHAUSTED, a failed Warp allocation,
              the host's OOM killer), ``error`` (another exception),
              ``timeout``, ``crashed`` (the worker died), ``skipped`` (not
              selected, --max-n, --time-budget, --hard-stop); ``failed``
              says more.
  speedup_vs_jaxmd / speedup_vs_cell   total_ms ratios, same configuration.
  Provenance columns as every benchmark's (`_harness.PROVENANCE`).

Plan. The seed's Figures 9 and 10 have one panel per β (α), bars for each
p. Configurations run by priority tier, largest N first inside a tier, all
methods of a configuration back to back:
  tier 1  every panel's largest p with N <= --max-n (32; 8 for α = 128:
          many particles per cell, where sorting and the interactions
          decide), and p = 1 on the large panels β ∈ {16, 32},
          α ∈ {32, 64, 128} (few per cell: where the seed finds the grid's
          empty cells cost most, and α = 128 is its out-of-memory case).
  tier 2  p = 8 (α = 128: p = 4) everywhere; p = 1 on the small panels.
  tier 3  p ∈ {2, 16} (α = 128: p = 2).
  tier 4  p = 4 (the rest).
The smallest configurations (N <= 2048) are dominated by fixed per-call
overheads whatever the method; they come last inside each tier.
Every row of the seed's grid is written to the CSV; rows not run say why.
``--plan`` prints the order with N and a rough H100 time guess and exits.

Isolation (`_harness`). The methods of one configuration run back to back
in one worker process, which keeps the configuration's inputs on the
device (imports and the scene are paid once per configuration, not per
method); one worker at a time, since on one GPU concurrent workers would
disturb the timings. A job that raises, runs out of memory, crashes the
worker or passes ``--timeout`` is recorded with its status, and a fresh
worker takes the next job; so does every new configuration. After
``--time-budget`` seconds no new configuration starts; at ``--hard-stop``
seconds the running job is killed. The CSV is rewritten after every row,
in case the whole run is killed.

Usage:
  python benchmarks/seed_rt_study.py --plan                         # dry run
  python benchmarks/seed_rt_study.py --small --out /tmp/seedstudy   # CPU smoke
  python benchmarks/seed_rt_study.py --time-budget 470 --hard-stop 505 \\
      --timeout 100                                                 # GPU, < 9 min
  python benchmarks/seed_rt_study.py --configs uniform:32:1 sphere:128:8
  python benchmarks/seed_rt_study.py --plot-only results.csv [--out DIR]
Writes seed_rt_study.csv, seed_rt_uniform.png, seed_rt_sphere.png and
seed_rt_headline.md to --out, else benchmarks/results/<device>/seed_rt/.
"""
