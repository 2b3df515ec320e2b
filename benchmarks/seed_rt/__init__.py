"""Seed 001 §5 reproduced: ray-tracing-style neighbour search against grids.

Entry point: ``benchmarks/seed_rt_study.py``. This package holds its three
parts: `seed_rt.plan` (which configurations, in which order), `seed_rt.worker`
(one job, measured in a `_harness` worker process) and `seed_rt.report`
(speed-ups, headline table, plots).

Scenes (float32, free space with walls as in the seed;
`jaxrt.sim.distributions`):
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
  aabb-sorted-fused, aabb-unsorted-fused, spheres-fused, squares-fused
                 seed 001's fused mode (`jaxrt.rt.FusedEnergy`,
                 `jaxrt.backends.rt.seed_energy`): the same methods, whose
                 intersection program sums the LJ energy during the
                 traversal (one atomic add per ray into energy[i]); no list.
  Speed-ups in the tables and on the plots are over "jax-md", the grid
  method (the seed's CUDA grid of cells), by total time.

The interaction (every method): per-particle LJ energy
``E_i = sum_j 4 eps [(sigma^2/r2)^6 - (sigma^2/r2)^3]``, σ = C/2, ε = 1,
r² clamped at (σ/10)² (the seed's code takes σ = ε = 1, which overflows
float32 at C = 1/32), summed over each Dense row in JAX for the list
methods and inside the kernels for the fused ones, with the same
arithmetic; ``pairs`` and ``energy_sum`` let the rows of one configuration
be checked against each other (they agree to float32 rounding).

What ``update`` redoes in the compute step: spheres, squares, cell and
jax-md rebuild their structure (BVH / grid) on every call. The two aabb
methods keep one BVH per compiled call site (`jaxrt.backends.rt.ffi`) and *refit* it,
because the inputs differ by 1e-3·C, below the rebuild threshold (0.2·C);
their compute step is refit + rays, closer to the seed's compute step (which
excludes the build) than the grid methods' update is.

Columns (three rotating input sets: the scene plus two copies jittered by
1e-3·C, clipped to the box; each timed call reads the next set, so no call
repeats the previous input):
  init_ms     list methods: median wall time of ``allocate(R)``: builds
              the search structure on the host path, measures the exact
              capacity and allocates the Dense ``(N, capacity)`` buffer.
              Fused methods (no list): their build_ms.
  compute_ms  list methods: median wall time of one jitted call
              ``f(R, nbrs) = (update(R, nbrs), lj_energy(R, idx))``: the
              list search plus the energy sum over the pairs found (a
              gather + reduction in JAX, the same code for every method).
              Fused methods: one jitted ``FusedEnergy`` call (aabb: refit
              of the kept tree + rays; spheres / squares: build + rays).
  build_ms, query_ms
              Warp methods only (SPECS §7.2, the seed's own split): the
              structure alone (aabb: extent, Morton sort, placement, boxes,
              BVH rebuild; spheres / squares: survey, primitive boxes, new
              BVH) and the rays alone on it (fused: with the interactions;
              list: writing the Dense rows), timed in Warp outside JAX with
              a device synchronise per sample (``--no-split`` skips them).
  interaction_ms
              list methods: the jitted JAX energy sum alone over the
              allocate'd list (the seed's CUDA compute step is its
              interaction kernel).
  paper_init_ms, paper_compute_ms
              the seed's init / compute: build_ms, and query_ms (+
              interaction_ms for a list method).
  pairs, energy_sum
              ordered pairs found and the float64 sum of the per-particle
              energies, on the first input set.
  search_ms   the same with ``update`` alone (no energy), for reference
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
Every row of the seed's grid (60 configurations x 10 methods = 600 rows)
is written to the CSV; rows not run say why. Jobs certain to fail are not
run (`seed_rt.plan.refusal`): a Dense list whose mean row alone passes
what the method can index (2**29 entries for the Warp lists, 2**31 for
cell and jax-md; sphere α = 64, p >= 16 and α = 128, p >= 8), and
squares at α = 128, p = 32 (4N triangle boxes pass Warp's 32-bit byte
offsets). The fused methods run those configurations.
Jobs guessed longer than ``--heavy-s`` (default 60 s; the guesses know
the H200's rows at N = 67M: `seed_rt.plan._GUESS`) are taken out of their
configuration and run after all the others, longest first, each in a part
of its own: on the H200 the 67M configuration's spheres-fused once timed
out after 150 s and, with its siblings, left no time for the part's other
configurations. From ``--large-n`` particles (default 4e6) every
measurement makes one timed call after its warm-up instead of
``--min-repeats`` (calls take seconds there and barely vary). Each job's
timeout is `seed_rt.plan.TIMEOUT_FACTOR` times its guess, at least
``--timeout``. ``--plan`` prints the order with N, the timed calls, a
rough H100/H200 time guess, the longest timeout and the parts, and exits.

Parts. ``--part K`` (or ``K/M``, checked against the plan) runs the K-th
of the consecutive parts that ``--part-budget`` seconds (default 480,
start-up included, by the guess) cut the plan into, largest first; a
configuration is split over parts only if it alone exceeds the budget.
Each part writes its own CSV; ``--plot-only CSV...`` merges them
(benchmarks/RESULTS.md gives the GPU commands).

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
  python benchmarks/seed_rt_study.py --part 1/6 --time-budget 450 \\
      --hard-stop 520 --timeout 240 --out DIR/part1                 # GPU, < 9 min
  python benchmarks/seed_rt_study.py --plot-only DIR/part*/seed_rt_study.csv --out DIR
  python benchmarks/seed_rt_study.py --configs uniform:32:1 sphere:128:8
  python benchmarks/seed_rt_study.py --plot-only results.csv [--out DIR]
Writes seed_rt_study.csv, seed_rt_uniform.png, seed_rt_sphere.png and
seed_rt_headline.md to --out, else benchmarks/results/<device>/seed_rt/.
"""
