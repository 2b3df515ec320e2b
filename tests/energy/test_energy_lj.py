"""Lennard-Jones on neighbour lists (`jaxrt.energy.lj`) against jax-md.

Oracles: jax-md's `energy.lennard_jones_neighbor_list` on jax-md's own list,
jax-md's all-pairs `energy.lennard_jones_pair`, and a NumPy float64 brute
force for the truncations jax-md lacks.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax
from jax.test_util import check_grads
from jax_md import energy, partition, quantity, simulate, space

from jaxrt.energy import lj

try:
    import jaxrt
    # Delaunay triangulates 2D float64 systems only (tests/backends/test_delaunay.py).
    JAXRT_BACKENDS = [b for b in jaxrt.available_backends()
                      if b != "delaunay"]
except ImportError:  # the list front may not exist yet
    JAXRT_BACKENDS = []

FORMATS = [partition.Dense, partition.Sparse, partition.OrderedSparse]
LIST_FNS = ["jax_md"] + [f"jaxrt:{b}" for b in JAXRT_BACKENDS]


def _list_fn(name):
    if name == "jax_md":
        return partition.neighbor_list
    return functools.partial(jaxrt.neighbor_list, backend=name.split(":")[1])


@pytest.fixture(params=LIST_FNS)
def list_fn(request):
    """A neighbour-list factory with jax-md's signature."""
    return _list_fn(request.param)



def fluid(n_side=4, dim=3, density=0.8, seed=0, dtype=np.float32):
    """A jittered lattice: LJ-like spacing, no overlaps."""
    side = (n_side ** dim / density) ** (1 / dim)
    a = side / n_side
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * dim, indexing="ij"),
                 -1).reshape(-1, dim) * a
    rng = np.random.default_rng(seed)
    R = (g + rng.uniform(-0.15, 0.15, g.shape) * a) % side
    species = (np.arange(len(R)) % 2).astype(np.int32)
    return jnp.asarray(R, dtype), float(side), jnp.asarray(species)


SIGMA = np.array([[1.0, 1.1], [1.1, 0.9]], np.float32)
EPSILON = np.array([[1.0, 0.7], [0.7, 1.3]], np.float32)


def brute_lj(R, side, sigma, epsilon, species, r_cutoff, truncation,
             per_particle=False):
    """NumPy float64 all-pairs LJ with minimum image."""
    R = np.asarray(R, np.float64)
    d = R[:, None] - R[None]
    d -= side * np.round(d / side)
    r = np.sqrt(np.sum(d * d, -1))
    s = np.asarray(sigma, np.float64)[species[:, None], species[None]]
    e = np.asarray(epsilon, np.float64)[species[:, None], species[None]]
    np.fill_diagonal(r, 1.0)
    u = 4 * e * ((s / r) ** 12 - (s / r) ** 6)
    if truncation == "shifted":
        u -= 4 * e * ((s / r_cutoff) ** 12 - (s / r_cutoff) ** 6)
    u = np.where(r < r_cutoff, u, 0.0)
    np.fill_diagonal(u, 0.0)
    return u.sum(1) / 2 if per_particle else u.sum() / 2


# ---------------------------------------------------------------------------
# Equality with jax-md

# One energy function (and one jit cache) for every list factory: lists of
# the same layout and capacity compile once.
# rc + skin = 2.62 stays below half the box (2.69), as the ray-traced
# backends require.
R0, SIDE0, SPECIES0 = fluid(n_side=5)
PARAMS = dict(species=SPECIES0, sigma=jnp.asarray(SIGMA),
              epsilon=jnp.asarray(EPSILON), r_onset=1.8, r_cutoff=2.2,
              dr_threshold=0.2)
_DISP0, _ = space.periodic(SIDE0)
_OUR_TOTAL = lj.lennard_jones_pair_neighbor_list(
    _DISP0, species=SPECIES0, sigma=jnp.asarray(SIGMA),
    epsilon=jnp.asarray(EPSILON), r_onset=1.8 * 1.1, r_cutoff=2.2 * 1.1)
_OUR_PP = lj.lennard_jones_pair_neighbor_list(
    _DISP0, species=SPECIES0, sigma=jnp.asarray(SIGMA),
    epsilon=jnp.asarray(EPSILON), r_onset=1.8 * 1.1, r_cutoff=2.2 * 1.1,
    per_particle=True)


@jax.jit
def _ours(R, nbrs):
    e, g = jax.value_and_grad(_OUR_TOTAL)(R, nbrs)
    return e, -g, _OUR_PP(R, nbrs)


@functools.lru_cache(maxsize=None)
def _reference(fmt):
    """jax-md on its own list: energy, forces, per-particle energies."""
    neighbor_fn, energy_fn = energy.lennard_jones_neighbor_list(
        _DISP0, SIDE0, format=fmt, **PARAMS)
    # jax-md refuses per-particle energies on OrderedSparse; its Sparse list
    # gives the same numbers.
    pp_fmt = partition.Sparse if fmt is partition.OrderedSparse else fmt
    pp_neighbor_fn, pp_fn = energy.lennard_jones_neighbor_list(
        _DISP0, SIDE0, format=pp_fmt, per_particle=True, **PARAMS)
    nbrs, pp_nbrs = neighbor_fn.allocate(R0), pp_neighbor_fn.allocate(R0)
    out = jax.jit(lambda R: (energy_fn(R, nbrs),
                             quantity.force(energy_fn)(R, nbrs),
                             pp_fn(R, pp_nbrs)))(R0)
    return tuple(np.asarray(x) for x in out)


@pytest.mark.parametrize("fmt", FORMATS)
def test_energy_forces_per_particle_equal_jax_md(list_fn, fmt):
    neighbor_fn, energy_fn = lj.lennard_jones_neighbor_list(
        _DISP0, SIDE0, format=fmt, neighbor_list_fn=list_fn, **PARAMS)
    nbrs = neighbor_fn.allocate(R0)
    assert not nbrs.did_buffer_overflow
    e, f, pp = _ours(R0, nbrs)
    e_ref, f_ref, pp_ref = _reference(fmt)
    assert abs(e_ref) > 1 and np.abs(f_ref).max() > 1  # a real test
    np.testing.assert_allclose(e, e_ref, rtol=2e-6)
    np.testing.assert_allclose(f, f_ref, rtol=1e-4,
                               atol=1e-5 * np.abs(f_ref).max())
    assert pp.shape == (R0.shape[0],)
    np.testing.assert_allclose(pp, pp_ref, rtol=1e-5,
                               atol=1e-6 * np.abs(pp_ref).max())
    np.testing.assert_allclose(pp.sum(), e, rtol=1e-5)


def test_factory_matches_pair_factory_and_all_pairs_oracle():
    """The jax-md-style factory (cutoffs in units of max sigma) equals the
    absolute-unit factory, and both equal jax-md's list-free sum."""
    neighbor_fn, energy_fn = lj.lennard_jones_neighbor_list(
        _DISP0, SIDE0, neighbor_list_fn=partition.neighbor_list, **PARAMS)
    nbrs = neighbor_fn.allocate(R0)
    e_all = energy.lennard_jones_pair(
        _DISP0, **{k: v for k, v in PARAMS.items() if k != "dr_threshold"})
    e1, e2, e3 = jax.jit(lambda R: (energy_fn(R, nbrs), _OUR_TOTAL(R, nbrs),
                                    e_all(R)))(R0)
    np.testing.assert_allclose(e1, e2, rtol=1e-6)
    np.testing.assert_allclose(e1, e3, rtol=2e-5)


def test_dynamic_box_and_species_keywords():
    """``box=`` reaches the displacement only (as in jax-md, e.g. for NPT),
    and ``species=`` replaces the factory's."""
    R, side, species = fluid(n_side=4)
    box = jnp.eye(3) * side
    disp, _ = space.periodic_general(box, fractional_coordinates=False)
    kw = dict(species=species, sigma=jnp.asarray(SIGMA),
              epsilon=jnp.asarray(EPSILON), r_onset=1.6, r_cutoff=2.0,
              format=partition.Sparse, fractional_coordinates=False,
              disable_cell_list=True)
    ref_fn, ref_energy = energy.lennard_jones_neighbor_list(disp, box, **kw)
    nbrs = ref_fn.allocate(R)
    _, our_energy = lj.lennard_jones_neighbor_list(
        disp, box, neighbor_list_fn=partition.neighbor_list, **kw)
    other = 1 - species
    _, other_energy = lj.lennard_jones_neighbor_list(
        disp, box, neighbor_list_fn=partition.neighbor_list,
        **{**kw, "species": other})
    new_box = box * 1.03
    got, want, swapped, want_swapped = jax.jit(lambda R: (
        our_energy(R, nbrs, box=new_box), ref_energy(R, nbrs, box=new_box),
        our_energy(R, nbrs, species=other), other_energy(R, nbrs)))(R)
    np.testing.assert_allclose(got, want, rtol=2e-6)
    assert abs(got - our_energy(R, nbrs)) > 1e-3 * abs(got)  # box mattered
    np.testing.assert_allclose(swapped, want_swapped, rtol=2e-6)


def test_truncations_match_float64_brute_force(x64):
    R, side, species = fluid(dtype=np.float64, seed=1)
    disp, _ = space.periodic(side)
    rc = 2.0
    fns = {(t, pp): lj.lennard_jones_pair_neighbor_list(
        disp, species=species, sigma=jnp.asarray(SIGMA, jnp.float64),
        epsilon=jnp.asarray(EPSILON, jnp.float64), r_cutoff=rc,
        truncation=t, per_particle=pp)
        for t in ("truncated", "shifted") for pp in (False, True)}
    compute = jax.jit(lambda R, nbrs: {k: f(R, nbrs) for k, f in fns.items()})
    for fmt in FORMATS:
        nbrs = partition.neighbor_list(disp, side, rc, format=fmt).allocate(R)
        got = compute(R, nbrs)
        for (truncation, per_particle), value in got.items():
            assert value.dtype == jnp.float64
            want = brute_lj(R, side, SIGMA, EPSILON, np.asarray(species), rc,
                            truncation, per_particle)
            np.testing.assert_allclose(value, want, rtol=1e-10, atol=1e-12)


def test_float64_stays_float64(x64):
    R, side, _ = fluid(n_side=3, dtype=np.float64)
    disp, _ = space.periodic(side)
    neighbor_fn, energy_fn = lj.lennard_jones_neighbor_list(
        disp, side, sigma=1.0, epsilon=1.0,
        neighbor_list_fn=partition.neighbor_list)
    nbrs = neighbor_fn.allocate(R)
    e, f = jax.jit(lambda R: (energy_fn(R, nbrs),
                              quantity.force(energy_fn)(R, nbrs)))(R)
    assert e.dtype == f.dtype == jnp.float64


# ---------------------------------------------------------------------------
# Gradients


def test_check_grads_positions_and_parameters(x64):
    R, side, species = fluid(n_side=3, dim=2, density=0.5, dtype=np.float64)
    disp, _ = space.periodic(side)
    nbrs = partition.neighbor_list(disp, side, 1.9, dr_threshold=0.0,
                                   format=partition.Sparse).allocate(R)
    args = (R, jnp.asarray(SIGMA, jnp.float64),
            jnp.asarray(EPSILON, jnp.float64), jnp.float64(1.3),
            jnp.float64(1.8))
    for truncation in lj.TRUNCATIONS:
        fn = lj.lennard_jones_pair_neighbor_list(
            disp, species=species, r_onset=1.3, r_cutoff=1.8,
            truncation=truncation)
        # r_onset / r_cutoff only where the switch makes the energy smooth
        # in them (truncated / shifted jump as pairs cross r_cutoff).
        n_args = 5 if truncation == "smooth" else 3

        @jax.jit
        def f(*varying):
            R, sigma, epsilon, r_onset, r_cutoff = (
                varying + args[len(varying):])
            return fn(R, nbrs, sigma=sigma, epsilon=epsilon,
                      r_onset=r_onset, r_cutoff=r_cutoff)

        g = jax.grad(f, argnums=tuple(range(n_args)))(*args[:n_args])
        assert all(np.all(np.isfinite(x)) and np.any(x != 0) for x in g)
        # Second order (forces' derivatives) for the smooth one only, to
        # keep the test short; first order for all.
        check_grads(f, args[:n_args], order=2 if n_args == 5 else 1,
                    modes=["rev"], atol=1e-4, rtol=1e-4)


def test_finite_gradients_at_coincidence_and_cutoff():
    # Particles 0 and 1 coincide; 2 sits exactly at r_cutoff from 0, and 3
    # exactly at r_onset from 2.
    R = jnp.array([[1.0, 1.0], [1.0, 1.0], [3.5, 1.0], [3.5, 3.0]])
    disp, _ = space.free()
    fns = {t: lj.lennard_jones_pair_neighbor_list(
        disp, r_onset=2.0, r_cutoff=2.5, truncation=t)
        for t in lj.TRUNCATIONS}

    def f(R, sigma, epsilon, r_cutoff, nbrs, truncation):
        return fns[truncation](R, nbrs, sigma=sigma, epsilon=epsilon,
                               r_cutoff=r_cutoff)

    @jax.jit
    def values_and_grads(R, nbrs):
        return {t: jax.value_and_grad(f, argnums=(0, 1, 2, 3))(
            R, 1.0, 1.0, 2.5, nbrs, t) for t in lj.TRUNCATIONS}

    u = 4 * (0.5 ** 12 - 0.5 ** 6)
    # The coincident pair contributes nothing (as in jax-md), the pair at
    # r_cutoff nothing (strict <): only (2, 3), at r = 2 = r_onset, counts.
    want = {"smooth": u, "truncated": u,
            "shifted": u - 4 * (2.5 ** -12 - 2.5 ** -6)}
    for fmt in FORMATS:
        nbrs = partition.neighbor_list(disp, 10.0, 3.0, format=fmt,
                                       disable_cell_list=True).allocate(R)
        for t, (e, g) in values_and_grads(R, nbrs).items():
            for x in g:
                assert np.all(np.isfinite(x)), (fmt, t, g)
            np.testing.assert_allclose(e, want[t], rtol=1e-5)
    h = jax.jit(jax.hessian(f), static_argnums=5)(R, 1.0, 1.0, 2.5, nbrs,
                                                  "smooth")
    assert np.all(np.isfinite(h))


def test_hessian_matches_jax_md_all_pairs(x64):
    R, side, _ = fluid(n_side=2, dim=3, density=0.5, seed=3,
                       dtype=np.float64)
    disp, _ = space.periodic(side)
    nbrs = partition.neighbor_list(disp, side, 2.0,
                                   format=partition.OrderedSparse).allocate(R)
    fn = lj.lennard_jones_pair_neighbor_list(disp, r_onset=1.2, r_cutoff=1.5)
    # jax-md casts Python-float cutoffs to float32 even under x64: pass
    # float64 arrays so that both sides switch at the same radius.
    ref = energy.lennard_jones_pair(disp, sigma=jnp.float64(1.0),
                                    epsilon=jnp.float64(1.0),
                                    r_onset=jnp.float64(1.2),
                                    r_cutoff=jnp.float64(1.5))
    h, h_ref = jax.jit(lambda R: (jax.hessian(fn)(R, nbrs),
                                  jax.hessian(ref)(R)))(R)
    assert h.shape == (8, 3, 8, 3)
    assert np.abs(h_ref).max() > 1  # the pairs interact
    np.testing.assert_allclose(h, h_ref, rtol=1e-9, atol=1e-9)
    flat = np.asarray(h).reshape(24, 24)
    np.testing.assert_allclose(flat, flat.T, atol=1e-9)


SCAN_STEPS = 30


def _scan_problem(list_fn, R, side, **kw):
    """``final_energy((sigma, epsilon))``: the potential energy after
    ``SCAN_STEPS`` NVE steps with ``nbrs.update`` inside ``lax.scan``."""
    disp, shift = space.periodic(side)
    neighbor_fn, energy_fn = lj.lennard_jones_neighbor_list(
        disp, side, format=partition.Sparse, neighbor_list_fn=list_fn, **kw)
    nbrs0 = neighbor_fn.allocate(R)
    V0 = jax.random.normal(jax.random.PRNGKey(0), R.shape, R.dtype)

    def final_energy(params):
        sigma, epsilon = params

        def e(R, neighbor):
            return energy_fn(R, neighbor, sigma=sigma, epsilon=epsilon)

        init, apply = simulate.nve(e, shift, dt=0.005)
        state = init(jax.random.PRNGKey(1), R, 1.0, neighbor=nbrs0)
        state = state.set(momentum=V0)

        def step(carry, _):
            state, nbrs = carry
            nbrs = nbrs.update(state.position)
            return (apply(state, neighbor=nbrs), nbrs), None

        (state, nbrs), _ = lax.scan(step, (state, nbrs0), None,
                                    length=SCAN_STEPS)
        return e(state.position, nbrs), nbrs

    return final_energy


def test_grad_through_scan_matches_finite_differences(x64):
    R, side, _ = fluid(n_side=4, dim=2, density=0.6, dtype=np.float64, seed=2)
    final_energy = _scan_problem(partition.neighbor_list, R, side,
                                 r_onset=1.5, r_cutoff=2.0, dr_threshold=0.3)
    params = (jnp.float64(1.0), jnp.float64(1.0))
    (_, nbrs), g = jax.jit(jax.value_and_grad(final_energy, has_aux=True))(
        params)
    assert not nbrs.did_buffer_overflow
    assert np.abs(np.asarray(nbrs.reference_position - R)).max() > 0.15, (
        "the particles should move past half the skin: the list rebuilt")
    forward = jax.jit(lambda p: final_energy(p)[0])
    eps = 1e-5
    for i in range(2):
        up = list(params); up[i] = params[i] + eps
        dn = list(params); dn[i] = params[i] - eps
        fd = (forward(tuple(up)) - forward(tuple(dn))) / (2 * eps)
        np.testing.assert_allclose(g[i], fd, rtol=1e-5)


@functools.lru_cache(maxsize=None)
def _scan_gradient(name):
    final_energy = _scan_problem(_list_fn(name), R0, SIDE0, **PARAMS)
    params = (jnp.float32(1.0), jnp.float32(1.0))
    (_, nbrs), g = jax.jit(jax.value_and_grad(final_energy, has_aux=True))(
        params)
    assert not nbrs.did_buffer_overflow
    return np.asarray(g), np.asarray(nbrs.reference_position)


@pytest.mark.parametrize("name", LIST_FNS[1:])
def test_grad_through_scan_with_update_for_every_backend(name):
    """jax.grad through k MD steps with nbrs.update inside lax.scan gives
    jax-md's gradient for each jaxrt backend."""
    g_ref, _ = _scan_gradient("jax_md")
    g, reference_position = _scan_gradient(name)
    assert np.abs(reference_position - np.asarray(R0)).max() > 0.1, (
        "the particles should move past half the skin: the list rebuilt")
    np.testing.assert_allclose(g, g_ref, rtol=1e-4)


# ---------------------------------------------------------------------------
# Bad input


def test_bad_input_raises_value_errors_naming_the_argument():
    R, side, species = fluid(n_side=2)
    disp, _ = space.periodic(side)
    make = functools.partial(lj.lennard_jones_pair_neighbor_list, disp)
    with pytest.raises(ValueError, match="truncation"):
        make(truncation="cut")
    with pytest.raises(ValueError, match="species"):
        make(species=jnp.zeros(8), sigma=1.0)  # float species
    with pytest.raises(ValueError,
                       match=r"sigma has shape \(2,\) but species"):
        make(species=species, sigma=jnp.ones(2))
    with pytest.raises(ValueError, match="species has values up to 2"):
        make(species=species.at[0].set(2), sigma=jnp.asarray(SIGMA))
    with pytest.raises(ValueError, match="epsilon is not symmetric"):
        make(species=species, epsilon=jnp.array([[1.0, 0.5], [0.7, 1.0]]))
    with pytest.raises(ValueError, match="sigma must be > 0"):
        make(sigma=-1.0)
    with pytest.raises(ValueError, match="r_onset"):
        make(r_onset=2.5, r_cutoff=2.5)
    fn = make(species=species)
    nbrs = partition.neighbor_list(disp, side, 2.5).allocate(R)
    with pytest.raises(ValueError, match="species has 8 entries but R has 7"):
        fn(R[:7], nbrs)
    with pytest.raises(ValueError, match="sigma has shape"):
        make()(R, nbrs, sigma=jnp.ones(3))  # per-particle of the wrong length
    with pytest.raises(ValueError, match="species was given to the energy"):
        make()(R, nbrs, species=species)
    with pytest.raises(ValueError, match="species must be an integer"):
        fn(R, nbrs, species=jnp.zeros(8))
    with pytest.raises(ValueError, match="sigma must be concrete"):
        jax.jit(lambda s: lj.lennard_jones_neighbor_list(disp, side, sigma=s))(
            1.0)


def test_unknown_energy_keyword_raises_with_suggestion():
    """A misspelt keyword used to reach jax-md's displacement, which takes
    ``**unused`` and dropped it: sigmaa=2. gave the sigma=1 energy."""
    R, side, _ = fluid(n_side=2)
    disp, _ = space.periodic(side)
    nbrs = partition.neighbor_list(disp, side, 2.5).allocate(R)
    fn = lj.lennard_jones_pair_neighbor_list(disp)
    with pytest.raises(TypeError, match=r"\['sigmaa'\].*did you mean "
                       r"'sigma'\?.*accepts sigma, epsilon, r_onset"):
        fn(R, nbrs, sigmaa=2.0)
    with pytest.raises(TypeError, match=r"'colour'.*perturbation"):
        jax.jit(lambda R: fn(R, nbrs, colour=1.0))(R)  # at trace time too
    _, energy_fn = lj.lennard_jones_neighbor_list(
        disp, side, neighbor_list_fn=partition.neighbor_list)
    with pytest.raises(TypeError, match="did you mean 'epsilon'"):
        energy_fn(R, nbrs, epsilom=2.0)


def test_legitimate_energy_keywords_still_work():
    """Parameters and the displacement's own keywords (``box=`` of
    periodic_general, a keyword named in a custom displacement) pass."""
    R, side, _ = fluid(n_side=2)
    disp, _ = space.periodic(side)
    nbrs = partition.neighbor_list(disp, side, 2.5).allocate(R)
    fn = lj.lennard_jones_pair_neighbor_list(disp)
    e1 = fn(R, nbrs)
    e2 = fn(R, nbrs, sigma=1.05, epsilon=2.0, r_onset=1.9, r_cutoff=2.4)
    assert np.isfinite(e2) and abs(e2 - e1) > 1e-3 * abs(e1)
    # jax_md.simulate.nvt_nose_hoover passes its kT on to the energy.
    np.testing.assert_array_equal(fn(R, nbrs, kT=0.5), e1)
    general, _ = space.periodic_general(jnp.eye(3) * side,
                                        fractional_coordinates=False)
    g = lj.lennard_jones_pair_neighbor_list(general)
    np.testing.assert_allclose(g(R, nbrs, box=jnp.eye(3) * side), e1,
                               rtol=1e-6)

    # A custom displacement keyword (jax-md's canonicalisation probes t=).
    def scaled(Ra, Rb, scale=1.0, t=None):
        return disp(Ra, Rb) * scale
    s = lj.lennard_jones_pair_neighbor_list(scaled)
    np.testing.assert_allclose(s(R, nbrs, scale=1.0), e1, rtol=1e-6)
    assert abs(s(R, nbrs, scale=1.02) - e1) > 1e-3 * abs(e1)
    with pytest.raises(TypeError, match="'box'.*accepts.*scale"):
        s(R, nbrs, box=side)  # scaled has no **kwargs: box would be lost


def test_under_jit_bad_values_poison_with_nan():
    """Under jit a traced sigma <= 0 cannot raise; as documented, the energy
    is NaN rather than the (identical, by LJ's even powers) energy of
    -sigma."""
    R, side, _ = fluid(n_side=2)
    disp, _ = space.periodic(side)
    nbrs = partition.neighbor_list(disp, side, 2.5).allocate(R)
    fn = lj.lennard_jones_pair_neighbor_list(disp)
    assert np.isnan(jax.jit(lambda s: fn(R, nbrs, sigma=s))(-1.0))
    assert np.isnan(jax.jit(lambda e: fn(R, nbrs, epsilon=e))(-1.0))
    assert np.isfinite(jax.jit(lambda s: fn(R, nbrs, sigma=s))(1.0))


# --- The row gradient on Dense lists (jaxrt.energy.rows) -------------------

def _row_and_autodiff(disp, **kw):
    return (lj.lennard_jones_pair_neighbor_list(disp, gradient="rows", **kw),
            lj.lennard_jones_pair_neighbor_list(disp, gradient="autodiff",
                                                **kw))


@pytest.mark.parametrize("params", ["scalar", "per_particle", "species"])
def test_row_gradient_equals_autodiff(x64, params):
    R, side, species = fluid(n_side=4, dim=3, seed=5, dtype=np.float64)
    n = R.shape[0]
    disp, _ = space.periodic(side)
    kw = dict(r_onset=1.6, r_cutoff=2.0)
    if params == "per_particle":
        rng = np.random.default_rng(1)
        kw.update(sigma=jnp.asarray(rng.uniform(0.9, 1.1, n)),
                  epsilon=jnp.asarray(rng.uniform(0.5, 1.5, n)))
    elif params == "species":
        kw.update(species=species, sigma=jnp.array([[1.0, 1.1], [1.1, 0.9]]),
                  epsilon=jnp.array([[1.0, 0.7], [0.7, 1.3]]))
    rows, plain = _row_and_autodiff(disp, **kw)
    nbrs = partition.neighbor_list(disp, side, 2.0,
                                   format=partition.Dense).allocate(R)

    def grads(fn):
        def e(R, sigma, epsilon, r_cutoff):
            return fn(R, nbrs, sigma=sigma, epsilon=epsilon, r_cutoff=r_cutoff)
        sigma = kw.get("sigma", jnp.float64(1.0))
        epsilon = kw.get("epsilon", jnp.float64(1.0))
        return jax.jit(jax.value_and_grad(e, argnums=(0, 1, 2, 3)))(
            R, sigma, epsilon, jnp.float64(2.0))

    (e_rows, g_rows), (e_plain, g_plain) = grads(rows), grads(plain)
    assert abs(e_plain) > 1 and np.abs(g_plain[0]).max() > 1  # a real test
    np.testing.assert_allclose(e_rows, e_plain, rtol=1e-13)
    for a, b in zip(g_rows, g_plain):
        np.testing.assert_allclose(a, b, rtol=1e-10,
                                   atol=1e-12 * np.abs(b).max())


def test_row_gradient_hessian_and_box_derivative(x64):
    R, side, _ = fluid(n_side=2, dim=3, density=0.5, seed=3, dtype=np.float64)
    disp, _ = space.periodic_general(jnp.eye(3) * side,
                                     fractional_coordinates=False)
    rows, plain = _row_and_autodiff(disp, r_onset=1.2, r_cutoff=1.5)
    nbrs = partition.neighbor_list(disp, side, 1.5, format=partition.Dense,
                                   disable_cell_list=True).allocate(R)
    box = jnp.eye(3) * side
    h_rows, h_plain = (jax.jit(jax.hessian(lambda R: f(R, nbrs, box=box)))(R)
                       for f in (rows, plain))
    assert np.abs(h_plain).max() > 1
    np.testing.assert_allclose(h_rows, h_plain, rtol=1e-10,
                               atol=1e-12 * np.abs(h_plain).max())
    # d/d(box): the metric's keyword arguments are differentiated too.
    gb_rows, gb_plain = (jax.grad(lambda b: f(R, nbrs, box=b))(box)
                         for f in (rows, plain))
    np.testing.assert_allclose(gb_rows, gb_plain, rtol=1e-10, atol=1e-12)


def test_row_gradient_compiles_no_scatter():
    R, side, _ = fluid(n_side=4, dim=3)
    disp, _ = space.periodic(side)
    rows, plain = _row_and_autodiff(disp)
    nbrs = partition.neighbor_list(disp, side, 2.5,
                                   format=partition.Dense).allocate(R)
    hlo = {name: jax.jit(jax.grad(f)).lower(R, nbrs).as_text()
           for name, f in (("rows", rows), ("autodiff", plain))}
    assert "scatter" in hlo["autodiff"]  # the positive control
    assert "scatter" not in hlo["rows"]


@pytest.mark.parametrize("fmt", [partition.Sparse, partition.OrderedSparse])
def test_edge_layout_gradients_scatter_materialized_edges(fmt):
    # On the H200 XLA fused the pair arithmetic and the gathers into the
    # scatters of reverse mode, far slower than scattering written-out
    # edges (jaxrt.layouts.edges); the barrier is what prevents it.
    R, side, _ = fluid(n_side=4, dim=3)
    disp, _ = space.periodic(side)
    nbrs = partition.neighbor_list(disp, side, 2.5, format=fmt).allocate(R)
    ours = lj.lennard_jones_pair_neighbor_list(disp, r_onset=2.0, r_cutoff=2.5)
    _, theirs = energy.lennard_jones_neighbor_list(disp, side, format=fmt,
                                                   r_onset=2.0, r_cutoff=2.5)
    text = {name: jax.jit(jax.grad(f)).lower(R, nbrs).as_text()
            for name, f in (("ours", ours), ("jax-md", theirs))}
    assert "scatter" in text["ours"] and "scatter" in text["jax-md"]
    assert "optimization_barrier" not in text["jax-md"]  # positive control
    assert "optimization_barrier" in text["ours"]
    got, want = jax.grad(ours)(R, nbrs), jax.grad(theirs)(R, nbrs)
    # The same pair terms summed in other orders (XLA:GPU fuses them
    # differently per program): each of a particle's ~50 terms may round
    # the partial sum by one ulp of the largest term, so the bound is a few
    # dozen ulps of the largest force, not of each component.
    eps = np.finfo(np.asarray(want).dtype).eps
    np.testing.assert_allclose(got, want, rtol=1e-5,
                               atol=64 * eps * float(np.abs(want).max()))
