"""What `jaxrt run` and `jaxrt demo` write: snapshots, an XYZ trajectory
that ASE and OVITO read, and the figures (energies, final state,
Delaunay triangulation) with their axes in the scene's units."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

# trajectory.xyz names species 0, 1, 2, ... by these elements (ASE and OVITO
# need real symbols; "X0" is a KeyError in ase.io.read): noble gases first,
# the classic LJ atoms, then the rest of the periodic table by Z. The file's
# comment line states the map (species_map="0:Ar 1:Ne").
_BY_Z = """H He Li Be B C N O F Ne Na Mg Al Si P S Cl Ar K Ca Sc Ti V Cr Mn Fe
Co Ni Cu Zn Ga Ge As Se Br Kr Rb Sr Y Zr Nb Mo Tc Ru Rh Pd Ag Cd In Sn Sb Te I
Xe Cs Ba La Ce Pr Nd Pm Sm Eu Gd Tb Dy Ho Er Tm Yb Lu Hf Ta W Re Os Ir Pt Au Hg
Tl Pb Bi Po At Rn Fr Ra Ac Th Pa U Np Pu Am Cm Bk Cf Es Fm Md No Lr Rf Db Sg Bh
Hs Mt Ds Rg Cn Nh Fl Mc Lv Ts Og""".split()
_NOBLE = ("Ar", "Ne", "Kr", "Xe", "He", "Rn")
XYZ_ELEMENTS = _NOBLE + tuple(e for e in _BY_Z if e not in _NOBLE)


def write_outputs(scene, out, state, frames, velocities, frame_steps, ke,
                   u) -> None:
    """snapshots.npz, trajectory.xyz, energies.png, final.png in ``out``.

    frames, velocities: float ``(F, N, dim)`` per snapshot; frame_steps:
    ``F`` step numbers; ke, u: float ``(steps,)`` energies.
    """
    p = scene.particles
    # velocity: the final one (kept for old readers); velocities: per frame.
    np.savez(out / "snapshots.npz", positions=frames, velocities=velocities,
             steps=np.asarray(frame_steps),
             velocity=np.asarray(state.velocity), masses=p.masses,
             box=np.asarray(scene.box.size))
    write_xyz(out / "trajectory.xyz", scene, frames, velocities, frame_steps)

    # Figures made without pyplot: nothing to close, no GUI backend.
    energy_figure(scene, ke, u).savefig(out / "energies.png", dpi=100,
                                        bbox_inches="tight")
    final_figure(scene, frames[-1], np.asarray(state.velocity),
                 frame_steps[-1]).savefig(out / "final.png", dpi=100,
                                          bbox_inches="tight")


@dataclasses.dataclass(frozen=True)
class Units:
    """Unit names for the plots' labels: ``length``, ``time``, ``energy``,
    ``speed``, and ``system``, what they are (for the title)."""

    length: str
    time: str
    energy: str
    speed: str
    system: str


def units(scene) -> Units:
    """The units a scene's numbers are in, as far as it tells: reduced LJ
    units (σ, ε, τ = σ √(m/ε)) where an LJ effect has σ = ε = 1 and every
    mass is 1; SI for the built-in dam break (its tank is given in metres
    and its gravity as 9.81 m/s², in 2D energies per metre of depth);
    otherwise the scene file's own, unnamed."""
    p = scene.particles
    lj = [e for e in scene.effects if getattr(e, "kind", None) == "lj"]
    if lj and all(np.all(np.asarray(e.sigma, float) == 1.0)
                  and np.all(np.asarray(e.epsilon, float) == 1.0)
                  for e in lj) and np.all(p.masses == 1.0):
        return Units("σ", "τ", "ε", "σ/τ", "reduced LJ units")
    if scene.name == "dam-break":
        energy = "J/m" if p.dim == 2 else "J"
        return Units("m", "s", energy, "m/s", "SI units")
    return Units("scene units", "scene units", "scene units", "scene units",
                 "the scene's units")


def energy_figure(scene, ke, u):
    """The run's energies against time: kinetic, and where there is one,
    potential and total (each summed over the particles), with the step on
    the top axis. ke, u: float ``(steps,)``, after each step. Returns a
    matplotlib Figure."""
    from matplotlib.figure import Figure

    un = units(scene)
    dt = scene.integrator.dt
    steps = np.arange(1, len(ke) + 1)
    t = steps * dt
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    ax.plot(t, ke, label="kinetic")
    if np.any(u):
        ax.plot(t, u, label="potential")
        ax.plot(t, ke + u, label="total", color="k")
    ax.set_xlabel(f"time t ({un.time}); dt = {_amount(dt, un.time)}")
    ax.set_ylabel(f"energy ({un.energy}), sum over "
                  f"{scene.particles.n} particles")
    top = ax.secondary_xaxis("top", functions=(lambda x: x / dt,
                                               lambda k: k * dt))
    top.set_xlabel("step")
    ax.set_title(f"{scene.name}: energies ({un.system})", pad=10)
    ax.legend()
    return fig


def final_figure(scene, position, velocity, step: int):
    """The particles at the end of the run seen along z (3D: projected on
    x-y; 1D: on the x axis), coloured by speed |v|, inside the box's
    finite sides. position, velocity: float ``(N, dim)``; step: the step
    they are at. Returns a matplotlib Figure."""
    from matplotlib.figure import Figure

    un = units(scene)
    pos = np.asarray(position, float)
    dim = pos.shape[1]
    speed = np.linalg.norm(np.asarray(velocity, float), axis=1)
    fig = Figure(figsize=(6.8, 6))
    ax = fig.subplots()
    y = pos[:, 1] if dim > 1 else np.zeros(len(pos))
    dots = ax.scatter(pos[:, 0], y, c=speed, s=4, cmap="viridis")
    fig.colorbar(dots, ax=ax, shrink=0.8,
                 label=f"speed |v| ({un.speed})")
    ax.set_xlabel(f"x ({un.length})")
    ax.set_ylabel(f"y ({un.length})" if dim > 1 else "(1D: no y axis)")
    size = np.asarray(scene.box.size, float)
    for axis, set_lim in zip(range(min(dim, 2)), (ax.set_xlim, ax.set_ylim)):
        if np.isfinite(size[axis]) and size[axis] > 0:
            set_lim(0, size[axis])
    ax.set_aspect("equal")
    view = {3: ", seen along z", 1: ", on the x axis"}.get(dim, "")
    t = step * scene.integrator.dt
    ax.set_title(f"{scene.name}: step {step}, t = {_amount(t, un.time)}"
                 f"{view}")
    return fig


def _amount(value: float, unit: str) -> str:
    """``value`` and its unit (the number alone in the scene's unnamed
    units)."""
    return f"{value:.4g}" if unit == "scene units" else f"{value:.4g} {unit}"


def triangulation_stats(nbrs) -> dict | None:
    """`jaxrt.backends.delaunay.stats` of a Delaunay list, else None."""
    from jaxrt.backends import delaunay
    if not isinstance(getattr(nbrs, "backend_state", None),
                      delaunay.Triangulation):
        return None
    return delaunay.stats(nbrs)


def write_triangulation(path, scene, state, nbrs) -> None:
    """The flock and its triangulation (the list's, at its last rebuild):
    boids as arrows coloured by speed, the Delaunay edges in grey (edges
    that wrap around a periodic box are left out of the picture)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    tri_state = nbrs.backend_state
    pos = np.asarray(tri_state.position)
    tri = np.asarray(tri_state.tri)
    shift = np.asarray(tri_state.shift)
    n = scene.particles.n
    e = np.arange(3)
    a, b = tri[:, e].ravel(), tri[:, (e + 1) % 3].ravel()
    same = np.all(shift[:, e] == shift[:, (e + 1) % 3], axis=-1).ravel()
    keep = same & (a < n) & (b < n) & (a < b)
    segments = np.stack([pos[a[keep]], pos[b[keep]]], axis=1)
    R = np.asarray(state.position)
    V = np.asarray(state.velocity)
    fig, ax = plt.subplots(figsize=(8, 8))
    ax.add_collection(LineCollection(segments, colors="0.75",
                                     linewidths=0.3))
    arrows = ax.quiver(R[:, 0], R[:, 1], V[:, 0], V[:, 1],
                       np.linalg.norm(V, axis=1), cmap="viridis", scale=30,
                       width=0.003)
    un = units(scene)
    fig.colorbar(arrows, ax=ax, shrink=0.8, label=f"speed |v| ({un.speed})")
    size = np.asarray(scene.box.size, float)
    ax.set_xlim(0, size[0])
    ax.set_ylim(0, size[1])
    ax.set_xlabel(f"x ({un.length})")
    ax.set_ylabel(f"y ({un.length})")
    ax.set_aspect("equal")
    ax.set_title(f"{scene.name}: {n} boids and their Delaunay triangulation")
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def xyz_symbols(p) -> tuple[np.ndarray, str]:
    """Element symbols ``(N,)`` of particles ``p`` and the comment line's
    map ``"0:Ar 1:Ne"`` (species present only). Raises past 118 species."""
    species = np.zeros(p.n, int) if p.species is None else p.species
    if species.max() >= len(XYZ_ELEMENTS):
        raise ValueError(
            f"particles.species goes up to {species.max()} but trajectory.xyz "
            f"can name {len(XYZ_ELEMENTS)} species (0 to "
            f"{len(XYZ_ELEMENTS) - 1}) as elements; renumber the species.")
    return (np.asarray(XYZ_ELEMENTS)[species],
            " ".join(f"{s}:{XYZ_ELEMENTS[s]}" for s in np.unique(species)))


def write_xyz(path, scene, frames, velocities, frame_steps) -> None:
    """Extended XYZ that ase.io.read and OVITO read, one frame per snapshot.

    frames, velocities: float ``(F, N, dim)``; frame_steps: ``F`` ints.
    Columns ``species:S:1:pos:R:3:velocities:R:3`` (axes beyond ``dim``
    written as 0); species as elements (`XYZ_ELEMENTS`, map in
    ``species_map=``); ``Lattice=`` the diagonal box (a zero vector on an
    axis without a positive side, and no Lattice at all when no axis has
    one); ``pbc=`` per axis. Floats round-trip: 9 significant digits for
    float32 runs, 17 for float64.
    """
    p = scene.particles
    dim = p.dim
    symbols, species_map = xyz_symbols(p)
    size = [s if math.isfinite(s) and s > 0 else 0.0
            for s in scene.box.size] + [0.0] * (3 - dim)
    header = ""
    if any(size):
        # repr: the shortest text that reads back as the same float64.
        header = 'Lattice="' + " ".join(
            repr(float(size[i]) if i == j else 0.0)
            for i in range(3) for j in range(3)) + '" '
    pbc = " ".join("T" if b == "periodic" else "F"
                   for b in list(scene.box.boundary) + ["free"] * (3 - dim))
    header += (f'Properties=species:S:1:pos:R:3:velocities:R:3 pbc="{pbc}" '
               f'species_map="{species_map}"')
    digits = 9 if frames.dtype == np.float32 else 17
    with open(path, "w") as f:
        for pos, vel, step in zip(frames, velocities, frame_steps):
            f.write(f"{p.n}\n{header} step={step}\n")
            cols = np.zeros((p.n, 6))
            cols[:, :dim], cols[:, 3:3 + dim] = pos, vel
            for s, row in zip(symbols, cols):
                f.write(s + "".join(f" {x:.{digits}g}" for x in row) + "\n")

