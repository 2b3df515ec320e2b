"""Domain decomposition over several devices: slabs, halos, migration.

The box is cut into ``devices`` slabs of equal width along one axis
(``Decomposition.axis``, x by default), one slab per device of a 1-D
`jax.sharding.Mesh`. Everything runs inside `jax.shard_map`:

* each device **owns** the particles in its slab, in ``capacity`` padded
  slots (a global id per slot, ``-1`` for an empty one);
* it **receives the halo**: the particles of its two neighbours within
  ``w = cutoff + skin`` of its faces, in ``halo_capacity`` slots per face,
  by `jax.lax.ppermute` (periodic images shifted by the box side at the
  ends of a periodic axis; nothing crosses a wall or free end);
* it builds its own neighbour list with any `jaxrt` backend on owned +
  halo particles (Dense, the split axis treated as free, the other axes as
  the box says). Empty slots sit on a parking lattice far outside the slab,
  spaced wider than the list's reach, so they have no neighbours;
* energies: the per-particle energy (each pair split half and half between
  its two particles) summed over **owned** particles only, then
  `jax.lax.psum`: an owned-owned pair is counted once on its device, an
  owned-halo pair half on each of the two devices. Forces are ``-jax.grad``
  of that energy through ``shard_map``: the halo cotangents travel back to
  the owners through the transpose of the ``ppermute``. With
  ``row_energy`` the steps take each owned particle's force from its own
  Dense row instead (its row holds all its neighbours): no reverse
  exchange, no scatter;
* **rebuild**, when some particle moved more than ``skin / 2`` since the
  last one (the rule of the single-device list, decided over all devices
  with `jax.lax.pmax` inside a `jax.lax.cond`): positions are wrapped,
  particles that crossed a face go to the neighbour that now owns them
  (``migrate_capacity`` per face), halos are chosen again and the lists
  rebuilt. Between rebuilds halo positions are refreshed every step.

Overflow is never silent: a full owned, halo or migration buffer, a
particle that moved further than one slab, and a neighbour-list overflow
set bits of `DomainState.error` (sticky); `check` raises naming the
capacity to raise. A halo wider than a slab (``cutoff + skin > side /
devices``) and too few devices are refused when the functions are made.

    import jaxrt
    from jaxrt.sim.domains import Decomposition, decompose
    from jaxrt.energy import lennard_jones_pair_neighbor_list

    dom = decompose(
        box_size=(L, L, L), periodic=True, cutoff=2.5, skin=0.3,
        energy=lambda d: lennard_jones_pair_neighbor_list(
            d, r_onset=2.0, r_cutoff=2.5, per_particle=True),
        decomposition=Decomposition(devices=4))
    state = dom.distribute(R, V)              # host: place, pad, build
    state = dom.forces_into(state)            # the first accelerations
    step = jax.jit(functools.partial(dom.verlet_step, dt=0.005))
    for _ in range(100):
        state, (ke, pe, mom) = step(state)
    dom.check(state)                          # raises on any overflow
    R_final = dom.gather(state)               # (N, dim), global order

For your own integrator: ``dom.energy(state)`` (a scalar,
differentiable in ``state.position``), ``dom.energy_and_forces(state)``,
then ``dom.update(state)`` after moving ``state.position``.

One module past 800 lines on purpose: one decomposition (sharding,
halos, migration, its checks).
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P
from jax_md import partition

from jaxrt.errors import Bits, Error, raise_for
from jaxrt.lists import neighbors as _neighbors

__all__ = ["Decomposition", "DomainError", "DomainState", "Domains",
           "decompose", "shard_map"]

if hasattr(jax, "shard_map"):
    def shard_map(f, *, mesh, in_specs, out_specs):
        """`jax.shard_map` without the varying-axis checks (jaxrt's Pallas
        cell kernel declares no mesh axes on its outputs)."""
        return jax.shard_map(f, mesh=mesh, in_specs=in_specs,
                             out_specs=out_specs, check_vma=False)
else:  # older JAX
    from jax.experimental.shard_map import shard_map as _old

    def shard_map(f, *, mesh, in_specs, out_specs):
        return _old(f, mesh=mesh, in_specs=in_specs, out_specs=out_specs,
                    check_rep=False)


class DomainError(Error, ValueError):
    """A decomposition that cannot work, or a run that overflowed."""


@enum.unique
class Overflow(Bits):
    """Bits of `DomainState.error`."""
    OWNED = 1 << 0       # more particles in a slab than capacity
    HALO = 1 << 1        # more halo particles at a face than halo_capacity
    MIGRATION = 1 << 2   # more crossing a face than migrate_capacity
    TOO_FAR = 1 << 3     # a particle moved further than one slab
    LIST = 1 << 4        # a device's neighbour list overflowed
    NONFINITE = 1 << 5   # a position is NaN or infinite


_FIX = {
    Overflow.OWNED: "raise Decomposition.capacity (owned slots per device)",
    Overflow.HALO: "raise Decomposition.halo_capacity (halo slots per face)",
    Overflow.MIGRATION: "raise Decomposition.migrate_capacity (particles "
                        "crossing one face at one rebuild)",
    Overflow.TOO_FAR: "a particle moved more than one slab between two "
                      "rebuilds: lower the time step (positions may have "
                      "blown up)",
    Overflow.LIST: "a device's neighbour list overflowed: distribute again "
                   "(it reallocates) or raise capacity_multiplier",
    Overflow.NONFINITE: "a particle's position is NaN or infinite (the "
                        "run blew up): lower the time step or check the "
                        "initial positions; distributing again cannot help",
}


@dataclasses.dataclass(frozen=True)
class Decomposition:
    """How to cut the box: ``devices`` slabs along box axis ``axis``.

    capacity: owned slots per device; halo_capacity: halo slots per face
    per device; migrate_capacity: particles crossing one face at one
    rebuild. None: sized by `Domains.distribute` from the initial
    particles (``slack`` times the fullest device, plus 16).
    axis_name: the mesh axis's name.
    """
    devices: int
    axis: int = 0
    capacity: int | None = None
    halo_capacity: int | None = None
    migrate_capacity: int | None = None
    slack: float = 1.5
    axis_name: str = "domains"

    def __post_init__(self):
        if not (isinstance(self.devices, (int, np.integer))
                and self.devices >= 1):
            raise DomainError(f"Decomposition.devices must be an int >= 1; "
                              f"got {self.devices!r}.")
        for k in ("capacity", "halo_capacity", "migrate_capacity"):
            v = getattr(self, k)
            if v is not None and not (isinstance(v, (int, np.integer))
                                      and v >= 1):
                raise DomainError(f"Decomposition.{k} must be an int >= 1 "
                                  f"or None; got {v!r}.")
        if not self.slack >= 1:
            raise DomainError("Decomposition.slack must be >= 1.")


class DomainState(NamedTuple):
    """Per-device arrays, each with a leading axis of ``devices`` (sharded
    over the mesh). ``C`` owned slots, ``H`` halo slots per face.

    position, velocity, accel: float ``(devices, C, dim)`` of the owned
    slots, in each device's frame (not wrapped along the split axis between
    rebuilds; `Domains.gather` wraps). gid: int32 ``(devices, C)``, global
    ids, -1 in empty slots. send: int32 ``(devices, 2, H)``, the owned
    slots sent to the (left, right) neighbour's halo (C where empty).
    shift: float ``(devices, 2)``, what is added along the split axis to
    what is sent (the box side across a periodic end). halo_gid: int32
    ``(devices, 2H)``: ids of the halo received (from the right neighbour,
    then from the left), -1 where empty. nbrs: the devices' lists, jax-md
    `NeighborList`s with the same leading axis. rebuilds: int32
    ``(devices,)``. error: int32 ``(devices,)``, `Overflow` bits, sticky.
    """
    position: jax.Array
    velocity: jax.Array
    accel: jax.Array
    gid: jax.Array
    send: jax.Array
    shift: jax.Array
    halo_gid: jax.Array
    nbrs: Any
    rebuilds: jax.Array
    error: jax.Array

    def check(self) -> None:
        """Raise `DomainError` naming each overflow, its devices and its
        fix; host-side (`jaxrt.check` does the same)."""
        per = np.asarray(self.error)
        raise_for(Overflow.of(per), {
            b: f"{b.name} on device(s) "
               f"{np.flatnonzero(per & int(b)).tolist()}: {_FIX[b]}"
            for b in Overflow}, DomainError, "domain decomposition "
            "failed (results since then are wrong): ")

    @property
    def capacity(self) -> int:
        return self.position.shape[1]

    @property
    def halo_capacity(self) -> int:
        return self.send.shape[2]


def _local_displacement(periodic, side, axis: int):
    """Minimum image on the periodic axes other than ``axis``; a plain
    difference on ``axis`` and non-periodic axes."""
    axes = [a for a, p in enumerate(periodic) if p and a != axis]
    if not axes:
        return lambda ra, rb, **kw: ra - rb
    L = np.asarray(side, float)[axes]

    def displacement(ra, rb, **kw):
        d = ra - rb
        Ld = jnp.asarray(L, d.dtype)
        w = d[..., axes] - Ld * jnp.round(d[..., axes] / Ld)
        return d.at[..., axes].set(w)
    return displacement


def _unstack(tree):
    return jax.tree_util.tree_map(lambda x: x[0], tree)


def _stack(tree):
    return jax.tree_util.tree_map(lambda x: x[None], tree)


def _compact(mask, size: int, fill: int):
    """Indices of the first ``size`` True entries of ``mask`` (``fill``
    after them) and whether there were more."""
    idx = jnp.nonzero(mask, size=size, fill_value=fill)[0]
    return idx.astype(jnp.int32), jnp.sum(mask) > size


@dataclasses.dataclass(frozen=True, eq=False)
class Domains:
    """The functions of one decomposition (made by `decompose`).

    distribute(R, V=None) -> DomainState (host, eager); update(state) ->
    state (halo refresh; migration, halos and lists again when a particle
    moved more than skin / 2); energy(state) -> float (); energy_and_forces
    (state) -> (energy, forces ``(devices, C, dim)``); verlet_step(state,
    dt, mass=1.0) -> (state, (kinetic, potential, momentum));
    gather(state, what="position") -> ``(N, dim)`` in global order;
    pairs(state) -> sorted global ``i * N + j`` (i < j) of the lists;
    check(state) raises `DomainError` on any overflow bit.
    """
    decomposition: Decomposition
    mesh: Mesh
    box_size: np.ndarray
    periodic: tuple
    cutoff: float
    skin: float
    neighbor_fn: Any
    local_energy: Callable
    displacement: Callable
    n: int = 0
    one_body: Callable | None = None
    density: Callable | None = None
    accel: Callable | None = None
    row_energy: Callable | None = None

    # -- geometry ---------------------------------------------------------
    @property
    def devices(self) -> int:
        return self.decomposition.devices

    @property
    def axis(self) -> int:
        return self.decomposition.axis

    @property
    def width(self) -> float:
        """Slab width along the split axis."""
        return float(self.box_size[self.axis]) / self.devices

    @property
    def halo_width(self) -> float:
        return self.cutoff + self.skin

    def _spec(self):
        return P(self.decomposition.axis_name)

    def _smap(self, fn, n_in: int, n_out: int):
        spec = self._spec()
        ins = tuple([spec] * n_in)
        outs = spec if n_out == 1 else tuple([spec] * n_out)
        return shard_map(fn, mesh=self.mesh, in_specs=ins, out_specs=outs)

    def _parking(self, count: int, dtype, lo=0.0):
        """``count`` sites beyond the reach of the slab starting at ``lo``
        (its frame), spaced by more than the list's reach (no
        neighbours). Computed from an iota (no large constant in the
        compiled program)."""
        dim = len(self.box_size)
        s = 1.5 * self.halo_width + 1e-3
        rest = jnp.arange(count, dtype=jnp.int32)
        cols = [None] * dim
        for a in range(dim):
            if a == self.axis:
                continue
            L = float(self.box_size[a])
            m = max(1, int(L // s)) if L > 0 and math.isfinite(L) else 64
            cols[a] = (rest % m).astype(dtype) * s
            rest = rest // m
        cols[self.axis] = (jnp.asarray(lo, dtype) + (
            self.width + 3 * self.halo_width + 2 * s)
            + rest.astype(dtype) * s)
        return jnp.stack(cols, axis=-1)

    def _frame(self, me, dtype):
        """(lo, hi) of device ``me``'s slab along the split axis."""
        lo = me.astype(dtype) * jnp.asarray(self.width, dtype)
        return lo, lo + jnp.asarray(self.width, dtype)

    # -- halo ---------------------------------------------------------------
    def _perms(self):
        n = self.devices
        left = [(i, (i - 1) % n) for i in range(n)]
        right = [(i, (i + 1) % n) for i in range(n)]
        return left, right

    def _exchange(self, X, send, shift=None, fill=0.0):
        """Values of the halo, ``(2H,) + X.shape[1:]``, from the owners'
        ``X`` (per owned slot): from the right neighbour (its left face),
        then from the left one; ``fill`` where empty. ``shift``: added
        along the split axis (positions)."""
        name = self.decomposition.axis_name
        left, right = self._perms()
        C = X.shape[0]
        out = []
        for face, perm in ((0, left), (1, right)):
            idx = send[face]
            vals = X[jnp.minimum(idx, C - 1)]
            if shift is not None:
                vals = vals.at[:, self.axis].add(shift[face])
            ok = (idx < C).reshape((-1,) + (1,) * (X.ndim - 1))
            vals = jnp.where(ok, vals, fill)
            out.append(lax.ppermute(vals, name, perm))
        return jnp.concatenate(out)

    def _halo(self, R, send, shift, park_halo):
        """Halo positions ``(2H, dim)``, parked where empty."""
        got = self._exchange(R, send, shift, fill=jnp.inf)
        ok = jnp.isfinite(got[:, 0])
        return jnp.where(ok[:, None], got, park_halo), ok

    def _local_positions(self, R, gid, send, shift):
        C = R.shape[0]
        H = send.shape[1]
        me = lax.axis_index(self.decomposition.axis_name)
        park = self._parking(C + 2 * H, R.dtype, self._frame(me, R.dtype)[0])
        Rown = jnp.where((gid >= 0)[:, None], R, park[:C])
        halo, _ = self._halo(R, send, shift, park[C:])
        return jnp.concatenate([Rown, halo])

    # -- energy ---------------------------------------------------------------
    def _energy_local(self, R, gid, send, shift, nbrs):
        """This device's share: owned particles' energies."""
        valid = gid >= 0
        u = jnp.zeros((), R.dtype)
        if self.local_energy is not None:
            Rloc = self._local_positions(R, gid, send, shift)
            e = self.local_energy(Rloc, nbrs)[:R.shape[0]]
            u = jnp.sum(jnp.where(valid, e, 0))
        if self.one_body is not None:
            u = u + self.one_body(R, valid)
        return u

    def _forces_local(self, R, gid, send, shift, nbrs, energy=True):
        if self.row_energy is None or self.local_energy is None:
            u, g = jax.value_and_grad(self._energy_local)(R, gid, send,
                                                          shift, nbrs)
            return u, -jnp.where((gid >= 0)[:, None], g, 0)
        # Rows: an owned particle's row holds all its neighbours, so the
        # per-row gradient of the local pair energy is its whole force;
        # no cotangents go back through the halo exchange.
        C = R.shape[0]
        valid = gid >= 0
        Rloc = self._local_positions(R, gid, send, shift)
        g = jax.grad(self.row_energy)(Rloc, nbrs)[:C]
        u = jnp.zeros((), R.dtype)
        if energy:  # the per-particle pass, for the energy only
            e = self.local_energy(Rloc, nbrs)[:C]
            u = jnp.sum(jnp.where(valid, e, 0))
        if self.one_body is not None:
            ub, gb = jax.value_and_grad(self.one_body)(R, valid)
            u, g = u + ub, g + gb
        return u, -jnp.where(valid[:, None], g, 0)

    def _other_accel(self, R, V, gid, send, shift, nbrs):
        """Accelerations not from the potential (SPH), ``(C, dim)``: the
        density on owned + halo, the halo's densities from their owners,
        then ``accel`` on owned + halo (velocities exchanged too)."""
        C = R.shape[0]
        Rloc = self._local_positions(R, gid, send, shift)
        Vloc = jnp.concatenate([V, self._exchange(V, send)])
        rho = jnp.zeros((0,), R.dtype)
        if self.density is not None:
            rho_own = self.density(Rloc, nbrs)[:C]
            rho = jnp.concatenate([rho_own, self._exchange(rho_own, send,
                                                           fill=1.0)])
        a = self.accel(Rloc, Vloc, nbrs, rho)[:C]
        return jnp.where((gid >= 0)[:, None], a, 0)

    def energy(self, state: DomainState) -> jax.Array:
        """Total energy, float ``()``; differentiable in ``state.position``
        (the gradient goes through ``shard_map`` and the halo exchange)."""
        name = self.decomposition.axis_name

        def body(R, gid, send, shift, nbrs):
            u = self._energy_local(R[0], gid[0], send[0], shift[0],
                                   _unstack(nbrs))
            return lax.psum(u, name)[None]
        spec = self._spec()
        f = shard_map(body, mesh=self.mesh, in_specs=(spec,) * 5,
                      out_specs=spec)
        return f(state.position, state.gid, state.send, state.shift,
                 state.nbrs)[0]

    def energy_and_forces(self, state: DomainState):
        """(total energy ``()``, forces float ``(devices, C, dim)``, zero in
        empty slots), the forces by `jax.grad` inside ``shard_map``."""
        name = self.decomposition.axis_name

        def body(R, gid, send, shift, nbrs):
            u, f = self._forces_local(R[0], gid[0], send[0], shift[0],
                                      _unstack(nbrs))
            return lax.psum(u, name)[None], f[None]
        u, f = self._smap(body, 5, 2)(state.position, state.gid, state.send,
                                       state.shift, state.nbrs)
        return u[0], f

    # -- rebuild: migration, halo choice, lists ----------------------------
    def _select_halo(self, R, gid, me, H: int):
        """send ``(2, H)`` and shift ``(2,)`` of owned ``R`` in ``me``'s
        frame (positions already wrapped into the slab)."""
        ax, n = self.axis, self.devices
        lo, hi = self._frame(me, R.dtype)
        x = R[:, ax]
        valid = gid >= 0
        w = jnp.asarray(self.halo_width, R.dtype)
        L = jnp.asarray(float(self.box_size[ax]), R.dtype)
        per = self.periodic[ax]
        to_left = valid & (x - lo < w)
        to_right = valid & (hi - x < w)
        if not per:  # nothing leaves through a wall or a free end
            to_left &= me > 0
            to_right &= me < n - 1
        C = R.shape[0]
        sl, ovl = _compact(to_left, H, C)
        sr, ovr = _compact(to_right, H, C)
        zero = jnp.zeros((), R.dtype)
        shift = jnp.stack([jnp.where(me == 0, L, zero) if per else zero,
                           jnp.where(me == n - 1, -L, zero) if per else zero])
        return jnp.stack([sl, sr]), shift, ovl | ovr

    def _migrate(self, R, V, A, gid, me, M: int):
        """Wrap, send the particles that left the slab to the neighbour
        that owns them now; returns (R, V, A, gid, error bits)."""
        ax, n = self.axis, self.devices
        name = self.decomposition.axis_name
        dtype = R.dtype
        C = R.shape[0]
        valid = gid >= 0
        # Wrap every periodic axis (the split one included) into the box.
        for a, p in enumerate(self.periodic):
            if p:
                L = jnp.asarray(float(self.box_size[a]), dtype)
                R = R.at[:, a].set(jnp.where(valid, jnp.mod(R[:, a], L),
                                             R[:, a]))
        err = jnp.zeros((), jnp.int32)
        if n == 1:
            return R, V, A, gid, err
        owner = jnp.clip(jnp.floor(R[:, ax] / self.width).astype(jnp.int32),
                         0, n - 1)
        right_dev, left_dev = (me + 1) % n, (me - 1) % n
        go_r = valid & (owner != me) & (owner == right_dev)
        go_l = valid & (owner != me) & (owner == left_dev) & ~go_r
        far = valid & (owner != me) & ~go_r & ~go_l
        err |= jnp.where(jnp.any(far), int(Overflow.TOO_FAR), 0)
        left, right = self._perms()
        recv = []
        for go, perm in ((go_l, left), (go_r, right)):
            idx, ov = _compact(go, M, C)
            err |= jnp.where(ov, int(Overflow.MIGRATION), 0)
            ok = idx < C
            j = jnp.minimum(idx, C - 1)
            pack = [jnp.where(ok[:, None], X[j], 0) for X in (R, V, A)]
            g = jnp.where(ok, gid[j], -1)
            recv.append([lax.ppermute(x, name, perm) for x in (*pack, g)])
        stay = valid & (owner == me)
        pool = [jnp.concatenate([X, recv[0][k], recv[1][k]])
                for k, X in enumerate((R, V, A))]
        pgid = jnp.concatenate([jnp.where(stay, gid, -1), recv[0][3],
                                recv[1][3]])
        idx, ov = _compact(pgid >= 0, C, pgid.shape[0])
        err |= jnp.where(ov, int(Overflow.OWNED), 0)
        ok = idx < pgid.shape[0]
        j = jnp.minimum(idx, pgid.shape[0] - 1)
        R, V, A = (jnp.where(ok[:, None], X[j], 0) for X in pool)
        gid = jnp.where(ok, pgid[j], -1)
        return R, V, A, gid, err

    def _rebuild_local(self, R, V, A, gid, send, nbrs, rebuilds, error):
        name = self.decomposition.axis_name
        me = lax.axis_index(name)
        C, H = R.shape[0], send.shape[1]
        M = self.decomposition.migrate_capacity or H
        R, V, A, gid, err = self._migrate(R, V, A, gid, me, M)
        send, shift, ovh = self._select_halo(R, gid, me, H)
        err |= jnp.where(ovh, int(Overflow.HALO), 0)
        park = self._parking(C, R.dtype, self._frame(me, R.dtype)[0])
        valid = gid >= 0
        R = jnp.where(valid[:, None], R, park)
        V = jnp.where(valid[:, None], V, 0)
        A = jnp.where(valid[:, None], A, 0)
        Rloc = self._local_positions(R, gid, send, shift)
        # Force the rebuild: a reference far from every position.
        far = Rloc.at[:, self.axis].add(10 * self.halo_width + 1.0)
        nbrs = self.neighbor_fn.update(Rloc, nbrs.set(reference_position=far))
        # A NaN position sets the list's overflow bit too; report the
        # cause, since reallocating (LIST's fix) cannot cure it.
        nonfinite = ~jnp.all(jnp.isfinite(jnp.where(valid[:, None], R, 0)))
        err |= jnp.where(nonfinite, int(Overflow.NONFINITE), 0)
        err |= jnp.where((nbrs.did_buffer_overflow > 0) & ~nonfinite,
                         int(Overflow.LIST), 0)
        halo_gid = self._halo_gid(gid, send)
        return (R, V, A, gid, send, shift, halo_gid, nbrs, rebuilds + 1,
                error | err)

    def _halo_gid(self, gid, send):
        name = self.decomposition.axis_name
        left, right = self._perms()
        C = gid.shape[0]
        out = []
        for face, perm in ((0, left), (1, right)):
            idx = send[face]
            g = jnp.where(idx < C, gid[jnp.minimum(idx, C - 1)], -1)
            out.append(lax.ppermute(g, name, perm))
        return jnp.concatenate(out)

    def _stale(self, R, gid, nbrs):
        ref = nbrs.reference_position[:R.shape[0]]
        d = jax.vmap(self.displacement)(R, ref)
        moved = jnp.sum(d * d, axis=-1)
        return jnp.any((gid >= 0) & (moved > (self.skin / 2) ** 2))

    def _update_local(self, s: DomainState) -> DomainState:
        """Unstacked state: rebuild iff some particle anywhere moved more
        than skin / 2 since the last rebuild."""
        name = self.decomposition.axis_name
        stale = lax.pmax(self._stale(s.position, s.gid, s.nbrs)
                         .astype(jnp.int32), name) > 0

        def rebuild(s):
            return DomainState(*self._rebuild_local(
                s.position, s.velocity, s.accel, s.gid, s.send, s.nbrs,
                s.rebuilds, s.error))
        s = lax.cond(stale, rebuild, lambda s: s, s)
        # NaN moves nobody past the skin (comparisons are false), so the
        # rebuild's own check may never run: look at every update.
        bad = ~jnp.all(jnp.isfinite(
            jnp.where((s.gid >= 0)[:, None], s.position, 0)))
        return s._replace(error=s.error | jnp.where(
            bad, int(Overflow.NONFINITE), 0).astype(s.error.dtype))

    def _per_device(self, fn, state: DomainState):
        spec = self._spec()

        def body(*leaves):
            s = _unstack(DomainState(*leaves))
            return _stack(fn(s))
        f = shard_map(body, mesh=self.mesh, in_specs=(spec,) * 10,
                      out_specs=spec)
        return f(*state)

    @functools.cached_property
    def _jit_local_positions(self):
        """(R, gid, send) -> owned + halo positions of freshly chosen
        halos, per device."""
        def body(R, gid, send):
            me = lax.axis_index(self.decomposition.axis_name)
            s, sh, _ = self._select_halo(R[0], gid[0], me, send.shape[2])
            return self._local_positions(R[0], gid[0], s, sh)[None]
        return jax.jit(self._smap(body, 3, 1))

    @functools.cached_property
    def _jit_rebuild(self):
        return jax.jit(lambda s: self._per_device(self._rebuild_fn, s))

    def _rebuild_fn(self, s):
        return DomainState(*self._rebuild_local(
            s.position, s.velocity, s.accel, s.gid, s.send, s.nbrs,
            s.rebuilds, s.error))

    def update(self, state: DomainState) -> DomainState:
        """After moving ``state.position``: migrate, choose halos and
        rebuild the lists if some particle moved more than skin / 2 since
        the last rebuild (decided over all devices)."""
        return self._per_device(self._update_local, state)

    def rebuild(self, state: DomainState) -> DomainState:
        """Migrate, choose halos and rebuild the lists now (jitted)."""
        return self._jit_rebuild(state)

    def verlet_step(self, state: DomainState, dt: float, mass=1.0,
                    energy: bool = True):
        """One velocity Verlet step (kick, drift, update, forces, kick), as
        `jaxrt.sim`'s; returns ``(state, (kinetic, potential, momentum))``,
        totals over all devices. ``mass``: a scalar. ``energy=False``:
        with ``row_energy``, skip the per-particle energy pass (the
        potential is then reported as 0)."""
        name = self.decomposition.axis_name
        wrap_axes = [a for a, p in enumerate(self.periodic)
                     if p and a != self.axis]

        def fn(s: DomainState):
            valid = (s.gid >= 0)[:, None]
            v_half = s.velocity + 0.5 * dt * s.accel
            R = s.position + jnp.where(valid, dt * v_half, 0)
            for a in wrap_axes:
                L = jnp.asarray(float(self.box_size[a]), R.dtype)
                R = R.at[:, a].set(jnp.where(valid[:, 0], jnp.mod(R[:, a], L),
                                             R[:, a]))
            s = self._update_local(s._replace(position=R, velocity=v_half))
            u, f = self._forces_local(s.position, s.gid, s.send, s.shift,
                                      s.nbrs, energy)
            a = f / mass
            if self.accel is not None:
                a = a + self._other_accel(s.position, s.velocity, s.gid,
                                          s.send, s.shift, s.nbrs)
            v = s.velocity + 0.5 * dt * a
            valid = (s.gid >= 0)[:, None]
            ke = 0.5 * mass * jnp.sum(jnp.where(valid, v * v, 0))
            mom = mass * jnp.sum(jnp.where(valid, v, 0), axis=0)
            s = s._replace(velocity=v, accel=a)
            rec = lax.psum((ke, u, mom), name)
            return s, rec

        spec = self._spec()

        def body(*leaves):
            s, rec = fn(_unstack(DomainState(*leaves)))
            return _stack(s), _stack(rec)
        f = shard_map(body, mesh=self.mesh, in_specs=(spec,) * 10,
                      out_specs=(spec, spec))
        new, rec = f(*state)
        return new, jax.tree_util.tree_map(lambda x: x[0], rec)

    def forces_into(self, state: DomainState, mass=1.0) -> DomainState:
        """``state`` with ``accel`` = forces / mass, plus the accelerations
        not from the potential (as after a step)."""
        _, f = self.energy_and_forces(state)
        a = f / mass
        if self.accel is not None:
            def body(R, V, gid, send, shift, nbrs):
                return self._other_accel(R[0], V[0], gid[0], send[0],
                                         shift[0], _unstack(nbrs))[None]
            a = a + self._smap(body, 6, 1)(
                state.position, state.velocity, state.gid, state.send,
                state.shift, state.nbrs)
        return state._replace(accel=a)

    # -- host side ------------------------------------------------------------
    def _sharding(self):
        return NamedSharding(self.mesh, self._spec())

    def _put(self, tree):
        sh = self._sharding()
        return jax.tree_util.tree_map(lambda x: jax.device_put(x, sh), tree)

    def distribute(self, R, V=None, *, dtype=None) -> DomainState:
        """Place particles ``R`` (float ``(N, dim)``, velocities ``V``) on
        the devices: owners, padding, halos, lists. Eager (host); sizes
        the capacities the decomposition leaves None."""
        R = np.asarray(R, np.float64)
        n, dim = R.shape
        if dim != len(self.box_size):
            raise DomainError(f"R has dim {dim} but box_size has "
                              f"{len(self.box_size)} entries.")
        dtype = jnp.dtype(dtype or jnp.asarray(R[:1]).dtype)
        V = np.zeros_like(R) if V is None else np.asarray(V, np.float64)
        dec, ax, nd = self.decomposition, self.axis, self.devices
        Rw = R.copy()
        for a, p in enumerate(self.periodic):
            if p:
                Rw[:, a] = np.mod(Rw[:, a], self.box_size[a])
        owner = np.clip(np.floor(Rw[:, ax] / self.width).astype(int), 0,
                        nd - 1)
        counts = np.bincount(owner, minlength=nd)
        x = Rw[:, ax] - owner * self.width
        w = self.halo_width
        faces = np.concatenate([np.bincount(owner[x < w], minlength=nd),
                                np.bincount(owner[self.width - x < w],
                                            minlength=nd)])
        C = dec.capacity or int(math.ceil(dec.slack * counts.max())) + 16
        H = dec.halo_capacity or int(math.ceil(dec.slack * faces.max())) + 16
        if counts.max() > C:
            d = int(np.argmax(counts))
            raise DomainError(
                f"device {d} owns {counts[d]} particles but "
                f"Decomposition.capacity = {C}; raise it (or leave it None).")
        if faces.max() > H:
            raise DomainError(
                f"a face has {faces.max()} halo particles but "
                f"Decomposition.halo_capacity = {H}; raise it (or leave it "
                "None).")
        pos = np.stack([np.asarray(self._parking(C, np.float64,
                                                 d * self.width))
                        for d in range(nd)])
        vel = np.zeros((nd, C, dim))
        gid = -np.ones((nd, C), np.int32)
        for d in range(nd):
            ids = np.flatnonzero(owner == d)
            pos[d, :len(ids)] = Rw[ids]
            vel[d, :len(ids)] = V[ids]
            gid[d, :len(ids)] = ids
        pos = jnp.asarray(pos, dtype)
        vel = jnp.asarray(vel, dtype)
        send = np.full((nd, 2, H), C, np.int32)
        shift = np.zeros((nd, 2))
        # A list sized on every device's local set (host, eager), then
        # stacked; the rebuild below fills each device's own.
        zeros = self._put((pos, vel, jnp.zeros_like(pos), jnp.asarray(gid),
                           jnp.asarray(send), jnp.asarray(shift, dtype)))
        pos_d, vel_d, acc_d, gid_d, send_d, shift_d = zeros

        Rloc = self._jit_local_positions(pos_d, gid_d, send_d)
        Rloc = np.asarray(Rloc)
        # Sized on the device with the most particles (owned + halo); the
        # capacity multiplier covers the others' fuller rows (an overflow
        # is flagged, and run_chunk distributes again).
        real = [np.sum(r[:, ax] < (d + 1) * self.width + 2 * w)
                for d, r in enumerate(Rloc)]  # parked sites lie beyond
        fullest = int(np.argmax(real))
        best = self.neighbor_fn.allocate(jnp.asarray(Rloc[fullest], dtype))
        nbrs = jax.tree_util.tree_map(
            lambda a: jnp.broadcast_to(a, (nd,) + a.shape), best)
        state = DomainState(
            pos_d, vel_d, acc_d, gid_d, send_d, shift_d,
            self._put(jnp.full((nd, 2 * H), -1, jnp.int32)),
            self._put(nbrs), self._put(jnp.zeros((nd,), jnp.int32)),
            self._put(jnp.zeros((nd,), jnp.int32)))
        state = self.rebuild(state)
        object.__setattr__(self, "n", n)
        return state._replace(rebuilds=state.rebuilds * 0)

    def errors(self, state: DomainState) -> Overflow:
        return Overflow.of(state.error)

    def check(self, state: DomainState) -> None:
        """Raise `DomainError` naming each overflow (and its fix):
        `DomainState.check`."""
        state.check()

    def gather(self, state: DomainState, what: str = "position",
               n: int | None = None) -> np.ndarray:
        """``state.<what>`` of every particle, float64 ``(N, dim)``, in the
        global order of `distribute` (positions wrapped into the box)."""
        n = n or self.n
        vals = np.asarray(getattr(state, what), np.float64)
        gid = np.asarray(state.gid)
        out = np.full((n, vals.shape[-1]), np.nan)
        ok = gid >= 0
        if np.bincount(gid[ok], minlength=n).max(initial=0) > 1:
            raise DomainError("a particle is owned twice (a bug).")
        out[gid[ok]] = vals[ok]
        if np.isnan(out).any():
            raise DomainError(f"{int(np.isnan(out[:, 0]).sum())} particles "
                              "are owned by no device (an overflow lost "
                              "them: see check).")
        if what == "position":
            for a, p in enumerate(self.periodic):
                if p:
                    out[:, a] = np.mod(out[:, a], self.box_size[a])
        return out

    def pairs(self, state: DomainState, within: float | None = None
              ) -> np.ndarray:
        """Sorted unique global ``i * N + j`` (i < j) of the devices'
        lists; ``within``: only pairs closer than it (by the positions of
        the last rebuild, each device's frame)."""
        n = self.n
        idx = np.asarray(state.nbrs.idx)
        gid = np.asarray(state.gid)
        hg = np.asarray(state.halo_gid)
        ref = np.asarray(state.nbrs.reference_position, np.float64)
        codes = []
        for d in range(idx.shape[0]):
            lg = np.concatenate([gid[d], hg[d], [-1]])
            C = gid.shape[1]
            i = np.repeat(np.arange(idx[d].shape[0]), idx[d].shape[1])
            j = idx[d].ravel()
            keep = (i < C) & (j < len(lg) - 1)
            i, j = i[keep], j[keep]
            if within is not None:
                dr = np.asarray(jax.vmap(self.displacement)(
                    jnp.asarray(ref[d][i]), jnp.asarray(ref[d][j])))
                keep = np.sum(dr * dr, -1) < within ** 2
                i, j = i[keep], j[keep]
            gi, gj = lg[i], lg[j]
            keep = (gi >= 0) & (gj >= 0) & (gi != gj)
            gi, gj = gi[keep].astype(np.int64), gj[keep].astype(np.int64)
            codes.append(np.minimum(gi, gj) * n + np.maximum(gi, gj))
        return np.unique(np.concatenate(codes))


def decompose(*, box_size, periodic, cutoff: float, skin: float,
              energy: Callable | None, decomposition: Decomposition,
              backend="auto", capacity_multiplier: float = 1.25,
              one_body: Callable | None = None,
              density: Callable | None = None,
              accel: Callable | None = None,
              row_energy: Callable | None = None, devices=None) -> Domains:
    """The functions of a slab decomposition (`Domains`).

    box_size: float ``(dim,)`` sides; periodic: bool or one per axis.
    cutoff, skin: the list's (halo width ``cutoff + skin``). energy: a
    factory ``energy(displacement) -> e(R, nbrs) -> (n,)``, per-particle
    energies (each pair half and half), e.g.
    ``lambda d: jaxrt.energy.lennard_jones_pair_neighbor_list(d, ...,
    per_particle=True)``. backend: any `jaxrt.neighbor_list` backend.
    one_body: optional ``u(R, valid) -> ()``, an external energy of the
    owned particles (``valid``: bool ``(C,)``). density, accel: optional
    factories of forces not from a potential (SPH), each given the
    displacement: ``density(d) -> rho(R, nbrs) -> (n,)`` and ``accel(d)
    -> a(R, V, nbrs, rho) -> (n, dim)``; the halo's densities and
    velocities come from their owners before ``accel``. row_energy:
    optional, the same pair energy as a total on a Dense list whose
    gradient for particle k is summed over row k alone (jaxrt's
    ``gradient="rows"``, e.g. ``lennard_jones_pair_neighbor_list(d, ...)``
    without per_particle): the steps then take the owned particles'
    forces from their own rows, with no reverse halo exchange and no
    scatter (`Domains.energy` is still differentiated through the halo).
    devices: the JAX devices
    (default ``jax.devices()[:decomposition.devices]``).

    Raises `DomainError` if the halo is wider than a slab, the split axis
    has no positive side, or there are fewer devices than asked for.
    """
    dec = decomposition
    box = np.asarray(box_size, float).ravel()
    dim = box.size
    if isinstance(periodic, (bool, np.bool_)):
        periodic = (bool(periodic),) * dim
    periodic = tuple(bool(p) for p in periodic)
    if len(periodic) != dim:
        raise DomainError(f"periodic needs {dim} entries (one per axis).")
    if not 0 <= dec.axis < dim:
        raise DomainError(f"Decomposition.axis = {dec.axis} but the box has "
                          f"{dim} axes.")
    L = box[dec.axis]
    if not (math.isfinite(L) and L > 0):
        raise DomainError(f"the split axis {dec.axis} needs a positive box "
                          f"side; got {L}.")
    width = L / dec.devices
    w = float(cutoff) + float(skin)
    if dec.devices > 1 and w > width:
        most = max(1, int(L // w))
        raise DomainError(
            f"halo wider than a domain: cutoff + skin = {w:.4g} but each of "
            f"Decomposition(devices={dec.devices}) slabs along axis "
            f"{dec.axis} is {L:.4g} / {dec.devices} = {width:.4g} wide; use "
            f"devices <= {most} along this axis, a larger box, or a shorter "
            "cutoff or skin.")
    devs = list(jax.devices() if devices is None else devices)
    if len(devs) < dec.devices:
        raise DomainError(
            f"Decomposition(devices={dec.devices}) needs {dec.devices} JAX "
            f"devices, found {len(devs)} ({devs[0].platform}). On a CPU set "
            f"XLA_FLAGS=--xla_force_host_platform_device_count="
            f"{dec.devices} before JAX starts.")
    mesh = Mesh(np.asarray(devs[:dec.devices]), (dec.axis_name,))
    disp = _local_displacement(periodic, box, dec.axis)
    local_periodic = tuple(p and a != dec.axis for a, p in
                           enumerate(periodic))
    nl = _neighbors.neighbor_list(
        disp, box, float(cutoff), float(skin),
        capacity_multiplier=capacity_multiplier, format=partition.Dense,
        backend=backend, periodic=local_periodic)
    if energy is None and accel is None and one_body is None:
        raise DomainError("give energy, accel or one_body: nothing to "
                          "compute.")
    return Domains(dec, mesh, box, periodic, float(cutoff), float(skin), nl,
                   None if energy is None else energy(disp), disp,
                   one_body=one_body,
                   density=None if density is None else density(disp),
                   accel=None if accel is None else accel(disp),
                   row_energy=None if row_energy is None else row_energy(disp))


# ---------------------------------------------------------------------------
# Runs: chunks of steps, redone on overflow


def chunk_fn(dom: Domains, dt: float, mass=1.0):
    """``chunk(state, steps) -> (state, (kinetic, potential, momentum))``:
    ``steps`` `Domains.verlet_step` in one jitted ``lax.scan``; records
    ``(steps,)`` (momentum ``(steps, dim)``)."""
    @functools.partial(jax.jit, static_argnames=("steps",))
    def chunk(state, steps: int):
        def body(s, _):
            return dom.verlet_step(s, dt, mass)
        return lax.scan(body, state, None, length=steps)
    return chunk


def run_chunk(dom: Domains, chunk, state: DomainState, steps: int,
              stats: dict | None = None):
    """Run ``steps`` steps; a chunk that overflowed anything is thrown away
    and redone from its start after `Domains.distribute` again (which
    reallocates the lists and resizes the capacities it sized). Raises
    `DomainError` if it overflows again. ``stats``: a dict whose
    ``"redone"`` counts the redone chunks."""
    new, rec = chunk(state, steps=steps)
    if dom.errors(new):
        if stats is not None:
            stats["redone"] = stats.get("redone", 0) + 1
        R, V, A = (dom.gather(state, k) for k in ("position", "velocity",
                                                  "accel"))
        dtype = state.position.dtype
        state = dom.distribute(R, V, dtype=dtype)
        gid = np.asarray(state.gid)
        acc = np.zeros(state.position.shape)
        acc[gid >= 0] = A[gid[gid >= 0]]
        state = state._replace(accel=dom._put(jnp.asarray(acc, dtype)))
        new, rec = chunk(state, steps=steps)
        dom.check(new)
    return new, rec


def from_scene(scene, devices: int, *, backend=None,
               capacity_multiplier: float | None = None) -> Domains:
    """`decompose` for a `jaxrt.sim.Scene`: slabs along x, the scene's
    cutoff, skin and backend (or ``backend``).

    Decomposed: LJ (scalar sigma / epsilon), SPH (sph_density,
    sph_pressure, sph_viscosity), one-body potentials (gravity, walls).
    Raises `DomainError` for what is not decomposed yet: other pair
    effects (boids), LJ with species or per-particle radii, unequal masses,
    the Langevin integrator.
    """
    from jaxrt.energy import lj as _lj
    from jaxrt.sim import effects as _effects
    from jaxrt.sim.spec import Context
    p = scene.particles
    if scene.integrator.kind != "verlet":
        raise DomainError("only the verlet integrator (NVE) is decomposed "
                          "so far.")
    if np.ptp(p.masses) > 0:
        raise DomainError("particles of unequal masses are not decomposed "
                          "yet.")
    mass = float(p.masses[0])
    dtype = jnp.dtype(scene.dtype)
    pair = scene.pair_effects
    sph_kinds = (_effects.SPHDensity, _effects.SPHPressure,
                 _effects.SPHViscosity)
    ljs = [e for e in pair if isinstance(e, _effects.LJ)]
    sph = [e for e in pair if isinstance(e, sph_kinds)]
    if not pair or len(ljs) + len(sph) < len(pair):
        raise DomainError(
            "decomposed runs take Lennard-Jones and SPH scenes (lj-fluid, "
            "dam-break, TOML scenes with lj or sph_* effects, plus gravity "
            f"/ walls); this scene's pair effects are "
            f"{[e.kind for e in pair]}.")
    energy = None
    if ljs:
        lj = ljs[0]
        if (p.species is not None or p.radius is not None
                or np.ndim(lj.sigma) or np.ndim(lj.epsilon)):
            raise DomainError("LJ with species or per-particle radii is not "
                              "decomposed yet.")
        r_onset = 0.8 * lj.r_cutoff if lj.r_onset is None else lj.r_onset

        def energy(disp, per_particle=True):
            return _lj.lennard_jones_pair_neighbor_list(
                disp, sigma=lj.sigma, epsilon=lj.epsilon, r_onset=r_onset,
                r_cutoff=lj.r_cutoff, truncation=lj.truncation,
                per_particle=per_particle)

        def row_energy(disp):
            return energy(disp, per_particle=False)

    else:
        row_energy = None
    density = accel = None
    if sph:
        def terms(disp):
            ctx = Context(scene, disp, dtype, mass)
            return [e.term(ctx) for e in sph]

        def density(disp):
            fns = [t.density for t in terms(disp) if t.density]
            return fns[0] if fns else None

        def accel(disp):
            fns = [t.accel for t in terms(disp) if t.accel]

            def a(R, V, nbrs, rho):
                out = fns[0](R, V, nbrs, rho)
                for f in fns[1:]:
                    out = out + f(R, V, nbrs, rho)
                return out
            return a

    one_body = None
    others = [e for e in scene.effects if not e.pairwise]
    if others:
        ctx = Context(scene, lambda a, b, **kw: a - b, dtype, mass)
        bodies = [e.term(ctx) for e in others]
        if any(t.energy is None or t.accel or t.density for t in bodies):
            raise DomainError("one-body effects must be potentials (gravity, "
                              "walls).")

        def one_body(R, valid):
            def each(r):
                return sum(t.energy(r[None], None) for t in bodies)
            return jnp.sum(jnp.where(valid, jax.vmap(each)(R), 0))
    nb = scene.neighbors
    size = np.asarray(scene.box.size, float)
    size = np.where(np.isfinite(size) & (size > 0), size, 1.0)
    return decompose(
        box_size=size, periodic=scene.box.periodic, cutoff=scene.cutoff,
        skin=nb.skin, energy=energy,
        decomposition=Decomposition(devices=devices),
        backend=backend or nb.backend,
        capacity_multiplier=capacity_multiplier or nb.capacity_multiplier,
        one_body=one_body, density=density, accel=accel,
        row_energy=row_energy)
