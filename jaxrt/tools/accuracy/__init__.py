"""What accuracy costs in time: sweep the knobs that trade one for the other.

``jaxrt accuracy [SCENE] --out DIR [--quick]`` (`jaxrt.tools.cli`) calls
`run`.
On a scene (`SCENES`: the LJ fluid by default; ``lj-fluid-2d``, the LJ
fluid in 2D, where the Delaunay backend runs; the dam break for SPH, 2D
too) it varies one knob at a time away from the scene's own setting (the
*base*) and measures,
for each value, the time per step and its errors against a float64
reference of the same scene. Outputs in ``DIR``: ``accuracy.csv`` (one row
per knob value), ``<knob>.png`` (each error against the time per step, the
Pareto front drawn) and ``summary.md`` (sentences computed from the rows).

One function per concern:

* knobs as data: `Knob` (a name, its `Value`\\s, the scenes and
  dimensions it applies to, whether it is available here) and `KNOBS`; a
  `Value` maps a `Scene` to a `Scene` (every knob is a scene field, a
  backend option, or an effect in place of the LJ: `LJFused`, `LJPairs`)
  and may run in some dimensions only (Delaunay 2D, `jaxrt.pairs` 3D) or
  only where it can (the Pallas kernels: CUDA GPUs);
* a knob may need a scene of its own (`Knob.own_scene`): per-particle
  cutoff radii (the ``radii`` knob: one grid of the largest radius,
  ``Cell(radius_classes=)``, the BVH, the fused LJ with ``radii=``) run on
  `polydisperse` (`jaxrt.sim.lj_polydisperse`, ``jaxrt.sim.LJ(radii=)``:
  pair ``ij`` cut at ``max(r_i, r_j)``, the list built with those radii),
  against that scene's own float64 reference, its pairs checked at
  ``max(r_i, r_j)`` (`brute_pairs` ``radii=``);
* the reference: `equilibrate` (float64), `reference_forces` (float64,
  brute force), `measure` of the float64 scene itself (continuing the
  equilibration, its list by the scene's backend, ``cell``);
* the error measures, each a pure function of arrays (tested by hand):
  `force_rms_rel`, `energy_drift`, `brute_pairs` / `pairs_missed`, `rdf` /
  `rdf_difference`, `position_rms`;
* timing: `measure` times the jitted chunks of the run itself, the first
  (compiling) chunk excluded, every chunk synchronised
  (`jax.block_until_ready`), the median over chunks reported;
* `pareto_front`, `write_csv`, `plot_knob`, `write_summary`.

Definitions (the CSV's columns):

* ``time_per_step_ms``: median over the run's chunks (``chunk`` steps in one
  jitted ``lax.scan`` each; list updates, forces, integrator) of the chunk's
  wall time / ``chunk``; the first chunk (compilation) and any chunk redone
  after a list overflow are excluded. ``time_min_ms`` / ``time_max_ms``: the
  extremes of the same samples. ``time_per_tau_ms``: ``time_per_step_ms /
  dt``, per unit of simulated time (what the summary ranks by, so that a
  longer time step counts for what it saves).
* ``force_rms_rel``: ``sqrt(mean |F - F_ref|^2) / sqrt(mean |F_ref|^2)`` at
  the equilibrated configuration, where ``F_ref`` is the float64 brute-force
  force of the *scene's own* potential (so it isolates precision and list
  effects); ``force_rms_rel_full``: the same against float64 LJ cut plainly
  at ``r_ref`` (the longest cutoff the box allows, at most 5 sigma): the
  error of the truncation itself (none with cutoff radii: each pair has
  its own stretched potential). (SPH: accelerations.)
* ``drift_per_particle_1e4``: the least-squares slope of
  ``(E(t) - E(t_1)) / N`` against the step number, times 10^4: energy drift
  per particle per 10^4 steps of the setting's own Hamiltonian, NVE;
  ``drift_se``: its standard error from 10 block means (`energy_drift`);
  ``max_abs_dE_per_particle``: ``max |E(t) - E(t_1)| / N`` over the run
  (the energy excursion, robust in short runs: it scales as dt^2).
  Empty for non-conservative scenes (dam break).
* ``pairs_missed``: after every chunk, the pairs within the interaction
  cutoff (with radii: ``max(r_i, r_j)``) at the current positions (float64
  brute force, minimum image on periodic axes) that the list in use lacks (or, for `LJPairs`, the pairs
  `jaxrt.pairs` finds at those positions), summed over the checks
  (``pairs_checked``: the brute-force pairs over the same checks; ``k``:
  mean neighbours within the cutoff per particle); ``missed_depth_ulps``:
  the deepest missed pair's distance inside its cut, in ulps of the
  distances' scale (`missed_depth_ulps`): up to `ROUNDING_ULPS` a search in
  float32 decides by rounding, as jax-md's metric does; deeper, the list is
  wrong.
* ``rdf_l2`` / ``rdf_linf``: ``sqrt(sum (g - g_ref)^2 dr)`` and
  ``max |g - g_ref|`` of the radial distribution functions over the run's
  chunk-end frames, on the fixed grid ``dr`` up to ``r_max`` (periodic
  scenes only); ``rdf_noise`` in the summary: the same between the two
  halves of the reference run (each half from half the frames, so about
  √2 above the noise of a setting against the reference), the floor
  below which a difference means nothing.
* ``position_rms``: RMS distance between the setting's final positions and
  the reference's (chaotic for the LJ fluid, so a measure of divergence).
* ``rebuilds``: list rebuilds over the run; ``triangulation_rebuilds``
  (Delaunay lists): rebuilds of the triangulation from scratch (Qhull on
  the host) where its maintenance by flips gave up.
"""
from jaxrt.tools.provenance import PROVENANCE, provenance  # noqa: F401
from jaxrt.tools.accuracy.knobs import (  # noqa: F401
    DELAUNAY_CAPACITY,
    KNOBS,
    Knob,
    LJFused,
    LJPairs,
    POLYDISPERSE_DENSITY,
    Value,
    fused_takes,
    knobs,
    lj_as,
    pallas_here,
    polydisperse,
    replace_neighbors,
    unchanged,
    warp_here,
    with_lj)
from jaxrt.tools.accuracy.measures import (  # noqa: F401
    Drift,
    ROUNDING_ULPS,
    brute_pairs,
    energy_drift,
    exact_pairs,
    force_rms_rel,
    missed_depth_ulps,
    pair_distances,
    pairs_missed,
    pareto_front,
    position_rms,
    rdf,
    rdf_difference,
    rdf_grid)
from jaxrt.tools.accuracy.scenes import (  # noqa: F401
    FULL,
    Measured,
    Plan,
    QUICK,
    SCENES,
    auto_backend_for,
    base_scene,
    describe,
    equilibrate,
    finish_row,
    in_walls,
    lj_fluid_2d,
    long_cutoff,
    measure,
    own_search,
    rdf_edges,
    rdf_noise,
    reference_forces,
    reference_scene,
    row_key,
    scene_kind,
    triangulation_rebuilds_of,
    with_state)
from jaxrt.tools.accuracy.report import (  # noqa: F401
    COLUMNS,
    ERRORS,
    NOT_FOR,
    TARGETS,
    cheapest,
    depth_note,
    fmt_value,
    num,
    plot_knob,
    summary_lines,
    write_csv,
    write_summary)
from jaxrt.tools.accuracy.sweep import (  # noqa: F401
    run)
