"""Library-level cases of `jaxrt.sim.domains`, run by tests/sim/test_domains.py in
a subprocess with 4 fake CPU devices (the count must be set before JAX
starts). Each case prints ``CASE <name> ok``; any failure raises.

    XLA_FLAGS=--xla_force_host_platform_device_count=4 \\
        python tests/domains_cases.py [case ...]
"""
import dataclasses
import functools
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxrt import sim  # noqa: E402
from jaxrt.sim import domains
from jaxrt.sim.domains import Decomposition, DomainError, decompose  # noqa: E402
from jaxrt.energy import lennard_jones_pair_neighbor_list  # noqa: E402

BACKEND = "brute"  # quick to compile; the CLI test runs the cell list


def lj_energy(d):
    return lennard_jones_pair_neighbor_list(d, r_onset=2.0, r_cutoff=2.5,
                                            per_particle=True)


def lj_domains(L, devices=4, backend=BACKEND, rows=False, **dec):
    row = (lambda d: lennard_jones_pair_neighbor_list(
        d, r_onset=2.0, r_cutoff=2.5)) if rows else None
    return decompose(box_size=(L,) * 3, periodic=True, cutoff=2.5, skin=0.3,
                     energy=lj_energy, backend=backend, row_energy=row,
                     decomposition=Decomposition(devices=devices, **dec))


def by_gid(dom, state, values):
    gid = np.asarray(state.gid)
    out = np.zeros((dom.n, values.shape[-1]))
    out[gid[gid >= 0]] = np.asarray(values)[gid >= 0]
    return out


def case_forces():
    """Energy, forces (from the owned rows) and jax.grad of the decomposed
    energy (through shard_map and the halo) equal the single-device ones
    (float64)."""
    scene = dataclasses.replace(sim.lj_fluid(n=1200, backend=BACKEND),
                                dtype="float64")
    compiled = sim.compile_scene(scene)
    s0, nbrs = compiled.init()
    from jaxrt.sim.compile import _Forces  # the single device's potential
    ctx = sim.Context(scene, compiled.displacement, jnp.float64, 1.0)
    u1 = float(_Forces.collect(scene, ctx, []).potential(s0.position, nbrs))
    # Forces from the owned rows (energy_and_forces, row_energy) and from
    # jax.grad of the energy through shard_map and the halo exchange.
    dom = lj_domains(scene.box.size[0], rows=True)
    st = dom.distribute(scene.particles.positions, dtype=jnp.float64)
    u, f = jax.jit(dom.energy_and_forces)(st)
    g = jax.jit(jax.grad(lambda R: dom.energy(st._replace(position=R))))(
        st.position)
    F1 = np.asarray(s0.accel)
    assert abs(float(u) - u1) < 1e-9 * abs(u1), (float(u), u1)
    assert np.abs(by_gid(dom, st, f) - F1).max() < 1e-10
    assert np.abs(by_gid(dom, st, -g) - F1).max() < 1e-10
    # Empty slots get no force.
    assert not np.any(np.asarray(f)[np.asarray(st.gid) < 0])

    # The README's user step: energy_and_forces, move, update, under jit.
    @jax.jit
    def step(state):
        U, F = dom.energy_and_forces(state)
        drift = jnp.asarray([0.06, 0.0, 0.0])  # across the faces
        state = state._replace(position=state.position + 1e-4 * F + drift)
        return dom.update(state), U
    for _ in range(8):
        st, U = step(st)
    dom.check(st)
    assert int(np.asarray(st.rebuilds)[0]) >= 2  # it did migrate / rebuild
    R = dom.gather(st)
    potential = _Forces.collect(scene, ctx, []).potential
    u1 = float(potential(jnp.asarray(R), compiled.neighbor_fn.allocate(
        jnp.asarray(R))))
    u4 = float(jax.jit(dom.energy)(st))
    assert abs(u4 - u1) < 1e-9 * abs(u1), (u4, u1)


def streaming_lattice(planes, v_of_layer):
    """4 x 4 x 4 sites at spacing 3 in a periodic box of 12 (4 slabs of 3
    along x); only the x-planes in ``planes``; velocity along x per
    y-layer. No pair is within the cutoff, ever: free streaming."""
    g = np.stack(np.meshgrid(np.asarray(planes), np.arange(4), np.arange(4),
                             indexing="ij"), -1).reshape(-1, 3)
    R = (g + 0.5) * 3.0
    V = np.zeros_like(R)
    V[:, 0] = v_of_layer(g[:, 1])
    return R, V


@functools.lru_cache(maxsize=None)
def streaming_domains():
    """One decomposition (and compiled chunk) for the streaming cases:
    fixed capacities, so both cases run the same programs."""
    dom = lj_domains(12.0, capacity=40, halo_capacity=40)
    return dom, domains.chunk_fn(dom, 0.05)


def run_streaming(R, V, steps):
    dom, chunk = streaming_domains()
    dt = 0.05
    st = dom.distribute(R, V, dtype=jnp.float64)
    seen_empty = set()
    for _ in range(steps // 10):
        st, rec = chunk(st, steps=10)
        dom.check(st)
        counts = np.sum(np.asarray(st.gid) >= 0, axis=1)
        seen_empty |= set(np.flatnonzero(counts == 0).tolist())
    want = np.mod(R + V * dt * steps, 12.0)
    got = dom.gather(st)
    d = got - want
    d -= 12.0 * np.round(d / 12.0)
    assert np.abs(d).max() < 1e-9, np.abs(d).max()
    return st, seen_empty


def owners_ok(dom, st):
    st = dom.rebuild(st)  # migrate now
    gid = np.asarray(st.gid)
    x = np.asarray(st.position)[..., 0]
    for d in range(4):
        ok = gid[d] >= 0
        assert np.all((x[d][ok] >= 3.0 * d) & (x[d][ok] < 3.0 * (d + 1))), d


def case_migration():
    """Particles cross every face both ways (the periodic end too): the
    decomposed run equals free streaming; each device owns its slab."""
    R, V = streaming_lattice(range(4), lambda j: np.where(j % 2, -2.0, 2.0))
    st, _ = run_streaming(R, V, steps=130)
    dom = streaming_domains()[0]
    assert int(np.asarray(st.rebuilds)[0]) >= 40
    owners_ok(dom, st)


def case_empty_domain():
    """Two slabs hold everything, moving +x: slabs empty and fill again;
    at distribution two devices own nothing."""
    R, V = streaming_lattice([0, 1], lambda j: 2.0 + 0 * j)
    dom = streaming_domains()[0]
    st0 = dom.distribute(R, V, dtype=jnp.float64)
    counts = np.sum(np.asarray(st0.gid) >= 0, axis=1)
    assert counts.tolist() == [16, 16, 0, 0], counts
    st, empty = run_streaming(R, V, steps=130)
    assert empty == {0, 1, 2, 3}, empty  # every device was empty once
    owners_ok(dom, st)


def case_redo():
    """run_chunk throws away a chunk that overflowed, distributes again
    (reallocating) and redoes it: the same result as without overflow."""
    dom, chunk = streaming_domains()
    R, V = streaming_lattice(range(4), lambda j: np.where(j % 2, -2.0, 2.0))
    st = dom.distribute(R, V, dtype=jnp.float64)
    calls = []

    def flaky(state, steps):
        new, rec = chunk(state, steps=steps)
        if not calls:  # the first call reports a list overflow
            new = new._replace(error=new.error | int(domains.Overflow.LIST))
        calls.append(steps)
        return new, rec
    stats = {}
    new, _ = domains.run_chunk(dom, flaky, st, 10, stats)
    assert stats == {"redone": 1} and calls == [10, 10], (stats, calls)
    dom.check(new)
    want = np.mod(R + V * 0.05 * 10, 12.0)
    d = dom.gather(new) - want
    assert np.abs(d - 12.0 * np.round(d / 12.0)).max() < 1e-9


def case_overflow():
    """A full slab is flagged and check() names the capacity to raise."""
    R, V = streaming_lattice([0, 1], lambda j: 0 * j)
    dom = lj_domains(12.0, capacity=20, halo_capacity=40)
    st = dom.distribute(R, V, dtype=jnp.float64)
    moved = st.position.at[1, :, 0].add(-3.0)  # slab 1's into slab 0
    st = jax.jit(dom.update)(st._replace(position=moved))
    assert dom.errors(st) & domains.Overflow.OWNED
    try:
        dom.check(st)
    except DomainError as e:
        assert "Decomposition.capacity" in str(e), e
    else:
        raise AssertionError("no error")


def case_nonfinite():
    """A NaN position is named as such, not as a list overflow whose fix
    (distribute again) cannot help."""
    R, V = streaming_lattice([0, 1], lambda j: 0 * j)
    dom = lj_domains(12.0, capacity=20, halo_capacity=40)
    st = dom.distribute(R, V, dtype=jnp.float64)
    first = int(jnp.argmax(st.gid[0] >= 0))
    bad = st.position.at[0, first, 0].set(jnp.nan)
    st = jax.jit(dom.update)(st._replace(position=bad))
    bits = dom.errors(st)
    assert bits & domains.Overflow.NONFINITE, bits
    assert not bits & domains.Overflow.LIST, bits
    try:
        dom.check(st)
    except DomainError as e:
        assert "NaN or infinite" in str(e), e
        assert "overflowed" not in str(e), e
    else:
        raise AssertionError("no error")


CASES = {k[5:]: v for k, v in dict(globals()).items()
         if k.startswith("case_")}

if __name__ == "__main__":
    assert len(jax.devices()) >= 4, jax.devices()
    for name in sys.argv[1:] or CASES:
        t = time.perf_counter()
        CASES[name]()
        print(f"CASE {name} ok ({time.perf_counter() - t:.1f} s)",
              flush=True)
