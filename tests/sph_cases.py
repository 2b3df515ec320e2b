"""Scenes, references and checks shared by the list-free SPH tests
(tests/energy/test_sph_fused.py, tests/energy/test_sph_fused_warp.py):
each list-free walk against `jaxrt.energy.sph` on jax-md's all-pairs Dense
list (an independent search). Tolerances are the test modules'."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax_md import partition, space

from jaxrt.energy import acceleration_fused, density_fused, sph

RTOL = 1e-12
EOS = sph.Tait(rho0=1.0, c0=10.0, gamma=7.0)
KERNEL = {2: sph.CubicSpline(1.3, dim=2), 3: sph.WendlandC2(1.3, dim=3)}


def close(a, b, rtol=RTOL, row_scale=None):
    """``a == b`` to ``rtol`` of b's largest entry (shapes equal), or of
    ``row_scale[i]`` (float ``(N,)``) for row ``i`` where that is larger."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    scale = max(float(np.max(np.abs(b), initial=0.0)), 1e-300)
    if row_scale is None:
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)
        return
    rows = np.maximum(np.asarray(row_scale), scale)
    atol = rtol * rows.reshape(rows.shape + (1,) * (b.ndim - 1))
    bad = np.abs(a - b) > atol
    assert not np.any(bad), (f"{np.sum(bad)} entries differ beyond {rtol} "
                             f"of their row's scale: {a[bad]} vs {b[bad]}")


def fluid(n_side, dim, dx=1.0, seed=0, jitter=0.2):
    """A jittered lattice in ``[0, n_side dx)``: (R float64 (N, dim), side)."""
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * dim, indexing="ij"),
                 -1).reshape(-1, dim) * dx
    rng = np.random.default_rng(seed)
    side = n_side * dx
    return (g + rng.uniform(-jitter, jitter, g.shape) * dx) % side, side


def fluid_state(n_side, dim, seed=0):
    """`fluid` with velocities (normal) and masses (uniform in [0.8, 1.2]):
    (R, V, mass) as float64 arrays ((N, dim), (N, dim), (N,)) and the
    side."""
    R, side = fluid(n_side, dim, seed=seed)
    rng = np.random.default_rng(seed + 1)
    V = rng.normal(0, 1.0, R.shape)
    mass = rng.uniform(0.8, 1.2, len(R))
    return jnp.asarray(R), jnp.asarray(V), jnp.asarray(mass), side


def neighbour_fn(displacement, box, cutoff, **kw):
    """jax-md's all-pairs Dense list (the references' list)."""
    return partition.neighbor_list(
        displacement, box if box is not None else 1.0, cutoff,
        format=partition.Dense, disable_cell_list=True,
        capacity_multiplier=2.0, **kw)


def loss_of_every_input(accel, weights, R, V, h, m, a, b, rho0, c0, gamma):
    """A scalar of ``accel``'s outputs (its accelerations weighted by
    ``weights``, its densities) as a function of every differentiable
    input: positions, velocities, h, masses, alpha, beta and the Tait
    parameters (``accel(R, V, **keywords)``)."""
    out = accel(R, V, h=h, mass=m, alpha=a, beta=b,
                eos=sph.Tait(rho0, c0, gamma))
    return jnp.sum(weights * out.total) + jnp.sum(jnp.sin(out.density))


def check_every_input_gradient(fused, ref, nbrs, R, V, mass):
    """The gradients of `loss_of_every_input` through the list-free
    ``fused`` == through the list path's ``ref`` on ``nbrs`` (finite,
    `RTOL`), at h 1.2, alpha 0.5, beta 0.3 and Tait (1.1, 9.0, 7.0)."""
    weights = jnp.asarray(np.random.default_rng(5).normal(size=R.shape))
    args = (R, V, 1.2, mass, 0.5, 0.3, 1.1, 9.0, 7.0)

    def listed(R, V, **k):
        return ref(R, V, nbrs, **k)

    grads = [jax.jit(jax.grad(
        lambda *a, fn=fn: loss_of_every_input(fn, weights, *a),
        argnums=tuple(range(9))))(*args) for fn in (fused, listed)]
    for x, y in zip(*grads):
        assert np.all(np.isfinite(x))
        close(x, y)


def check_momentum(mass, acc):
    """Momentum conserved: every pair term is antisymmetric, so the
    mass-weighted accelerations sum to rounding."""
    total = jnp.sum(mass[:, None] * acc.total, axis=0)
    assert float(jnp.max(jnp.abs(total))) < 1e-10 * float(
        jnp.max(jnp.abs(mass[:, None] * acc.total)))


def check_coincident_and_exact_support(dim, backend):
    """Free particles (support 1.0): coincident, exactly the support apart
    (nothing counted), inside, and 1e-9 apart. Densities against the
    kernel's values; accelerations against the list path, finite, and zero
    on the coincident and support pairs. Returns (accel, ref, nbrs, R, V)
    for further checks."""
    kernel = sph.CubicSpline(0.5, dim=dim)   # support 2h = 1.0
    pad = (0.0,) * (dim - 2)
    R = jnp.asarray([[1.0, 1.0, *pad], [1.0, 1.0, *pad],   # coincident
                     [5.0, 5.0, *pad], [6.0, 5.0, *pad],   # the support
                     [1.0, 8.0, *pad], [1.6, 8.0, *pad],   # inside
                     [8.0, 1.0, *pad], [8.0, 1.0 + 1e-9, *pad]])
    V = jnp.asarray(np.random.default_rng(0).normal(size=R.shape))
    displacement, _ = space.free()
    rho = density_fused(displacement, None, kernel, backend=backend)(R)
    w0, w = kernel.w(jnp.zeros(())), kernel.w(jnp.asarray(0.6))
    w_near = kernel.w(jnp.asarray(1e-9))
    close(rho, jnp.asarray([2 * w0, 2 * w0, w0, w0, w0 + w, w0 + w,
                            w0 + w_near, w0 + w_near]))
    accel = acceleration_fused(displacement, None, kernel, EOS, alpha=1.0,
                               beta=1.0, backend=backend)
    nbrs = neighbour_fn(displacement, None, float(kernel.cutoff)).allocate(R)
    ref = sph.acceleration(displacement, kernel, EOS, alpha=1.0, beta=1.0)
    out = accel(R, V)
    want = jax.jit(ref)(R, V, nbrs)
    # The 1e-9 pair's viscosity (~1e-13) is a sliver of that pair's pressure
    # force (~1e-4, the same kernel gradient): a walk may round it anywhere
    # within float64's rtol of the particle's largest pair term, which is
    # the scale each row is held to (not the viscosity column's own max).
    row_scale = np.max([np.max(np.abs(np.asarray(f)), -1) for f in want
                        if np.ndim(f) == 2], 0)
    for a, b in zip(out, want):
        assert np.all(np.isfinite(a))
        close(a, b, row_scale=row_scale if np.ndim(b) == 2 else None)
    np.testing.assert_array_equal(np.asarray(out.total[:4]), 0.0)
    return accel, ref, nbrs, R, V


def check_scan_steps_match_list(dim, n_side, backend=None):
    """Five explicit steps of a periodic fluid under ``jit`` and
    ``lax.scan``: the list-free walk's trajectory is the list path's (its
    list updated each step, 0.1 skin)."""
    R, V, _, side = fluid_state(n_side, dim)
    displacement, shift = space.periodic(side)
    kernel = KERNEL[dim]
    kw = {} if backend is None else dict(backend=backend)
    fused = acceleration_fused(displacement, side, kernel, EOS, mass=1.0,
                               alpha=0.2, **kw)
    ref = sph.acceleration(displacement, kernel, EOS, mass=1.0, alpha=0.2)
    nfn = neighbour_fn(displacement, side, float(kernel.cutoff),
                       dr_threshold=0.1)
    dt = 1e-3

    @jax.jit
    def run_fused(R, V):
        def step(carry, _):
            R, V = carry
            V = V + dt * fused(R, V).total
            return (shift(R, dt * V), V), None
        return lax.scan(step, (R, V), None, length=5)[0]

    @jax.jit
    def run_list(R, V, nbrs):
        def step(carry, _):
            R, V, nbrs = carry
            V = V + dt * ref(R, V, nbrs).total
            R = shift(R, dt * V)
            return (R, V, nbrs.update(R)), None
        return lax.scan(step, (R, V, nbrs), None, length=5)[0]

    R1, V1 = run_fused(R, V)
    R2, V2, nbrs = run_list(R, V, nfn.allocate(R))
    assert not nbrs.did_buffer_overflow
    close(R1, R2)
    close(V1, V2, 1e-11)
