"""SPH on neighbour lists (`jaxrt.energy.sph`).

Oracles: numerical quadrature for the kernels' normalisation, a NumPy
float64 all-pairs SPH written independently of the package (hand-coded
cubic spline and its derivative), the reference density of a regular
lattice, and central finite differences.
"""
from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from jax_md import partition, space

from jaxrt.energy import sph

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



def lattice(n, dx, dim):
    g = np.stack(np.meshgrid(*[np.arange(n)] * dim, indexing="ij"), -1)
    return g.reshape(-1, dim) * dx


# ---------------------------------------------------------------------------
# Kernels


@jax.jit
def _kernel_samples(k, radial, grid, beyond, inside, r):
    """Every kernel evaluation the test needs, in one compiled call."""
    return dict(radial=k.w(radial), grid=k.w(grid), beyond=k.w(beyond),
                grad_beyond=k.grad_w(beyond), inside=k.w(inside),
                grad=k.grad_w(r), fd=(k.w(r + 1e-6) - k.w(r - 1e-6)) / 2e-6,
                w0=k.w(jnp.zeros_like(r[0])), grad0=k.grad_w(
                    jnp.zeros_like(r[0])))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", sorted(sph.KERNELS))
def test_kernel_normalised_and_compact(name, dim, x64):
    h = 0.37
    k = sph.kernel(name, h, dim=dim)
    assert isinstance(k, sph.KERNELS[name]) and k.dim == dim
    np.testing.assert_allclose(float(k.cutoff), k.support * h)
    # Radial Gauss-Legendre on each unit interval of q = r/h: exact for the
    # piecewise polynomials, so a wrong normalisation cannot hide.
    x, wq = np.polynomial.legendre.leggauss(16)
    radial = np.concatenate([(a + (x + 1) / 2) * h
                             for a in range(int(k.support))])
    weights = np.tile(wq / 2 * h, int(k.support))
    # Independently: a Cartesian midpoint sum (coarser; 2e-3 is its error).
    n = 40 if dim == 2 else 24
    g = (np.arange(-n, n) + 0.5) * (k.support * h / n)
    grid = np.linalg.norm(np.stack(np.meshgrid(*[g] * dim, indexing="ij"),
                                   -1), axis=-1)
    beyond = np.array([1.0, 1.0 + 1e-12, 1.5]) * k.support * h
    r = np.linspace(0.01, 0.99, 23) * k.support * h
    out = {key: np.asarray(v) for key, v in _kernel_samples(
        k, radial, grid, beyond, (1 - 1e-3) * k.support * h, r).items()}

    shell = 2 * np.pi * radial if dim == 2 else 4 * np.pi * radial ** 2
    np.testing.assert_allclose(np.sum(weights * shell * out["radial"]), 1.0,
                               rtol=1e-12)
    np.testing.assert_allclose(out["grid"].sum() * (g[1] - g[0]) ** dim, 1.0,
                               rtol=2e-3)
    # Compact support: exactly zero (value and slope) from the cutoff on,
    # positive just inside.
    assert np.all(out["beyond"] == 0) and np.all(out["grad_beyond"] == 0)
    assert out["inside"] > 0
    # grad_w is dW/dr: compare with central differences.
    np.testing.assert_allclose(out["grad"], out["fd"], rtol=1e-6,
                               atol=1e-8 * out["w0"] / h)
    # Zero slope at the centre (the quintic's terms cancel only to rounding).
    assert abs(out["grad0"]) < 1e-12 * out["w0"] / h


# ---------------------------------------------------------------------------
# Against an independent all-pairs SPH


def _cubic_np(r, h, dim):
    q = r / h
    sigma = 10 / (7 * np.pi) if dim == 2 else 1 / np.pi
    norm = sigma / h ** dim
    w = np.where(q < 1, 1 - 1.5 * q ** 2 + 0.75 * q ** 3,
                 np.where(q < 2, 0.25 * (2 - q) ** 3, 0.0))
    dw = np.where(q < 1, -3 * q + 2.25 * q ** 2,
                  np.where(q < 2, -0.75 * (2 - q) ** 2, 0.0))
    return norm * w, norm * dw / h


def brute_sph(R, V, m, side, h, rho0, c0, gamma, alpha, beta, eps=0.01):
    """Float64 NumPy all-pairs density and accelerations (min image)."""
    R, V, m = (np.asarray(x, np.float64) for x in (R, V, m))
    dim = R.shape[1]
    d = R[:, None] - R[None]
    d -= side * np.round(d / side)
    r = np.linalg.norm(d, axis=-1)
    w, dw = _cubic_np(r, h, dim)
    rho = (m[None] * w).sum(1)  # the diagonal is the self term m_i W(0)
    p = rho0 * c0 ** 2 / gamma * ((rho / rho0) ** gamma - 1)
    c = c0 * (rho / rho0) ** ((gamma - 1) / 2)
    safe = np.where(r > 0, r, 1.0)
    grad = (dw / safe)[..., None] * d
    pij = p[:, None] / rho[:, None] ** 2 + p[None] / rho[None] ** 2
    vr = np.sum((V[:, None] - V[None]) * d, -1)
    mu = h * vr / (r ** 2 + eps * h ** 2)
    c_mean = (c[:, None] + c[None]) / 2
    rho_mean = (rho[:, None] + rho[None]) / 2
    pi = np.where(vr < 0, (-alpha * c_mean * mu + beta * mu ** 2) / rho_mean,
                  0.0)
    a_p = -np.sum(m[None, :, None] * pij[..., None] * grad, axis=1)
    a_v = -np.sum(m[None, :, None] * pi[..., None] * grad, axis=1)
    return rho, a_p, a_v


def disordered(n=7, dim=2, seed=0, dtype=np.float32):
    """A jittered periodic lattice with random velocities and masses."""
    dx = 0.1
    rng = np.random.default_rng(seed)
    side = n * dx
    R = (lattice(n, dx, dim) + rng.uniform(-0.3, 0.3, (n ** dim, dim)) * dx
         ) % side
    V = rng.normal(0, 1.0, R.shape)
    m = 1000 * dx ** dim * rng.uniform(0.8, 1.2, len(R))
    return (jnp.asarray(R, dtype), jnp.asarray(V, dtype),
            jnp.asarray(m, dtype), side)


EOS = dict(rho0=1000.0, c0=10.0, gamma=7.0)
VISC = dict(alpha=0.5, beta=0.3)
R1, V1, M1, SIDE1 = disordered()
H1 = 0.13
DISP1, _ = space.periodic(SIDE1)
KERNEL1 = sph.CubicSpline(H1, dim=2)
_ACCEL1 = sph.acceleration(DISP1, KERNEL1, sph.Tait(**EOS), mass=M1, **VISC)


@jax.jit
def _sph1(R, V, nbrs):
    return _ACCEL1(R, V, nbrs)


@functools.lru_cache(maxsize=None)
def _brute1():
    return brute_sph(R1, V1, M1, SIDE1, H1, **EOS, **VISC)


@pytest.mark.parametrize("fmt", FORMATS)
def test_density_and_forces_match_all_pairs_oracle(list_fn, fmt):
    # mask_self=False: Dense and Sparse lists then hold i-i pairs, which must
    # not add a second self term (OrderedSparse never holds them).
    nbrs = list_fn(DISP1, SIDE1, float(KERNEL1.cutoff), format=fmt,
                   mask_self=False).allocate(R1)
    assert not nbrs.did_buffer_overflow
    out = _sph1(R1, V1, nbrs)
    rho, a_p, a_v = _brute1()
    np.testing.assert_allclose(out.density, rho, rtol=2e-6)
    scale_p, scale_v = np.abs(a_p).max(), np.abs(a_v).max()
    assert scale_p > 1 and scale_v > 1  # both terms really act
    np.testing.assert_allclose(out.pressure, a_p, atol=1e-4 * scale_p)
    np.testing.assert_allclose(out.viscosity, a_v, atol=1e-4 * scale_v)
    # Momentum: each pair term is antisymmetric.
    for acc, scale in ((out.pressure, scale_p), (out.viscosity, scale_v)):
        momentum = np.sum(np.asarray(M1)[:, None] * np.asarray(acc), axis=0)
        total = np.sum(np.abs(np.asarray(M1)[:, None] * np.asarray(acc)))
        assert np.all(np.abs(momentum) < 1e-5 * total), momentum


# ---------------------------------------------------------------------------
# Physics checks


# Stated tolerance on the relative error of the summation density on a
# regular lattice with h = 1.3 dx (measured, 2D / 3D: cubic 5e-5 / 2.7e-3,
# quintic 5e-5 / 1.2e-4, Wendland C2 1.0e-2 / 9.5e-3, C4 8.5e-3 / 8.5e-3).
# The Wendland kernels overshoot at this h/dx: they need a larger h to
# approach a partition of unity.
LATTICE_TOL = {"cubic_spline": 5e-3, "quintic_spline": 5e-4,
               "wendland_c2": 1.5e-2, "wendland_c4": 1.5e-2}


@pytest.mark.parametrize("dim", [2, 3])
def test_density_of_regular_lattice_is_reference_density(dim, x64):
    n = 12 if dim == 2 else 7
    dx, rho0 = 0.1, 1000.0
    side = n * dx
    R = jnp.asarray(lattice(n, dx, dim))
    disp, _ = space.periodic(side)
    h = 1.3 * dx
    # One list, wide enough for the widest kernel (quintic: 3h).
    nbrs = partition.neighbor_list(disp, side, 3 * h,
                                   format=partition.Sparse).allocate(R)

    @jax.jit
    def densities(R, nbrs):
        return {name: sph.density(disp, sph.kernel(name, h, dim=dim),
                                  mass=rho0 * dx ** dim)(R, nbrs)
                for name in sph.KERNELS}

    for name, rho in densities(R, nbrs).items():
        err = np.abs(np.asarray(rho) / rho0 - 1).max()
        assert err < LATTICE_TOL[name], (name, err)
        # Every lattice site is equivalent.
        assert np.ptp(np.asarray(rho)) < 1e-9 * rho0


def test_gradients_wrt_h_eos_and_positions(x64):
    R, V, m, side = disordered(n=5, seed=1, dtype=np.float64)
    disp, _ = space.periodic(side)
    k = sph.WendlandC2(0.13, dim=2)
    accel = sph.acceleration(disp, k, sph.Tait(**EOS), mass=m, **VISC)
    nbrs = partition.neighbor_list(disp, side, 0.3,
                                   format=partition.OrderedSparse).allocate(R)

    @jax.jit
    def loss(h, rho0, c0, R):
        out = accel(R, V, nbrs, h=h, eos=sph.Tait(rho0, c0, 7.0))
        return (jnp.sum(out.density ** 2) * 1e-6
                + jnp.sum(out.total ** 2) * 1e-4)

    args = (jnp.float64(0.13), jnp.float64(1000.0), jnp.float64(10.0), R)
    grads = jax.grad(loss, argnums=(0, 1, 2, 3))(*args)
    assert all(np.all(np.isfinite(g)) and np.any(g != 0) for g in grads)
    eps = 1e-6
    fd = (loss(args[0] + eps, *args[1:]) - loss(args[0] - eps, *args[1:])) / (
        2 * eps)
    np.testing.assert_allclose(grads[0], fd, rtol=1e-6)
    check_grads(loss, args, order=1, modes=["rev"], atol=1e-5, rtol=1e-5,
                eps=1e-6)


def test_finite_gradients_with_coincident_particles():
    R = jnp.array([[0.5, 0.5], [0.5, 0.5], [0.55, 0.5], [0.9, 0.9]])
    V = jnp.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    disp, _ = space.free()
    k = sph.QuinticSpline(0.04, dim=2)
    accel = sph.acceleration(disp, k, sph.Tait(**EOS), mass=1.6)
    lists = [partition.neighbor_list(disp, 2.0, float(k.cutoff), format=fmt,
                                     disable_cell_list=True).allocate(R)
             for fmt in FORMATS]
    grad = jax.grad(lambda R, V, nbrs: jnp.sum(accel(R, V, nbrs).total),
                    argnums=(0, 1))
    # One compiled call for the three layouts.
    grads = jax.jit(lambda R, V, lists: [grad(R, V, nb) for nb in lists])(
        R, V, lists)
    for fmt, g in zip(FORMATS, grads):
        assert all(np.all(np.isfinite(x)) for x in g), fmt


# ---------------------------------------------------------------------------
# Bad input


def test_bad_input_raises_value_errors_naming_the_argument():
    disp, _ = space.free()
    with pytest.raises(ValueError, match="h must be finite and > 0"):
        sph.CubicSpline(0.0, dim=2)
    with pytest.raises(ValueError, match="h must be finite and > 0"):
        sph.kernel("wendland_c2", -0.1, dim=3)
    with pytest.raises(ValueError,
                       match="kernel name 'gaussian' is not known"):
        sph.kernel("gaussian", 0.1, dim=2)
    with pytest.raises(ValueError, match="dim=1"):
        sph.WendlandC4(0.1, dim=1)
    eos = sph.Tait(**EOS)
    with pytest.raises(ValueError, match="rho has negative entries"):
        eos.pressure(jnp.array([1000.0, -1.0]))
    with pytest.raises(ValueError, match="c0 must be finite and > 0"):
        sph.Tait(rho0=1000.0, c0=0.0)
    k = sph.CubicSpline(0.1, dim=2)
    with pytest.raises(ValueError, match="displacement must return"):
        sph.acceleration(space.metric(disp), k, eos)
    with pytest.raises(ValueError, match="alpha"):
        sph.acceleration(disp, k, eos, alpha=-1.0)
    R = jnp.zeros((4, 2)) + jnp.arange(4.0)[:, None] * 0.05
    nbrs = partition.neighbor_list(disp, 1.0, 0.2,
                                   disable_cell_list=True).allocate(R)
    with pytest.raises(ValueError, match=r"mass has shape \(3,\)"):
        sph.density(disp, k, mass=jnp.ones(3))(R, nbrs)
    with pytest.raises(ValueError, match="dim=3"):
        sph.density(disp, sph.CubicSpline(0.1, dim=3))(R, nbrs)
    with pytest.raises(ValueError, match="rho has negative entries"):
        sph.acceleration(disp, k, eos)(R, R, nbrs, rho=-jnp.ones(4))


def test_unknown_keyword_names_it_and_the_accepted_ones():
    """As the LJ energy: a typo raises TypeError with a suggestion and the
    list of accepted keywords (Python's own message had neither)."""
    disp, _ = space.free()
    k = sph.CubicSpline(0.1, dim=2)
    R = jnp.zeros((4, 2)) + jnp.arange(4.0)[:, None] * 0.05
    nbrs = partition.neighbor_list(disp, 1.0, 0.2,
                                   disable_cell_list=True).allocate(R)
    with pytest.raises(TypeError, match=r"\['hh'\].*did you mean 'h'\?.*"
                       r"accepts h, mass"):
        sph.density(disp, k)(R, nbrs, hh=0.2)
    with pytest.raises(TypeError, match=r"did you mean 'alpha'\?.*accepts "
                       r"rho, pressure"):
        sph.acceleration(disp, k, sph.Tait(**EOS))(R, R, nbrs, alpah=0.2)
    assert sph.density(disp, k)(R, nbrs, h=0.12, mass=2.0).shape == (4,)


def test_under_jit_bad_values_poison_with_nan():
    """Traced values cannot raise; as documented they give NaN, not a
    plausible wrong number."""
    disp, _ = space.free()
    R = jnp.zeros((4, 2)) + jnp.arange(4.0)[:, None] * 0.05
    nbrs = partition.neighbor_list(disp, 1.0, 0.3,
                                   disable_cell_list=True).allocate(R)
    density = sph.density(disp, sph.CubicSpline(0.1, dim=2))
    rho = jax.jit(lambda h: density(R, nbrs, h=h))(-0.1)
    assert np.all(np.isnan(rho))
    p = jax.jit(sph.Tait(**EOS).pressure)(jnp.array([1000.0, -1.0]))
    assert np.isfinite(p[0]) and np.isnan(p[1])
    rho = jax.jit(lambda h: density(R, nbrs, h=h))(0.1)
    assert math.isfinite(float(rho[0]))


@pytest.mark.parametrize("fmt", [partition.Sparse, partition.OrderedSparse])
def test_edge_layout_sums_scatter_materialized_edges_in_reverse_only(fmt):
    # An SPH step runs forward: its per-pair terms fuse into their
    # scatter-adds as XLA likes (a forward barrier made the H200's
    # OrderedSparse step slower). Differentiated (a fit of h or the EOS),
    # the cotangents are written out before reverse mode's scatters
    # (jaxrt.layouts.edges). A Dense list has no scatter and no barrier.
    def loss(R, V, nbrs):
        out = _ACCEL1(R, V, nbrs)
        return jnp.sum(out.density) + jnp.sum(out.pressure ** 2)

    forward, reverse = {}, {}
    for f in (fmt, partition.Dense):
        nbrs = partition.neighbor_list(DISP1, SIDE1, float(KERNEL1.cutoff),
                                       format=f).allocate(R1)
        forward[f] = _sph1.lower(R1, V1, nbrs).as_text()
        reverse[f] = jax.jit(jax.grad(loss)).lower(R1, V1, nbrs).as_text()
    for texts in (forward, reverse):
        assert "optimization_barrier" not in texts[partition.Dense]
        assert "scatter" in texts[fmt]
    assert "optimization_barrier" not in forward[fmt]
    assert "optimization_barrier" in reverse[fmt]
    # Forward mode still works (a custom JVP, not a custom VJP) and agrees
    # with the Dense list's, which has no barrier at all.
    tangent = jnp.asarray(np.random.default_rng(3).normal(size=R1.shape),
                          R1.dtype)  # not a translation, whose tangent is 0
    jvps = {}
    for f in (fmt, partition.Dense):
        nbrs = partition.neighbor_list(DISP1, SIDE1, float(KERNEL1.cutoff),
                                       format=f).allocate(R1)
        jvps[f] = jax.jvp(lambda R, n=nbrs: _ACCEL1(R, V1, n).pressure,
                          (R1,), (tangent,))[1]
        if f is partition.Dense:
            terms = int(jnp.max(jnp.sum(nbrs.idx < len(R1), axis=1)))
    scale = np.abs(np.asarray(jvps[partition.Dense])).max()
    assert np.all(np.isfinite(np.asarray(jvps[fmt]))) and scale > 0
    # The same pair terms summed in another order: each sum of at most
    # `terms` terms rounds differently by up to `terms` eps of its largest
    # term, taken as the largest tangent (no cancellation in this box).
    np.testing.assert_allclose(jvps[fmt], jvps[partition.Dense],
                               atol=terms * np.finfo(np.float32).eps * scale)
