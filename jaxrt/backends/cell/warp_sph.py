"""Warp kernels of the list-free SPH sums on a cell grid: Warp only (no
JAX; `jaxrt.backends.rt.ffi.cell_sph_density` and
`jaxrt.backends.rt.ffi.cell_sph_forces` put them behind JAX calls).

They walk the grid that `jaxrt.backends.cell.warp_kernels.sort_cells`
built (bin, radix sort, cell table, gather: the Lennard-Jones engine's
steps 1 to 4), with its stencil (`warp_kernels.stencil_functions`): a
thread per sorted particle, every pair met from both of its particles, no
atomics, the sums written in the sorted order.

* `density_sums`: ``sum_{j != i} m_j W(|r_ij|)`` (the self term is the
  caller's).
* `step_sums`: a whole step in one pipeline: the sort, the density
  walk (with each particle's self term and Tait's equation of state),
  the force walk.
* `force_sums`: the symmetric pressure term ``-sum_j m_j (q_i + q_j)
  grad_i W_ij`` (``q = P / rho^2``) and Monaghan's viscosity ``-sum_j m_j
  Pi_ij grad_i W_ij``, with per-particle velocities, masses, densities,
  ``q`` and sound speeds in the sorted order.

The pair terms are `jaxrt.energy.sph`'s, written out: ``W(r) = norm_w
f(r / h)`` for ``r < support h`` (0 beyond), ``dW/dr = norm_w f'(r / h) /
h``; ``f`` and ``f'`` per kernel (`KINDS`), the normalisation
(``sigma_d / h^dim``) from the caller. Coincident pairs (``r = 0``) add
``m_j W(0)`` to the density and nothing to the forces (``f'(0) = 0``, and
the unit vector is 0 there, as `jaxrt.energy.sph`'s safe norm).
"""

import warp as wp

from jaxrt.backends.cell import warp_kernels

# The kernels' ``f`` (the shape of `jaxrt.energy.sph`'s kernels), by name.
KINDS = ("cubic_spline", "quintic_spline", "wendland_c2", "wendland_c4")

# ``params`` rows: the smoothing length, the support radius ``support h``,
# ``norm_w = sigma_d / h^dim``, then the viscosity's alpha, beta and
# epsilon (the forces only).
H, SUPPORT, NORM_W, ALPHA, BETA, EPSILON = range(6)
# `step_sums` only: the self term's ``W(0)``, then Tait's ``rho0``,
# ``c0``, ``gamma`` and ``B = rho0 c0^2 / gamma``.
W0, RHO0, C0, GAMMA, B = range(6, 11)
N_PARAMS = 11

# Fast math off: the pair terms cancel (pressures of ~10^3 summing to O(1))
# and the tests hold float32 to the list path's tolerances.
_OPTIONS = {"enable_backward": False, "max_unroll": 1, "fast_math": False}


def _shape_function(scalar, kind: str):
    """``f(q), f'(q)`` of kernel ``kind`` for ``scalar``: the clamped
    polynomials of `jaxrt.energy.sph`."""
    zero, one, two = scalar(0.0), scalar(1.0), scalar(2.0)

    if kind == "cubic_spline":
        @wp.func
        def shape(q: scalar):
            a = wp.max(two - q, zero)
            b = wp.max(one - q, zero)
            return (a * a * a / scalar(4.0) - b * b * b,
                    scalar(-0.75) * a * a + scalar(3.0) * b * b)
    elif kind == "quintic_spline":
        @wp.func
        def shape(q: scalar):
            a = wp.max(scalar(3.0) - q, zero)
            b = wp.max(two - q, zero)
            c = wp.max(one - q, zero)
            a4, b4, c4 = a * a * a * a, b * b * b * b, c * c * c * c
            return (a4 * a - scalar(6.0) * (b4 * b) + scalar(15.0) * (c4 * c),
                    scalar(-5.0) * a4 + scalar(30.0) * b4
                    - scalar(75.0) * c4)
    elif kind == "wendland_c2":
        @wp.func
        def shape(q: scalar):
            a = wp.max(one - q / two, zero)
            a3 = a * a * a
            return a3 * a * (two * q + one), scalar(-5.0) * q * a3
    elif kind == "wendland_c4":
        @wp.func
        def shape(q: scalar):
            a = wp.max(one - q / two, zero)
            a5 = a * a * a * a * a
            poly = scalar(35.0) * q * q / scalar(12.0) + scalar(3.0) * q + one
            return (a5 * a * poly,
                    a5 * (a * (scalar(35.0) * q / scalar(6.0) + scalar(3.0))
                          - scalar(3.0) * poly))
    else:
        raise ValueError(f"kernel {kind!r} has no Warp form; choose one of "
                         f"{KINDS}.")
    return shape


def _walks(scalar, kind: str):
    """``(density_walk, force_walk)`` for positions of ``scalar`` and the
    kernel ``kind``."""
    shape = _shape_function(scalar, kind)
    return _density_walk(scalar, shape), _force_walk(scalar, shape)


def _density_walk(scalar, shape):
    """The density walk for ``scalar`` positions and ``shape``
    (`_shape_function`)."""
    vector = wp.types.vector(3, scalar)
    span, difference = warp_kernels.stencil_functions(scalar)
    stencil, SIDE = warp_kernels.stencil, warp_kernels.SIDE

    @wp.kernel(module="unique", module_options=_OPTIONS)
    def density_walk(position: wp.array(dtype=vector),
                     keys: wp.array(dtype=wp.int32),
                     start: wp.array(dtype=wp.int32),
                     grid: wp.array(dtype=vector),
                     cells: wp.array(dtype=wp.int32),
                     params: wp.array(dtype=scalar), flags: int,
                     mass: wp.array(dtype=scalar), step: int,
                     values: wp.array(dtype=wp.int32),
                     velocity: wp.array(dtype=vector),
                     velocity_sorted: wp.array(dtype=vector),
                     rho: wp.array(dtype=scalar),
                     q: wp.array(dtype=scalar),
                     sound: wp.array(dtype=scalar),
                     density: wp.array(dtype=scalar)):
        i = wp.tid()
        side = grid[SIDE]
        h = params[H]
        # Per-pair divisions by h as products (a rounding apart).
        inv_h = scalar(1.0) / h
        support = params[SUPPORT]
        norm_w = params[NORM_W]
        support2 = support * support
        s = stencil(flags, cells, keys[i])
        p = position[i]
        total = scalar(0.0)
        for dz in range(-s.az, s.az + 1):
            for piece in range(s.pieces):
                first, end, shift = span(s, start, side, dz, piece)
                for j in range(first, end):
                    d, d2 = difference(p - shift, position[j], side, s)
                    if d2 < support2 and j != i:
                        r = wp.sqrt(d2)
                        # `jaxrt.energy.sph`'s cut, r < support h.
                        if r < support:
                            f, df = shape(r * inv_h)
                            total = total + mass[j] * (norm_w * f)
        if step == 0:
            rho[i] = total
        else:
            # A whole step (`step_sums`): this particle's self term,
            # `jaxrt.energy.sph.Tait`'s pressure and sound speed (their
            # expressions), its density in the caller's order and its
            # velocity in the sorted one, for the force walk.
            r = total + mass[i] * params[W0]
            rho[i] = r
            ratio = r / params[RHO0]
            gamma = params[GAMMA]
            pressure = params[B] * (wp.pow(ratio, gamma) - scalar(1.0))
            q[i] = pressure / (r * r)
            sound[i] = params[C0] * wp.pow(ratio, (gamma - scalar(1.0))
                                           / scalar(2.0))
            j = values[i]
            density[j] = r
            velocity_sorted[i] = velocity[j]

    return density_walk


def _force_walk(scalar, shape):
    """The force walk for ``scalar`` positions and ``shape``
    (`_shape_function`)."""
    vector = wp.types.vector(3, scalar)
    span, difference = warp_kernels.stencil_functions(scalar)
    stencil, SIDE = warp_kernels.stencil, warp_kernels.SIDE

    @wp.kernel(module="unique", module_options=_OPTIONS)
    def force_walk(position: wp.array(dtype=vector),
                   keys: wp.array(dtype=wp.int32),
                   start: wp.array(dtype=wp.int32),
                   grid: wp.array(dtype=vector),
                   cells: wp.array(dtype=wp.int32),
                   params: wp.array(dtype=scalar), flags: int,
                   velocity: wp.array(dtype=vector),
                   mass: wp.array(dtype=scalar),
                   rho: wp.array(dtype=scalar),
                   q: wp.array(dtype=scalar),
                   sound: wp.array(dtype=scalar),
                   values: wp.array(dtype=wp.int32), scatter: int,
                   pressure: wp.array(dtype=vector),
                   viscosity: wp.array(dtype=vector)):
        i = wp.tid()
        side = grid[SIDE]
        h = params[H]
        # Per-pair divisions by h as products (a rounding apart).
        inv_h = scalar(1.0) / h
        support = params[SUPPORT]
        norm_w = params[NORM_W]
        alpha, beta = params[ALPHA], params[BETA]
        soft = params[EPSILON] * h * h
        support2 = support * support
        s = stencil(flags, cells, keys[i])
        p = position[i]
        vi = velocity[i]
        qi_own = q[i]
        ci = sound[i]
        rhoi = rho[i]
        acc_p = vector()
        acc_v = vector()
        for dz in range(-s.az, s.az + 1):
            for piece in range(s.pieces):
                first, end, shift = span(s, start, side, dz, piece)
                for j in range(first, end):
                    d, d2 = difference(p - shift, position[j], side, s)
                    # Coincident pairs: no force (unit 0).
                    if d2 < support2 and d2 > scalar(0.0):
                        r = wp.sqrt(d2)
                        if r < support:
                            f, df = shape(r * inv_h)
                            dw = norm_w * (df * inv_h)
                            grad_w = (dw / r) * d
                            mj = mass[j]
                            acc_p = acc_p - (mj * (qi_own + q[j])) * grad_w
                            vr = wp.dot(vi - velocity[j], d)
                            if vr < scalar(0.0):
                                mu = h * vr / (r * r + soft)
                                c_mean = (ci + sound[j]) / scalar(2.0)
                                rho_mean = (rhoi + rho[j]) / scalar(2.0)
                                visc = (-alpha * c_mean * mu + beta * mu * mu
                                        ) / rho_mean
                                acc_v = acc_v - (mj * visc) * grad_w
        out = i
        if scatter != 0:
            out = values[i]
        pressure[out] = acc_p
        viscosity[out] = acc_v

    return force_walk


_WALKS: dict = {}
BLOCK = warp_kernels.WALK_BLOCK


def walks(scalar, kind: str):
    """``(density_walk, force_walk)`` for ``scalar`` positions and the
    kernel ``kind`` (one of `KINDS`), built (and compiled) on first use."""
    key = (scalar, kind)
    if key not in _WALKS:
        _WALKS[key] = _walks(scalar, kind)
    return _WALKS[key]


def density_sums(kind: str, position, keys, start, grid, cells, params,
                 flags: int, mass, rho) -> None:
    """Launch the density walk.

    Args:
      kind: one of `KINDS`.
      position: vec3 ``(N,)``, keys: int32 (``N`` at least), start, grid,
        cells: what `warp_kernels.sort_cells` built and read (sorted
        order); params: scalar ``(N_PARAMS,)``; flags: ``PERIODIC <<
        axis`` bits of `warp_kernels`.
      mass: scalar ``(N,)`` sorted; rho: scalar ``(N,)`` out, sorted, the
        pair sums without the self term.
    """
    n = position.shape[0]
    if n == 0:
        return
    walk = walks(warp_kernels.scalar_of(position.dtype), kind)[0]
    # The step's outputs are not written (step 0): any arrays of their
    # types.
    wp.launch(walk, dim=n, device=position.device, block_dim=BLOCK,
              inputs=[position, keys, start, grid, cells, params, flags,
                      mass, 0, keys, position, position, rho, rho, rho, rho])


def force_sums(kind: str, position, keys, start, grid, cells, params,
               flags: int, velocity, mass, rho, q, sound, pressure,
               viscosity) -> None:
    """Launch the force walk: as `density_sums`, with vec3 ``velocity``
    and scalar ``mass``, ``rho``, ``q`` (``P / rho^2``), ``sound`` (sound
    speeds), all ``(N,)`` sorted; vec3 ``pressure`` and ``viscosity``
    ``(N,)`` out, sorted."""
    n = position.shape[0]
    if n == 0:
        return
    walk = walks(warp_kernels.scalar_of(position.dtype), kind)[1]
    wp.launch(walk, dim=n, device=position.device, block_dim=BLOCK,
              inputs=[position, keys, start, grid, cells, params, flags,
                      velocity, mass, rho, q, sound, keys, 0, pressure,
                      viscosity])


def step_sums(kind: str, points, velocity, mass, grid, cells, params,
              flags: int, *, keys, values, wrapped, start, position,
              mass_sorted, velocity_sorted, rho, q, sound, pressure,
              viscosity, density) -> None:
    """A whole SPH step's sums in one pipeline: `warp_kernels.sort_cells`
    (the masses gathered as its radii), the density walk (each particle
    then adds its self term, evaluates Tait's equation of state and
    gathers its velocity), the force walk.

    Args:
      kind: one of `KINDS`.
      points, velocity: vec3 ``(N,)``; mass: scalar ``(N,)``; the
        caller's order.
      grid, cells, flags: as `warp_kernels.sort_cells`' (``HAS_RADII``
        is set here); params: scalar ``(N_PARAMS,)``, every row.
      keys, values, wrapped, start, position: `warp_kernels.sort_cells`'
        scratch; mass_sorted, rho, q, sound: scalar ``(N,)`` scratch,
        velocity_sorted vec3 ``(N,)`` scratch.
      pressure, viscosity: vec3 ``(N,)`` out, density: scalar ``(N,)``
        out, the caller's order.
    """
    n = points.shape[0]
    if n == 0:
        return
    device = points.device
    warp_kernels.sort_cells(points, mass, grid, cells,
                            flags | warp_kernels.HAS_RADII, keys=keys,
                            values=values, wrapped=wrapped, start=start,
                            position=position, radius=mass_sorted)
    density_walk, force_walk = walks(warp_kernels.scalar_of(points.dtype),
                                     kind)
    wp.launch(density_walk, dim=n, device=device, block_dim=BLOCK,
              inputs=[position, keys, start, grid, cells, params, flags,
                      mass_sorted, 1, values, velocity, velocity_sorted, rho,
                      q, sound, density])
    wp.launch(force_walk, dim=n, device=device, block_dim=BLOCK,
              inputs=[position, keys, start, grid, cells, params, flags,
                      velocity_sorted, mass_sorted, rho, q, sound, values, 1,
                      pressure, viscosity])
