"""`jaxrt.energy.lennard_jones_fused` / `lennard_jones_perse_step` (seed 003
§3.2, ORCS) against the list path and jax-md.

Tolerances: in float64 the fused sums and the list path add the same pair
terms in different orders (per owner vs per row; ``high_precision_sum``
of per-particle vs per-pair values), so they agree to a few ulps of the
largest terms: ``rtol = 1e-12`` on energies and ``1e-10`` of the largest
force on forces (the terms are O(10) while single pairs reach O(1e3)
at the closest distances of these fluids). float32 runs are checked
against the float64 reference at ``rtol = 1e-4`` (energies are sums of
~10^3 terms of mixed sign) and ``2e-3`` of the largest force.

Nothing here names a device: on a GPU the same tests run the CUDA kernels.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import energy as jmd_energy
from jax_md import partition, space
from scenes import GEOMETRIES, fluid, slab_displacement

import jaxrt
from jaxrt.backends.cell import grid as cell_grid
from jaxrt.energy.listfree.lj import CellSums
from jaxrt.energy import (FusedInputError, HigherOrderError,
                          lennard_jones_fused, lennard_jones_neighbor_list,
                          lennard_jones_perse_step, lennard_jones_truncated)

BACKENDS = ("bvh", "brute", "cell")
# The cell walk as one kernel (`jaxrt.backends.cell.kernel.pair_sums`): compiled on
# a GPU, in Pallas' interpreter elsewhere; "kernel" in the parameter lists.
ON_GPU = jax.default_backend() in ("gpu", "cuda")
KERNEL = jaxrt.backends.Cell(kernel="pallas" if ON_GPU else "interpret")


# The same kernel in its cluster layout (tiles of candidates per program of
# particles), small tiles so that several are walked per run.
TILES = CellSums(kernel=KERNEL.kernel, block=16, tile=16)
# The thread walk two candidates per step, on cells half a cutoff across (25
# runs in 3D); and the array walk on those cells.
FINE = CellSums(kernel=KERNEL.kernel, unroll=2, across=2)
FINE_XLA = CellSums(kernel="xla", across=2)


def pick(backend):
    return {"kernel": KERNEL, "tiles": TILES, "fine": FINE,
            "fine-xla": FINE_XLA}.get(backend, backend)

E_RTOL, F_RTOL = 1e-12, 1e-10
SLOW = pytest.mark.slow
# The default run keeps one case per property (bvh, the kernels under
# test); the rest run with -m slow.
BRUTE_SLOW = ("bvh", pytest.param("brute", marks=SLOW))



def list_energy(displacement, box, periodic, R0, radii=None, **kw):
    """jaxrt's list path (Dense, cell list; bvh with radii): energy_fn(R),
    on a list allocated at ``R0`` and updated (rebuilt) at every R."""
    backend = "cell" if radii is None else "bvh"
    nfn, efn = lennard_jones_neighbor_list(
        displacement, box if box is not None else 1.0, dr_threshold=0.0,
        format=partition.Dense, radii=radii, capacity_multiplier=2.0,
        neighbor_list_fn=functools.partial(jaxrt.neighbor_list,
                                           backend=pick(backend),
                                           periodic=periodic or (box is not None)),
        **kw)
    nbrs = nfn.allocate(R0)

    def energy(R, **params):
        list_kw = {"radii": params["radii"]} if "radii" in params else {}
        return efn(R, nbrs.update(R, **list_kw), **params)
    return energy


def close(a, b, rtol):
    a, b = np.asarray(a), np.asarray(b)
    scale = max(float(np.max(np.abs(b), initial=0.0)), 1e-300)
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


def assert_periodic_matches_brute(R, side, backend):
    """The fused energy of ``backend`` in a periodic cube of ``side`` against
    brute force: the same pair count exactly, energy and forces to
    E_RTOL / F_RTOL."""
    displacement, _ = space.periodic(side)
    fused = lennard_jones_fused(displacement, side, backend=pick(backend))
    brute = lennard_jones_fused(displacement, side, backend="brute")
    assert int(fused.sums(R).count) == int(brute.sums(R).count)
    close(fused(R), brute(R), E_RTOL)
    close(jax.grad(fused)(R), jax.grad(brute)(R), F_RTOL)


@pytest.mark.parametrize("backend, geometry", [
    ("bvh", "periodic"), ("brute", "slab"), ("cell", "periodic"),
    ("kernel", "periodic"), pytest.param("kernel", "slab", marks=SLOW),
    pytest.param("kernel", "free", marks=SLOW),
    pytest.param("tiles", "periodic", marks=SLOW),
    pytest.param("tiles", "slab", marks=SLOW),
    pytest.param("fine-xla", "slab", marks=SLOW),
    pytest.param("fine", "periodic", marks=SLOW),
    pytest.param("fine", "free", marks=SLOW),
    pytest.param("tiles", "free", marks=SLOW),
    pytest.param("cell", "free", marks=SLOW),
    pytest.param("cell", "slab", marks=SLOW),
    pytest.param("bvh", "free", marks=SLOW), pytest.param("bvh", "slab", marks=SLOW),
    pytest.param("brute", "periodic", marks=SLOW),
    pytest.param("brute", "free", marks=SLOW)])
def test_energy_forces_match_list_path_float64(x64, backend, geometry):
    R, side = fluid()
    R = jnp.asarray(R)
    displacement, box, periodic = GEOMETRIES[geometry](side)
    fused = lennard_jones_fused(displacement, box, backend=pick(backend),
                                periodic=periodic)
    ref = list_energy(displacement, box, periodic, R)
    e, e_ref = fused(R), ref(R)
    assert e.dtype == jnp.float64
    close(e, e_ref, E_RTOL)
    close(jax.grad(fused)(R), jax.grad(ref)(R), F_RTOL)


@pytest.mark.parametrize("backend", BRUTE_SLOW)
def test_energy_matches_jax_md_float64(x64, backend):
    R, side = fluid()
    R = jnp.asarray(R)
    displacement, _ = space.periodic(side)
    # jax-md casts Python floats to float32: give it float64 arrays.
    f64 = functools.partial(jnp.asarray, dtype=jnp.float64)
    nfn, efn = jmd_energy.lennard_jones_neighbor_list(
        displacement, side, sigma=f64(1.1), epsilon=f64(0.7),
        r_onset=2.0, r_cutoff=2.4, dr_threshold=0.0, format=partition.Dense)
    # ... and its r_onset / r_cutoff too (maybe_downcast before they are
    # multiplied by max(sigma)): ours get the same float32-rounded value.
    fused = lennard_jones_fused(displacement, side, sigma=1.1, epsilon=0.7,
                                r_onset=2.0, r_cutoff=float(np.float32(2.4)),
                                backend=pick(backend))
    close(fused(R), efn(R, nfn.allocate(R)), E_RTOL)
    close(jax.grad(fused)(R), jax.grad(efn)(R, nfn.allocate(R)), F_RTOL)


@pytest.mark.parametrize("backend, geometry", [
    ("bvh", "periodic"), pytest.param("bvh", "free", marks=SLOW),
    ("cell", "periodic"), pytest.param("cell", "free", marks=SLOW),
    pytest.param("kernel", "periodic", marks=SLOW),
    pytest.param("kernel", "free", marks=SLOW),
    pytest.param("tiles", "periodic", marks=SLOW),
    pytest.param("brute", "periodic", marks=SLOW),
    pytest.param("brute", "free", marks=SLOW)])
def test_radii_match_list_path(x64, backend, geometry):
    R, side = fluid(n_side=5, density=0.4)
    R = jnp.asarray(R)
    radii = jnp.asarray(np.random.default_rng(1).uniform(0.8, 2.6, len(R)))
    displacement, box, periodic = GEOMETRIES[geometry](side)
    fused = lennard_jones_fused(displacement, box, radii=radii,
                                backend=pick(backend), periodic=periodic)
    ref = list_energy(displacement, box, periodic, R, radii=radii)
    close(fused(R), ref(R), E_RTOL)
    close(jax.grad(fused)(R), jax.grad(ref)(R), F_RTOL)
    # Smaller radii at call time (the factory's largest bounds the search).
    small = radii * 0.9
    close(fused(R, radii=small), ref(R, radii=small), E_RTOL)


@pytest.mark.parametrize("backend", BRUTE_SLOW)
def test_parameter_gradients_match_list_path(x64, backend):
    R, side = fluid()
    R = jnp.asarray(R)
    displacement, _ = space.periodic(side)
    fused = lennard_jones_fused(displacement, side, backend=pick(backend))
    ref = list_energy(displacement, side, None, R)
    for name in ("sigma", "epsilon"):
        value = jnp.asarray(0.95 if name == "sigma" else 1.3)
        g = jax.grad(lambda v: fused(R, **{name: v}))(value)
        g_ref = jax.grad(lambda v: ref(R, **{name: v}))(value)
        assert np.isfinite(g)
        close(g, g_ref, E_RTOL)
    both = jax.grad(lambda R, s, e: fused(R, sigma=s, epsilon=e),
                    argnums=(0, 1, 2))(R, 1.0, 1.0)
    assert all(np.all(np.isfinite(b)) for b in both)


@pytest.mark.parametrize("backend", BRUTE_SLOW + ("cell", "kernel", pytest.param(
    "tiles", marks=SLOW)))
def test_coincident_and_exact_cutoff_pairs(x64, backend):
    side = 10.0
    R = jnp.asarray([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0],   # coincident
                     [5.0, 5.0, 5.0], [7.5, 5.0, 5.0],   # exactly r_cutoff
                     [1.0, 6.0, 6.0], [2.2, 6.0, 6.0]])  # inside the switch
    displacement, _ = space.periodic(side)
    fused = lennard_jones_fused(displacement, side, backend=pick(backend))
    g = jax.grad(fused)(R)
    assert np.all(np.isfinite(g))
    np.testing.assert_array_equal(np.asarray(g[:4]), 0.0)
    # Only the inside pair counts: at exactly the cutoff the energy is 0
    # (the lists' strict d < r_cutoff).
    r = jnp.asarray(1.2)
    pair = lennard_jones_truncated(r, r_onset=2.0, r_cutoff=2.5)
    close(fused(R), pair, E_RTOL)
    close(g[5, 0], jax.grad(lennard_jones_truncated)(r, r_onset=2.0,
                                                      r_cutoff=2.5), F_RTOL)


@pytest.mark.parametrize("backend", BRUTE_SLOW + (
    "cell", pytest.param("kernel", marks=SLOW),
    pytest.param("tiles", marks=SLOW)))
def test_jit_scan_and_2d(x64, backend):
    R, side = fluid(n_side=10, dim=2)
    R = jnp.asarray(R)
    displacement, shift = space.periodic(side)
    fused = lennard_jones_fused(displacement, side, backend=pick(backend))
    ref = list_energy(displacement, side, None, R)
    close(jax.jit(fused)(R), ref(R), E_RTOL)

    def descend(R, _):
        R = shift(R, -1e-4 * jax.grad(fused)(R))
        return R, fused(R)

    R_end, energies = jax.lax.scan(descend, R, None, length=5)
    close(energies[-1], ref(R_end), E_RTOL)
    assert np.all(np.diff(np.asarray(energies)) < 0)  # descent lowers E


@pytest.mark.parametrize("backend, side_over_cutoff", [
    *[("cell", s) for s in (2.05, 2.6, 3.4, 7.0)],
    ("kernel", 2.05), ("tiles", 3.4), ("fine", 2.6),
    *[pytest.param("fine", s, marks=SLOW) for s in (2.05, 3.4)],
    *[("fine-xla", s) for s in (2.05, 3.4)],
    *[pytest.param("kernel", s, marks=SLOW) for s in (2.6, 3.4, 7.0)],
    *[pytest.param("tiles", s, marks=SLOW) for s in (2.05, 2.6, 7.0)]])
def test_cell_small_periodic_boxes_count_each_pair_once(x64, backend,
                                                        side_over_cutoff):
    """Boxes of 2 to 7 cutoffs: the grid has one to a few cells across, so
    stencil offsets alias; each pair must still be met once from each side
    (a doubled run would double the energy). Against brute force, exact
    pair counts."""
    r_cutoff = 2.5
    side = side_over_cutoff * r_cutoff
    n = max(8, int(0.5 * side ** 3))
    R = jnp.asarray(np.random.default_rng(3).uniform(0, side, (n, 3)))
    assert_periodic_matches_brute(R, side, backend)


def test_vmap(x64):
    (R0, side), (R1, _) = fluid(n_side=5, seed=0), fluid(n_side=5, seed=1)
    Rs = jnp.stack([jnp.asarray(R0), jnp.asarray(R1)])
    displacement, _ = space.periodic(side)
    for backend in BACKENDS:
        fused = lennard_jones_fused(displacement, side, backend=pick(backend))
        close(jax.vmap(fused)(Rs), jnp.stack([fused(Rs[0]), fused(Rs[1])]),
              E_RTOL)
        close(jax.vmap(jax.grad(fused))(Rs)[1], jax.grad(fused)(Rs[1]),
              F_RTOL)


@pytest.mark.parametrize("backend", BACKENDS)
def test_higher_order_raises_naming_list_path(x64, backend):
    R, side = fluid(n_side=4, density=0.5)
    R = jnp.asarray(R)
    displacement, _ = space.periodic(side)
    fused = lennard_jones_fused(displacement, side, backend=pick(backend))
    with pytest.raises(HigherOrderError, match="lennard_jones_neighbor_list"):
        jax.hessian(fused)(R)
    with pytest.raises(HigherOrderError, match="lennard_jones_neighbor_list"):
        jax.grad(jax.grad(lambda s: fused(R, sigma=s)))(1.0)
    with pytest.raises(HigherOrderError):
        jax.grad(lambda s: jnp.sum(jax.grad(fused)(R, sigma=s) ** 2))(1.0)


def test_bad_arguments_raise():
    R, side = fluid(n_side=4, density=0.5)
    R = jnp.asarray(R, jnp.float32)
    displacement, _ = space.periodic(side)
    fused = lennard_jones_fused(displacement, side, backend="brute")
    with pytest.raises(TypeError, match="sigmaa"):
        fused(R, sigmaa=1.0)
    fused(R, kT=1.0)  # jax_md.simulate passes kT on
    with pytest.raises(FusedInputError, match="NaN"):
        fused(R.at[3, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="radii was given"):
        fused(R, radii=jnp.ones(len(R)))
    with pytest.raises(ValueError, match="half the periodic box"):
        lennard_jones_fused(displacement, side, r_cutoff=side)(R)
    with pytest.raises(ValueError, match="scalar sigma"):
        lennard_jones_fused(displacement, side, sigma=jnp.ones(len(R)))
    with pytest.raises(ValueError, match="r_onset"):
        lennard_jones_fused(displacement, side, r_onset=3.0)
    with pytest.raises(ValueError, match="backend"):
        lennard_jones_fused(displacement, side, backend="nope")
    with pytest.raises(ValueError, match="radius_classes"):
        lennard_jones_fused(displacement, side,
                            backend=jaxrt.backends.Cell(radius_classes=1))
    if not ON_GPU:
        with pytest.raises(ValueError, match="kernel='pallas'.*CUDA"):
            lennard_jones_fused(displacement, side,
                                backend=jaxrt.backends.Cell(kernel="pallas"))
    with pytest.raises(ValueError, match="disagrees"):
        lennard_jones_fused(space.free()[0], side, periodic=True)(R)
    radii = jnp.ones(len(R))
    with_radii = lennard_jones_fused(displacement, side, radii=radii,
                                     backend="brute")
    with pytest.raises(FusedInputError, match="radii"):
        with_radii(R, radii=radii * 2)
    # Under jit the error is a NaN energy.
    assert np.isnan(jax.jit(lambda R: with_radii(R, radii=radii * 2))(R))


@pytest.mark.parametrize("backend, geometry", [
    ("bvh", "periodic"), ("bvh", "free"), ("kernel", "periodic"),
    pytest.param("kernel", "free", marks=SLOW), ("tiles", "free"),
    ("fine", "periodic")])
def test_float32_within_tolerance(geometry, backend):
    R, side = fluid()
    displacement, box, periodic = GEOMETRIES[geometry](side)
    with jax.enable_x64(True):
        ref = lennard_jones_fused(displacement, box, backend="brute",
                                  periodic=periodic)
        e64, f64 = ref(jnp.asarray(R)), jax.grad(ref)(jnp.asarray(R))
    fused = lennard_jones_fused(displacement, box, periodic=periodic,
                                backend=pick(backend))
    R32 = jnp.asarray(R, jnp.float32)
    e, g = fused(R32), jax.grad(fused)(R32)
    assert e.dtype == jnp.float32 and g.dtype == jnp.float32
    np.testing.assert_allclose(float(e), float(e64), rtol=1e-4)
    close(g, f64, 2e-3)


@pytest.mark.parametrize("backend", BRUTE_SLOW)
def test_perse_step_matches_leapfrog_on_list_forces(x64, backend):
    R, side = fluid()
    R = jnp.asarray(R)
    V = jnp.asarray(np.random.default_rng(2).normal(0, 0.3, R.shape))
    displacement, shift = space.periodic(side)
    dt, mass = 1e-3, 1.5
    step = lennard_jones_perse_step(displacement, side, dt=dt, mass=mass,
                                    backend=pick(backend))
    ref = list_energy(displacement, side, None, R)
    V_ref = V - dt / mass * jax.grad(ref)(R)
    R_ref = shift(R, dt * V_ref)
    R1, V1 = step(R, V)
    close(V1, V_ref, F_RTOL)
    close(R1, R_ref, 1e-14)
    _, _, e = step.energy(R, V)
    close(e, ref(R), E_RTOL)

    # Two steps in a scan: the kept tree is refit to the new positions.
    def body(carry, _):
        return step(*carry), None

    (R2, V2), _ = jax.lax.scan(body, (R, V), None, length=2)
    V_ref2 = V_ref - dt / mass * jax.grad(ref)(R_ref)
    close(V2, V_ref2, F_RTOL)


def test_perse_refuses_radii():
    displacement, _ = space.periodic(10.0)
    with pytest.raises(ValueError, match="equal radii"):
        lennard_jones_perse_step(displacement, 10.0, dt=1e-3,
                                 radii=jnp.ones(4))


def test_sums_count_pairs(x64):
    R, side = fluid(n_side=5)
    R = jnp.asarray(R)
    displacement, _ = space.periodic(side)
    fused = lennard_jones_fused(displacement, side)
    s = fused.sums(R)
    d = np.asarray(R)[:, None] - np.asarray(R)[None]
    d -= side * np.round(d / side)
    r2 = np.sum(d * d, -1)
    np.fill_diagonal(r2, np.inf)
    assert int(s.count) == int(np.sum(r2 < 2.5 ** 2)) // 2
    assert int(s.error) == 0
    close(s.energy, fused(R), 0)
    # The same sums through the custom VJP: XLA:GPU's default level may
    # fuse the backward's scaling differently (one ulp seen on the H200).
    close(-s.forces, jax.grad(fused)(R), 4 * np.finfo(np.float64).eps)


@SLOW
def test_fit_sigma_epsilon_on_energies(x64):
    """A training loop (`lax.scan` of gradient steps under `jit`) recovers
    sigma and epsilon from snapshot energies, as examples/fit_lj.py does
    on lists (on energies only: force matching needs second derivatives)."""
    # Different disorder, so sigma and epsilon are not traded for each other.
    snaps = [fluid(n_side=5, density=0.9, seed=s, jitter=j)
             for s, j in enumerate((0.02, 0.1, 0.2, 0.3))]
    side = snaps[0][1]
    Rs = jnp.stack([jnp.asarray(R) for R, _ in snaps])
    displacement, _ = space.periodic(side)
    fused = lennard_jones_fused(displacement, side)
    target = jnp.stack([fused(R) for R in Rs])

    def loss(p):
        e = jnp.stack([fused(R, sigma=jnp.exp(p[0]), epsilon=jnp.exp(p[1]))
                       for R in Rs])
        return jnp.mean(((e - target) / target) ** 2)

    optax = pytest.importorskip("optax")
    opt = optax.adam(0.01)

    @jax.jit
    def fit(p):
        def step(carry, _):
            p, state = carry
            updates, state = opt.update(jax.grad(loss)(p), state)
            return (optax.apply_updates(p, updates), state), None
        return jax.lax.scan(step, (p, opt.init(p)), None, length=300)[0][0]

    p0 = jnp.log(jnp.asarray([0.97, 1.2]))
    p = fit(p0)
    assert loss(p) < 1e-3 * loss(p0)
    np.testing.assert_allclose(np.exp(np.asarray(p)), [1.0, 1.0], atol=1e-3)


@SLOW
def test_scene_integrator_perse_matches_verlet(x64):
    """A scene with integrator 'perse' follows the Verlet scene's
    trajectory (leapfrog = velocity Verlet positions), with no list."""
    import dataclasses

    from jaxrt import sim
    scene = dataclasses.replace(sim.lj_fluid(n=216, dt=0.002), dtype="float64")
    perse = dataclasses.replace(
        scene, integrator=sim.Integrator(dt=0.002, kind="perse"),
        neighbors=sim.Neighbors(backend="bvh"))
    verlet, fused = sim.compile_scene(scene), sim.compile_scene(perse)
    assert fused.neighbor_fn is None
    (s0, n0), (f0, _) = verlet.init(), fused.init()
    s1, _, t_verlet = verlet.chunk(s0, n0, steps=10)
    f1, _, t_perse = fused.chunk(f0, None, steps=10)
    close(f1.position, s1.position, 1e-10)
    # The persé trace is at each step's start: shifted by one step.
    close(t_perse.potential[1:], t_verlet.potential[:-1], 1e-9)
    with pytest.raises(sim.SceneError, match="perse"):
        dataclasses.replace(perse, effects=perse.effects + (sim.Gravity(g=(0, 0, -1.0)),))


@pytest.mark.parametrize("launch", [
    {}, {"block": 16, "tile": 16}, {"unroll": 2, "across": 2},
    {"newton": True}, {"runs": "stored"}])
def test_kernel_lowers_for_cuda(x64, launch):
    """The fused kernel's layouts lower to Triton (energy and forces in one
    kernel): on a CPU too, by exporting for CUDA, so a primitive that
    Pallas' Triton lowering lacks fails here without a GPU."""
    from jax import export

    from jaxrt.backends.cell import kernel as _cell_kernel
    if _cell_kernel.pl is None:
        pytest.skip("this JAX has no Pallas Triton backend")
    R, side = fluid(n_side=6)
    displacement, _ = space.periodic(side)
    energy_fn = lennard_jones_fused(displacement, side,
                                    backend=CellSums(kernel="auto", **launch))
    for dtype in (jnp.float32, jnp.float64):
        exported = export.export(
            jax.jit(jax.value_and_grad(energy_fn)), platforms=["cuda"],
            disabled_checks=[export.DisabledSafetyCheck.custom_call(
                "__gpu$xla.gpu.triton")])(jnp.asarray(R, dtype))
        module = exported.mlir_module()
        assert module.count('name = "jaxrt_cell_pair_sums"') == 1


# ---------------------------------------------------------------------------
# Run images (issue #18): the kernel adds each run's periodic image to its
# particle once, instead of rounding every candidate's difference, on the
# axes where `fused.run_image_axes` proves it exact.


def image_axes(R, box, periodic=None, across=1, cutoff=2.5):
    """The static decision of the fused energy's kernel for these
    positions (`fused.run_image_axes`), on the padded 3 axes."""
    from jaxrt.energy.listfree import lj as fused
    R = np.asarray(R)
    box = float(box) if np.ndim(box) == 0 else np.asarray(box)
    dim = R.shape[1]
    displacement, _, _ = GEOMETRIES["periodic" if periodic is None
                                    else "slab"](box)
    params = fused.static_params(displacement, box, periodic, dim, 2.0,
                                  cutoff, cutoff)
    return fused.run_image_axes(params, len(R), across=across)


def test_run_image_axes_decisions():
    """Which axes take the runs' images: all where no stencil cell repeats
    (3 cells across, 10 along x), none where a free axis could coarsen the
    grid, per axis in between; the 2D energy's padding axis is flat."""
    big = np.zeros((343, 3))  # fluid(7): 7.54 = 3.01 cutoffs
    assert image_axes(big, 7.54) == (True, True, True)
    assert image_axes(big, 7.54, across=2) == (True, True, True)
    # 6.46 = 2.58 cutoffs: 2 cells across (aliased), 10 along x.
    assert image_axes(np.zeros((216, 3)), 6.46) == (True, False, False)
    assert image_axes(np.zeros((216, 3)), 6.2) == (False, False, False)
    assert image_axes(big, (7.54, 7.54, 6.0)) == (True, True, False)
    # A slab's free z can coarsen the grid without bound.
    assert image_axes(big, 7.54, (True, True, False)) == (False,) * 3
    assert image_axes(np.zeros((100, 2)), 8.0) == (True, True, False)
    # Sparse: the cell table's budget coarsens the grid (12 x 3 x 3 cells
    # need 108 > 4 N + 63).
    assert image_axes(np.zeros((11, 3)), 8.0) == (True, False, False)
    assert image_axes(np.zeros((12, 3)), 8.0) == (True, True, True)


def _traced_grid_cells():
    """``(query, cells)``: the fused grid's query in a periodic cube (cutoff
    2.5), and ``cells(side, R)``, `grid.grid`'s traced cells per axis
    (int32 ``(3,)``) for box ``side`` and positions ``R``."""
    from jaxrt.backends.contract import Geometry
    from jaxrt.energy.listfree import lj as fused
    query = fused.grid_query(fused.Params(2.0, 2.5, 2.5, (True,) * 3,
                                            (1.0,) * 3))

    @jax.jit
    def cells(side, R):
        geometry = Geometry(side=side, scale=jnp.ones(3, side.dtype))
        return cell_grid.grid(R, geometry, query)[2]

    return query, cells


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_run_image_axes_bound_the_traced_grid(dtype):
    """Wherever `run_image_axes` takes an axis, `grid.grid` (traced,
    in the positions' dtype) has enough cells on it: boxes a hair around
    whole numbers of cells, and N around the coarsening budget."""
    from jaxrt.energy.listfree import lj as fused
    rng = np.random.default_rng(7)
    query, cells = _traced_grid_cells()

    need = np.array([10, 3, 3])
    taken = 0
    with jax.enable_x64(dtype == "float64"):
        for n in (12, 200, 2000):
            R = jnp.zeros((n, 3), dtype)
            for _ in range(30):
                k = rng.integers(2, 30, 3) / np.array([4, 1, 1])
                side = tuple(float(x) for x in 2.5 * (1 + 2.0 ** -10) * k
                             * (1 + rng.uniform(-1e-6, 1e-6, 3)))
                params = fused.Params(2.0, 2.5, 2.5, (True,) * 3, side)
                axes = np.array(fused.run_image_axes(params, n))
                got = np.asarray(cells(jnp.asarray(side, dtype), R))
                assert np.all(got[axes] >= need[axes]), (side, n, got)
                taken += int(np.sum(axes))
    assert taken > 100  # the rule is not just "never"


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_static_cells_bound_the_traced_grid(dtype):
    """Wherever `grid.static_cells` gives a table, the traced grid
    (in the positions' dtype) does not coarsen and its every key is below
    the table: boxes a hair around whole numbers of cells, N around the
    coarsening budget; and it gives none with a free axis."""
    from jaxrt.energy.listfree import lj as fused
    rng = np.random.default_rng(11)
    query, cells = _traced_grid_cells()

    given = 0
    with jax.enable_x64(dtype == "float64"):
        for n in (12, 200, 2000, 20000):
            R = jnp.zeros((n, 3), dtype)
            budget = cell_grid.table_size(n) - 1
            for _ in range(30):
                k = rng.integers(2, 60, 3) / np.array([4, 1, 1])
                side = tuple(float(x) for x in 2.5 * (1 + 2.0 ** -10) * k
                             * (1 + rng.uniform(-1e-6, 1e-6, 3)))
                table = cell_grid.static_cells(n, side, query)
                got = np.asarray(cells(jnp.asarray(side, dtype), R))
                uncoarsened = np.floor(np.array(side) * np.array([4, 1, 1])
                                       / (2.5 * (1 + 2.0 ** -10)))
                if table is not None:
                    given += 1
                    assert np.prod(got) < table, (side, n, got, table)
                    assert np.prod(got) <= budget
                    # no coarsening happened: the counts are the box's
                    assert np.all(np.abs(got - uncoarsened) <= 1), (side, got)
    assert given > 30  # the rule is not just "never"
    free = fused.grid_query(fused.Params(2.0, 2.5, 2.5, (True, False, True),
                                           (10.0,) * 3))
    assert cell_grid.static_cells(100, (10.0,) * 3, free) is None


def faces_and_corners(dim, dtype):
    """Particles on the box's faces and corners and a hair below 0 (which
    the grid's ``mod`` rounds to ``side``, into the top cell), on a lattice
    of fillers, in a box of 8 (3.2 cutoffs): every pair's distance is far
    from 0 and from the cutoff, so float32 and float64 count the same
    pairs. Returns (R in ``dtype``, side)."""
    side = 8.0
    tiny = 1e-9 if dtype == jnp.float32 else 1e-17  # below half an ulp of 8
    g = np.stack(np.meshgrid(*[np.array([1.0, 3.0, 5.0, 7.0])] * dim,
                             indexing="ij"), -1).reshape(-1, dim)
    if dim == 3:
        special = [[-tiny, -tiny, -tiny], [-tiny, 2, 2], [4, -tiny, 4],
                   [4, 4, -tiny], [0, 6, 6], [side, side, 4]]
    else:
        special = [[-tiny, -tiny], [4, -tiny], [-tiny, 4], [0, 6],
                   [side, 2]]
    R = np.concatenate([g, np.asarray(special)])
    d = np.abs(R[:, None] - R[None])
    d = np.minimum(d, side - d)
    r = np.sqrt(np.sum(d * d, -1))[~np.eye(len(R), dtype=bool)]
    assert r.min() > 1.0 and np.abs(r - 2.5).min() > 1e-2
    R = jnp.asarray(R, dtype)
    assert np.any(np.asarray(jnp.mod(R, jnp.asarray(side, dtype))) == side)
    return R, side


@pytest.mark.parametrize("dim, dtype, backend, geometry", [
    (3, "float32", "kernel", "periodic"), (3, "float64", "tiles", "periodic"),
    (2, "float64", "kernel", "periodic"), (3, "float64", "kernel", "slab"),
    pytest.param(3, "float64", "kernel", "periodic", marks=SLOW),
    pytest.param(3, "float64", "fine", "periodic", marks=SLOW),
    pytest.param(3, "float32", "tiles", "periodic", marks=SLOW),
    pytest.param(2, "float32", "kernel", "periodic", marks=SLOW)])
def test_run_images_on_faces_and_corners(x64, dim, dtype, backend, geometry):
    """The kernel with the runs' images (or, in the slab, without: its free
    z can coarsen the grid) against float64 brute force on the same
    positions: exact pair counts, energies and forces. A particle a hair
    below 0 sits at ``side`` in the top cell: walked with the position
    the grid binned, its runs' images are right (with positions wrapped
    into [0, side) by another rounding it would stand a box away from its
    cell, and its pairs through that face would be missed)."""
    dtype = jnp.dtype(dtype)
    R, side = faces_and_corners(dim, dtype)
    periodic = (True, True, False) if geometry == "slab" else None
    cell = pick(backend)
    axes = image_axes(R, side, periodic, across=getattr(cell, "across", 1))
    want = {"slab": (False,) * 3, "periodic": (True,) * dim}[geometry]
    assert axes[:dim] == want
    displacement, box, _ = GEOMETRIES[geometry](side)
    fused = lennard_jones_fused(displacement, box, backend=cell,
                                periodic=periodic)
    brute = lennard_jones_fused(displacement, box, backend="brute",
                                periodic=periodic)
    R64 = R.astype(jnp.float64)
    assert int(fused.sums(R).count) == int(brute.sums(R64).count)
    rtol = (E_RTOL, F_RTOL) if dtype == jnp.float64 else (1e-5, 1e-4)
    close(fused(R), brute(R64), rtol[0])
    close(jax.grad(fused)(R), jax.grad(brute)(R64), rtol[1])


@pytest.mark.parametrize("backend", ["kernel", pytest.param("tiles",
                                                            marks=SLOW)])
def test_run_images_dense_fluid(x64, backend):
    """The md_step fluid's box with every axis on the runs' images (3 cells
    across): against brute force, float64."""
    R, side = fluid(n_side=7)
    R = jnp.asarray(R)
    assert image_axes(R, side) == (True, True, True)
    assert_periodic_matches_brute(R, side, backend)


# ---------------------------------------------------------------------------
# Runs found by the kernel (issue #18): each thread reads its runs' ends in
# the cell-start table instead of a per-particle table of runs written
# beforehand. The same candidates in the same order with the same
# arithmetic, so the sums must agree bitwise, not to a tolerance.


RUN_CASES = {
    # name: (positions in [0, 1) scaled by the box, box, periodic axes)
    # aliased across (2 cells across < 3) and a whole x row (9 cells <= 9)
    "cube of 2.004 cutoffs": (np.random.default_rng(1).uniform(0, 1, (150, 3)),
                              (5.01,) * 3, None),
    # one aliased axis, one with runs through the images, a long x
    "mixed box": (np.random.default_rng(2).uniform(0, 1, (301, 3)),
                  (30.0, 5.1, 7.0), None),
    "slab": (np.random.default_rng(3).uniform(0, 1, (200, 3)), (9.0,) * 3,
             (True, True, False)),
    "free": (np.random.default_rng(4).uniform(0, 1, (199, 3)), (9.0,) * 3,
             (False,) * 3),
    "2d": (np.random.default_rng(5).uniform(0, 1, (170, 2)), (11.0, 7.0),
           None),
    # a cloud through the faces of a box that would coarsen its grid:
    # every axis compacted (`grid.grid`)
    "cluster": ((np.array([0.999, 0.5, 0.002]) + 0.01 * np.random.default_rng(
        6).standard_normal((200, 3))) % 1.0, (300.0,) * 3, None),
}


@pytest.mark.parametrize("case, layout", [
    ("cube of 2.004 cutoffs", "thread"),
    pytest.param("mixed box", "tiles", marks=SLOW),
    pytest.param("mixed box", "thread", marks=SLOW),
    pytest.param("slab", "thread", marks=SLOW),
    pytest.param("free", "tiles", marks=SLOW),
    pytest.param("2d", "thread", marks=SLOW),
    pytest.param("cube of 2.004 cutoffs", "tiles", marks=SLOW),
    pytest.param("cluster", "thread", marks=SLOW),
    pytest.param("cluster", "tiles", marks=SLOW)])
def test_runs_found_by_the_kernel_equal_the_stored_runs(x64, case, layout):
    """Energy, forces and pair count of ``Cell(runs="kernel")`` equal
    ``Cell(runs="stored")``'s bitwise, in boxes that alias stencil cells,
    make the x row one run, mix periodic and free axes, and in 2D, with N
    not a multiple of the program's particles (spare lanes); and both
    count brute force's pairs."""
    unit, box, periodic = RUN_CASES[case]
    box = np.asarray(box)
    R = jnp.asarray(unit * box)
    if periodic is None or any(periodic):
        displacement = (space.periodic(jnp.asarray(box))[0] if periodic is None
                        else slab_displacement(float(box[0])))
    else:
        displacement = space.free()[0]
    launch = {"thread": {}, "tiles": {"block": 16, "tile": 16}}[layout]
    got = {}
    for runs in ("kernel", "stored"):
        fused = lennard_jones_fused(
            displacement, jnp.asarray(box), periodic=periodic,
            backend=CellSums(kernel=KERNEL.kernel, runs=runs, **launch))
        sums = fused.sums(R)
        got[runs] = (np.asarray(sums.energy), np.asarray(sums.forces),
                     int(sums.count))
    for a, b in zip(got["kernel"], got["stored"]):
        assert np.array_equal(a, b), case
    brute = lennard_jones_fused(displacement, jnp.asarray(box),
                                periodic=periodic, backend="brute")
    assert got["kernel"][2] == int(brute.sums(R).count)


def test_cell_runs_option_is_checked():
    with pytest.raises(ValueError, match="runs='table'.*'kernel' or 'stored'"):
        CellSums(runs="table")


# ---------------------------------------------------------------------------
# Newton's third law in the thread walk (issue #18): each pair met once, from
# the upper half of the stencil, the partner's force added by an atomic.


def test_newton_meets_each_pair_once(x64):
    """`pair_sums(newton=True)` with a pair count for its only term: the
    per-particle counts add up to brute force's pair count once (twice
    without newton), and are not the symmetric split (so the half stencil
    really ran); the vector sums (here ``x_i - x_j`` summed) agree."""
    from jaxrt.backends.cell import kernel as _cell_kernel
    from jaxrt.energy.listfree import lj as fused_module
    R, side = fluid(n_side=7)
    R = jnp.asarray(R)
    displacement, _ = space.periodic(side)
    params = fused_module.static_params(displacement, side, None, 3, 2.0,
                                         2.5, 2.5)
    order, runs, images = fused_module.cell_runs(R, params)
    assert images.axes == (True, True, True)

    def count_terms(d2, valid, scalars, mine, theirs, d):
        keep = valid & (d2 < 2.5 ** 2)
        return keep.astype(d2.dtype), (keep.astype(d2.dtype),)

    got = {}
    for newton in (False, True):
        got[newton] = _cell_kernel.pair_sums(
            images.position, None, jnp.asarray(params.side), jnp.zeros((1,)),
            periodic=params.periodic, pair_terms=count_terms, n_sums=1,
            interpret=True, newton=newton, **images.kernel_options())
    pairs = len(brute_pair_set(np.asarray(R), side, 2.5))
    assert float(jnp.sum(got[False][1])) == 2 * pairs
    assert float(jnp.sum(got[True][1])) == pairs
    assert not np.array_equal(2 * got[True][1], got[False][1])
    close(got[True][0], got[False][0], 1e-12)


def brute_pair_set(R, side, cutoff):
    d = R[:, None] - R[None]
    d -= side * np.round(d / side)
    r2 = np.sum(d * d, -1)
    i, j = np.nonzero(np.triu(r2 < cutoff ** 2, 1))
    return set(zip(i.tolist(), j.tolist()))


NEWTON = CellSums(kernel=KERNEL.kernel, newton=True)


@pytest.mark.parametrize("case", [
    "fluid", pytest.param("faces", marks=SLOW),
    pytest.param("aliased box", marks=SLOW),
    pytest.param("radii", marks=SLOW), pytest.param("walls", marks=SLOW)])
def test_newton_matches_brute_force(x64, case):
    """``Cell(newton=True)`` against float64 brute force: pair counts
    exactly, energy and forces to E_RTOL / F_RTOL, where the half stencil
    runs (a fluid with every axis on the runs' images, particles on the
    faces and corners, per-particle radii, free axes) and where it cannot
    (a box of 2 cells across, which repeats stencil cells: the full
    walk)."""
    radii = None
    if case == "faces":
        R, side = faces_and_corners(3, jnp.float64)
    elif case == "aliased box":
        R, side = fluid(n_side=4, density=0.5)
    else:  # fluid, radii, walls
        R, side = fluid(n_side=7)
        R = jnp.asarray(R)
        if case == "radii":
            radii = jnp.asarray(np.random.default_rng(6).uniform(
                0.8, 1.2, len(R)))
    displacement, box = space.periodic(side)[0], side
    if case == "walls":  # free axes: no wrap, nothing repeats
        displacement, box = space.free()[0], None
    R = jnp.asarray(R)
    kw = {} if radii is None else {"radii": radii}
    fused = lennard_jones_fused(displacement, box, backend=NEWTON, **kw)
    brute = lennard_jones_fused(displacement, box, backend="brute", **kw)
    assert int(fused.sums(R).count) == int(brute.sums(R).count)
    close(fused(R), brute(R), E_RTOL)
    close(jax.grad(fused)(R), jax.grad(brute)(R), F_RTOL)


def test_newton_refuses_the_cluster_layout():
    with pytest.raises(ValueError, match="newton=True, tile=16"):
        CellSums(newton=True, tile=16)
