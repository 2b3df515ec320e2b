"""Test-suite settings.

Hypothesis is derandomised (each test's examples follow from its name, so
a failure in CI is a failure on every machine) and keeps no example
database; the ``slow`` tests run many more examples of the same
properties.

The suite compiles hundreds of small XLA programs and runs each once or a
few times on tiny systems, so LLVM's optimisation passes cost far more than
they save: the CPU backend is told not to run them (set before JAX starts;
an ``XLA_FLAGS`` already in the environment wins). Semantics are unchanged
on the CPU (XLA's CPU backend does not enable fast-math either way), and
every comparison with jax-md compiles both sides under the same flags.

Not where a GPU is visible: the flag is not backend-specific, and XLA's GPU
backend at level 0 miscompiles programs that users run at the default
level (on the H200, jax 0.11.2: `jaxrt.pairs` under ``vmap`` returned pairs
8 Å past the cutoff, `benchmarks/debug/debug_pairs_gpu.py`), so the GPU's
tests compile as users do.
"""
import os


def _gpu_visible() -> bool:
    """Whether JAX may start a GPU backend (decided before JAX starts)."""
    platforms = os.environ.get("JAX_PLATFORMS", "")
    if platforms:
        return any(p in platforms for p in ("cuda", "gpu", "rocm"))
    return os.path.exists("/dev/nvidiactl") or os.path.exists("/dev/kfd")


if ("xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", "")
        and not _gpu_visible()):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_backend_optimization_level=0").strip()

# Many tests build the same small programs (one factory per test, the same
# shapes and options), and JAX's in-memory cache is per function object and
# dropped after each file (below): a compilation cache on disk, fresh for each
# run and shared by its workers (they inherit the variable from the
# controller, which removes the folder at the end), compiles each program
# once per run. test_never_wrong.py: 251 s -> 188 s on two cores. A cache the
# caller configured wins.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import tempfile
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(
        prefix="jaxrt-test-compile-cache-")
    os.environ["JAXRT_TEST_CACHE_OWNER"] = str(os.getpid())
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")

# On GPUs XLA rounds float32 matrix products to TF32 by default, so jax-md's
# periodic_general metric (a matrix product) is only good to ~1e-3 there and
# the float64 oracles would disagree with it near the cutoff. jaxrt copes
# (`jaxrt.lists.metric`'s slack); the oracles need the metric exact.
import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_default_matmul_precision", "highest")

try:  # a test dependency; GPU machines may run the suite's other files
    import hypothesis  # noqa: E402
except ImportError:
    pass
else:
    hypothesis.settings.register_profile("jaxrt", derandomize=True,
                                         database=None, deadline=None,
                                         print_blob=True)
    hypothesis.settings.load_profile("jaxrt")


@pytest.fixture
def x64():
    """float64 for one test (the ``jax.enable_x64`` context; tests whose
    callbacks run in other threads override it with the global flag)."""
    with jax.enable_x64(True):
        yield


def pytest_configure(config):
    """Compile the Warp kernels once, in a subprocess, before any test.

    Warp compiles CPU kernels in-process with its own LLVM (warp-clang);
    on a fresh machine the first test worker to load a kernel module would
    do that next to XLA's LLVM, and the suite's later XLA compiles then
    crashed twice (a segfault and an abort inside backend_compile) after
    the kernels changed. With the kernel cache filled here, workers only
    load compiled binaries.
    """
    import os
    import subprocess
    import sys
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return  # the controller did it
    modules = ("jaxrt.backends.rt.aabb", "jaxrt.backends.rt.epsilon",
               "jaxrt.backends.rt.spheres", "jaxrt.backends.rt.squares",
               "jaxrt.backends.rt.orcs")
    code = ("import importlib, warp as wp\n"
            f"for m in {modules!r}:\n"
            "    importlib.import_module(m)\n"
            "    wp.load_module(module=m, device='cpu')\n"
            "from jaxrt.pairs import warp_kernels as pk\n"
            "wp.load_module(module=pk, device='cpu')\n"
            "for s in (wp.float32, wp.float64):\n"
            "    wp.load_module(pk.walk_kernel(s).module, device='cpu')\n")
    try:
        subprocess.run([sys.executable, "-c", code], check=False,
                       capture_output=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired):
        pass  # the tests then compile the kernels themselves


try:
    import pytest  # noqa: E402
except ImportError:  # pragma: no cover
    pytest = None
else:
    @pytest.fixture(autouse=True, scope="module")
    def _free_compiled_programs():
        """Drop JAX's compiled programs after each test file.

        A worker compiles hundreds of programs that no later file calls; in
        a full run each worker grew past 5 GB, and workers have died inside
        XLA's compiler (aborts, segfaults) late in long runs. Files share
        few programs, so recompiling those is cheap.
        """
        yield
        import gc
        jax.clear_caches()
        gc.collect()


def pytest_unconfigure(config):
    """Remove the run's compilation cache (the process that made it)."""
    import shutil
    if os.environ.get("JAXRT_TEST_CACHE_OWNER") == str(os.getpid()):
        shutil.rmtree(os.environ["JAX_COMPILATION_CACHE_DIR"],
                      ignore_errors=True)


# Cases left to the slow run (`-m slow`; the H200 runs run them all) so
# that the default suite stays inside the brief's 15 minutes on CI's two
# cores. Each is a variant of a property that a default case keeps (named
# after the "#"): most cost is compiling a new program per allocate
# (~3 s on CI's cores), so a variant costs nearly what its sibling does.
LONG_CASES = {
    # test_warp_walk.py: [True-True] (half, self pairs) keeps the mixed
    # batch; scratch widths [0] and [1] keep both write paths.
    "tests/pairs/test_warp_walk.py::test_mixed_batch_row_for_row_and_ase[False-False]",
    "tests/pairs/test_warp_walk.py::test_atoms_past_their_scratch_row_are_walked_again[3]",
    "tests/pairs/test_warp_walk.py::test_atoms_past_their_scratch_row_are_walked_again[64]",
    # test_batch_reach.py: [True] keeps the own reach under jit.
    "tests/pairs/test_batch_reach.py::test_own_reach_batch_matches_ase_per_system_under_jit[False]",
    # test_unsorted_cuda.py: [options0] (plain), [options3] (half, self
    # pairs and species at once), [options4] (long runs: the stream) and
    # [options7] (brute force, half) keep the CUDA branch's single systems;
    # the batch with species, self pairs and half lists keeps [True].
    "tests/pairs/test_unsorted_cuda.py::test_single_system_unsorted_on_cuda_equals_ase[options1]",
    "tests/pairs/test_unsorted_cuda.py::test_single_system_unsorted_on_cuda_equals_ase[options2]",
    "tests/pairs/test_unsorted_cuda.py::test_single_system_unsorted_on_cuda_equals_ase[options5]",
    "tests/pairs/test_unsorted_cuda.py::test_single_system_unsorted_on_cuda_equals_ase[options6]",
    "tests/pairs/test_unsorted_cuda.py::test_mixed_batch_unsorted_on_cuda_equals_the_cpu_and_ase[True]",
    # test_cell_kernel.py: the kernel in Pallas' interpreter keeps
    # [random] (faces and 2D on the portable path: test_neighbors).
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[faces]",
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[2d]",
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[random free]",
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[lattice at cutoff, free]",
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[box of 2.01 cutoffs]",
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[box of 3.01 cutoffs]",
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[2d free]",
    # list and vmap/scan in the interpreter: test_energy_lj's grad through
    # a scan with updates [jaxrt:cell] and test_neighbors' vmap keep them.
    "tests/backends/test_cell_kernel.py::test_kernel_list_update_inside_grad",
    "tests/backends/test_cell_kernel.py::test_kernel_under_vmap_and_scan",
    # test_neighbors.py: [xla] keeps the internal buffers' overflow bits,
    # test_cell_kernel's overflow test keeps the kernel's.
    "tests/lists/test_neighbors.py::test_cell_list_internal_buffer_overflow_is_flagged[interpret]",
    "tests/lists/test_neighbors.py::test_overflow_is_flagged_sticky_and_fixed_by_reallocation[NeighborListFormat.Sparse]",
    "tests/lists/test_neighbors.py::test_overflow_is_flagged_sticky_and_fixed_by_reallocation[NeighborListFormat.OrderedSparse]",
    "tests/lists/test_neighbors.py::test_cell_list_allocated_on_a_lattice_survives_melting",
    "tests/lists/test_neighbors.py::test_small_periodic_boxes[3.0]",  # test_small_box
    # jax-md's own cases (test_jax_md_acceptance: custom mask, mask_self
    # False, dim=2) and the hypothesis scenes (dim 2 and 3) keep these.
    "tests/lists/test_neighbors.py::test_mask_self_false_keeps_self_pairs_and_custom_mask",
    "tests/lists/test_neighbors.py::test_two_dimensions",
    # jax-md's test_general_unit_cell (acceptance) and test_bvh's
    # fractional coordinates keep it; test_energy_lj's per-particle
    # energies and forces against jax-md (every backend and layout) keep
    # the LJ check.
    "tests/lists/test_neighbors.py::test_fractional_coordinates_orthorhombic",
    "tests/lists/test_neighbors.py::test_lennard_jones_energy_and_forces_equal_jax_md",
    # NVE with a jaxrt list: test_scene's builtin LJ and
    # tests/stability/test_nve_drift keep it.
    "tests/lists/test_neighbors.py::test_nve_in_fori_loop_with_jaxrt_list",
    # test_never_wrong.py: [cell-0] keeps a pair across a face; every face
    # and corner: test_neighbors' and stability's faces-and-corners cases.
    "tests/lists/test_never_wrong.py::test_two_particles_across_each_face[cell-1]",
    "tests/lists/test_never_wrong.py::test_two_particles_across_each_face[cell-2]",
    # tests/stability/test_far_from_origin keeps positions far away.
    "tests/lists/test_never_wrong.py::test_positions_near_a_million_in_free_space",
    # One layout or value of each keeps the property.
    "tests/lists/test_never_wrong.py::test_all_particles_at_one_point[NeighborListFormat.OrderedSparse]",
    "tests/lists/test_never_wrong.py::test_one_particle_and_an_empty_list[cell-NeighborListFormat.Sparse]",
    "tests/lists/test_never_wrong.py::test_all_particles_at_one_point[NeighborListFormat.Sparse]",
    "tests/lists/test_never_wrong.py::test_one_particle_and_an_empty_list[cell-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_never_wrong.py::test_box_sides_just_below_a_power_of_two_stay_orthorhombic[cell-3.999996]",
    "tests/lists/test_never_wrong.py::test_box_sides_just_below_a_power_of_two_stay_orthorhombic[cell-7.99]",
    "tests/lists/test_never_wrong.py::test_triclinic_boxes_in_every_layout[False-NeighborListFormat.Sparse-cell]",
    "tests/lists/test_never_wrong.py::test_triclinic_boxes_in_every_layout[False-NeighborListFormat.OrderedSparse-cell]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[twice-<lambda>-False-NeighborListFormat.Sparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[half-<lambda>-False-NeighborListFormat.Sparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[anisotropic-metric-False-NeighborListFormat.Sparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[anisotropic periodic-metric-True-NeighborListFormat.Sparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[soft core-soft_core-False-NeighborListFormat.Sparse]",
    # test_energy_lj.py: [jaxrt:cell] keeps grad through a scan with
    # updates; test_bvh's front update in a scan keeps bvh's list there.
    "tests/energy/test_energy_lj.py::test_grad_through_scan_with_update_for_every_backend[jaxrt:brute]",
    "tests/energy/test_energy_lj.py::test_grad_through_scan_with_update_for_every_backend[jaxrt:bvh]",
    "tests/energy/test_energy_lj.py::test_grad_through_scan_with_update_for_every_backend[jaxrt:bvh-unsorted]",
    "tests/energy/test_energy_lj.py::test_grad_through_scan_with_update_for_every_backend[jaxrt:spheres]",
    "tests/energy/test_energy_lj.py::test_grad_through_scan_with_update_for_every_backend[jaxrt:squares]",
    # test_fused.py: [cell-2.05], [kernel-2.05], [fine-xla-2.05]
    # keep each pair once in small boxes; the kernel's images keep 3D
    # float32 periodic and float64 slab.
    "tests/energy/test_fused.py::test_cell_small_periodic_boxes_count_each_pair_once[cell-2.6]",
    "tests/energy/test_fused.py::test_cell_small_periodic_boxes_count_each_pair_once[cell-3.4]",
    "tests/energy/test_fused.py::test_cell_small_periodic_boxes_count_each_pair_once[cell-7.0]",
    "tests/energy/test_fused.py::test_cell_small_periodic_boxes_count_each_pair_once[tiles-3.4]",
    "tests/energy/test_fused.py::test_run_images_on_faces_and_corners[3-float64-tiles-periodic]",
    "tests/energy/test_fused.py::test_run_images_on_faces_and_corners[2-float64-kernel-periodic]",
    # test_delaunay.py: [True-Dense] keeps it.
    "tests/backends/test_delaunay.py::test_random_scene_and_a_jitted_move_are_exact[False-NeighborListFormat.OrderedSparse]",
    # test_scene.py: test_lj_only_has_no_sph and the wall box keep "a
    # scene simulates only the effects it calls for".
    "tests/sim/test_scene.py::test_equal_radii_no_radius_handling",
    # mixed boundaries: test_neighbors' and test_cell_kernel's lists.
    "tests/sim/test_scene.py::test_mixed_boundaries_wrap_periodic_axis_only",
    # test_accuracy.py: test_radii_sweep_rows_have_their_own_reference
    # keeps the radii knob's rows.
    "tests/tools/test_accuracy.py::test_radii_knob_one_grid_misses_no_pair",
    # test_cli.py: [mixed-3d] keeps the trajectory read by ASE.
    "tests/tools/test_cli.py::test_trajectory_reads_in_ase[2d]",
    # test_cell_kernel.py: [random-xla] and [lattice at cutoff-interpret]
    # keep "OrderedSparse rows hold only lower neighbours" on both
    # engines; the other scenes are kept by the kernel's brute-force
    # comparison above and by test_neighbors' layouts.
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[faces-interpret]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[faces-xla]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[lattice at cutoff-xla]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[coincident-interpret]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[coincident-xla]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[box of 2.01 cutoffs-interpret]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[box of 2.01 cutoffs-xla]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[random-interpret]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[2d free-interpret]",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[2d free-xla]",
    # test_fused.py: bvh's list-free energy is kept by
    # test_radii_match_list_path[bvh-periodic], test_energy_matches_jax_md_float64[bvh]
    # and test_parameter_gradients_match_list_path[bvh]; [cell] keeps jit, scan and 2D.
    "tests/energy/test_fused.py::test_energy_forces_match_list_path_float64[bvh-periodic]",
    "tests/energy/test_fused.py::test_jit_scan_and_2d[bvh]",
    # [cell-2.05], [kernel-2.05] and [fine-xla-2.05] keep each pair once in
    # small boxes on every engine.
    "tests/energy/test_fused.py::test_cell_small_periodic_boxes_count_each_pair_once[fine-2.6]",
    "tests/energy/test_fused.py::test_cell_small_periodic_boxes_count_each_pair_once[fine-xla-3.4]",
    # test_neighbors.py: [0.5-Sparse] and [1.25-Dense] keep the trim of
    # a wider build, for a padded and a tight capacity.
    "tests/lists/test_neighbors.py::test_allocate_trims_its_wider_build_to_exactly_the_sized_list[0.5-NeighborListFormat.Dense]",
    "tests/lists/test_neighbors.py::test_allocate_trims_its_wider_build_to_exactly_the_sized_list[0.5-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_neighbors.py::test_allocate_trims_its_wider_build_to_exactly_the_sized_list[1.25-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_neighbors.py::test_allocate_trims_its_wider_build_to_exactly_the_sized_list[1.25-NeighborListFormat.Sparse]",
    # test_bvh.py: one case per format and periodicity is kept among
    # [True-Dense], [False-Sparse] (random scenes), the same for clustered
    # boxes, and [Dense] for faces and corners and the generic method.
    "tests/backends/test_bvh.py::test_random_scene_matches_jax_md_brute_force_and_cell[False-NeighborListFormat.Dense]",
    "tests/backends/test_bvh.py::test_random_scene_matches_jax_md_brute_force_and_cell[False-NeighborListFormat.OrderedSparse]",
    "tests/backends/test_bvh.py::test_random_scene_matches_jax_md_brute_force_and_cell[True-NeighborListFormat.Sparse]",
    "tests/backends/test_bvh.py::test_random_scene_matches_jax_md_brute_force_and_cell[True-NeighborListFormat.OrderedSparse]",
    "tests/backends/test_bvh.py::test_clustered_boxes_give_the_same_lists[False-NeighborListFormat.Dense]",
    "tests/backends/test_bvh.py::test_clustered_boxes_give_the_same_lists[False-NeighborListFormat.OrderedSparse]",
    "tests/backends/test_bvh.py::test_clustered_boxes_give_the_same_lists[True-NeighborListFormat.Sparse]",
    "tests/backends/test_bvh.py::test_clustered_boxes_give_the_same_lists[True-NeighborListFormat.OrderedSparse]",
    "tests/backends/test_bvh.py::test_particles_on_faces_and_corners_periodic[NeighborListFormat.OrderedSparse]",
    "tests/backends/test_bvh.py::test_particles_on_faces_and_corners_periodic[NeighborListFormat.Sparse]",
    "tests/backends/test_bvh.py::test_generic_method_backend_wraps_any_rt_method[NeighborListFormat.OrderedSparse]",
    "tests/backends/test_bvh.py::test_generic_method_backend_wraps_any_rt_method[NeighborListFormat.Sparse]",
    # test_never_wrong.py: each metric keeps its Dense case; the layouts
    # are kept by the Euclidean cases. test_neighbors.py: the periodic
    # random scene keeps [Dense], the free one every layout. Triclinic
    # periodic boxes keep [Dense] and [Sparse].
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[twice-<lambda>-False-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[half-<lambda>-False-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[soft core-soft_core-False-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[anisotropic-metric-False-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_never_wrong.py::test_non_euclidean_metrics_match_jax_md[anisotropic periodic-metric-True-NeighborListFormat.OrderedSparse]",
    "tests/lists/test_neighbors.py::test_random_scene_matches_jax_md_and_brute_force[True-NeighborListFormat.OrderedSparse-cell]",
    "tests/lists/test_neighbors.py::test_random_scene_matches_jax_md_and_brute_force[True-NeighborListFormat.Sparse-cell]",
    "tests/lists/test_never_wrong.py::test_triclinic_boxes_in_every_layout[True-NeighborListFormat.OrderedSparse-cell]",
    # Default-suite time, third pass: variants whose compiled programs no
    # other default case shares (each names the case that keeps its
    # property). Pallas' interpreter keeps [random] and the lattice at the
    # cutoff in the OrderedSparse rows' test; the portable path keeps
    # mixed boundaries (test_neighbors' per-axis box) and coincident
    # points (test_neighbors, stability's coincident cases).
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[lattice at cutoff]",
    "tests/backends/test_cell_kernel.py::test_kernel_matches_brute_force_and_the_portable_path[coincident]",
    "tests/backends/test_cell_kernel.py::test_kernel_mixed_boundaries_and_per_axis_box",
    "tests/backends/test_cell_kernel.py::test_ordered_sparse_rows_hold_only_lower_neighbours[random-xla]",
    "tests/backends/test_cell_kernel.py::test_kernel_sparse_layouts_and_self_pairs[NeighborListFormat.Sparse-False]",
    # [cell-periodic] and [kernel-periodic] keep the list path's float64
    # forces; the kernel's slab images keep slabs.
    "tests/energy/test_fused.py::test_energy_forces_match_list_path_float64[brute-slab]",
    # One edge layout each: SPH keeps OrderedSparse, LJ keeps Sparse.
    "tests/energy/test_energy_sph.py::test_edge_layout_sums_scatter_materialized_edges_in_reverse_only[NeighborListFormat.Sparse]",
    "tests/energy/test_energy_lj.py::test_edge_layout_gradients_scatter_materialized_edges[NeighborListFormat.OrderedSparse]",
    # SPH against the all-pairs oracle keeps [jaxrt:cell-Dense] and every
    # other backend's layouts; the cell list's Sparse and OrderedSparse
    # edges are kept by LJ's per-particle test and SPH's edge sums.
    "tests/energy/test_energy_sph.py::test_density_and_forces_match_all_pairs_oracle[jaxrt:cell-NeighborListFormat.Sparse]",
    "tests/energy/test_energy_sph.py::test_density_and_forces_match_all_pairs_oracle[jaxrt:cell-NeighborListFormat.OrderedSparse]",
    # test_small_box keeps every small box, layout and backend.
    "tests/lists/test_neighbors.py::test_small_periodic_boxes[2.01]",
    # [eam] keeps jax-md's wrappers that drop fractional_coordinates.
    "tests/lists/test_neighbors.py::test_fractional_positions_the_wrapper_does_not_announce[stillinger-weber]",
    # test_never_wrong: the triclinic Sparse rows of the cell list are kept
    # by test_small_box's [triclinic fractional-cell-Sparse].
    "tests/lists/test_never_wrong.py::test_triclinic_boxes_in_every_layout[True-NeighborListFormat.Sparse-cell]",
    # The tiny sweep keeps `jaxrt accuracy`; tests/pairs keep jaxrt.pairs.
    "tests/tools/test_accuracy.py::test_pairs_value_runs_lj_on_jaxrt_pairs_with_the_lists_forces",
}


if pytest is not None:
    @pytest.hookimpl(tryfirst=True)
    def pytest_collection_modifyitems(config, items):
        """Mark `LONG_CASES` slow (before ``-m`` deselects); a name that
        no longer matches a test is an error, not a silent no-op."""
        seen = set()
        for item in items:
            if item.nodeid in LONG_CASES:
                item.add_marker(pytest.mark.slow)
                seen.add(item.nodeid)
        if config.getoption("keyword") or any("::" in str(a)
                                               for a in config.args):
            return  # a selection of cases: the others are not collected
        files = {item.nodeid.split("::")[0] for item in items}
        stale = {c for c in LONG_CASES - seen if c.split("::")[0] in files}
        if stale:
            raise pytest.UsageError(
                "tests/conftest.py LONG_CASES names tests that do not "
                f"exist: {sorted(stale)}")
