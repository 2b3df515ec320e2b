"""The ``jaxrt`` command.

    jaxrt demo [--steps 2000] [--n 2048] [--backend auto] [--out jaxrt-out]
        LJ fluid NVE; checks jaxrt's list against jax-md's every chunk.
        The same as ``jaxrt run lj-fluid --compare-jax-md``.
    jaxrt run SCENE.toml|NAME [--steps N] [--out DIR] [--chunk K]
              [--backend B] [--n N] [--compare-jax-md]
              [--dtype float32|float64] [--devices D] [--save-pairs]
        --devices D: slabs along x over D devices (`jaxrt.sim.domains`; on a
        CPU, D fake devices are made); LJ and SPH scenes.
    jaxrt scenes            the built-in scenes: name, default steps and
                            what each is, one line each
    jaxrt accuracy [lj-fluid|lj-fluid-2d|dam-break] --out DIR [--quick]
                   [--budget S] [--knobs a,b] [--n N] [--steps N]
        what accuracy costs in time: every knob against a float64
        reference (CSV, one PNG per knob, summary.md; jaxrt.tools.accuracy)

Arguments and scene files are checked before JAX, jax-md and Warp are
imported (they take seconds to load): a typo is reported at once.
"""
from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys
import time
import warnings

import numpy as np

from jaxrt.layouts.codes import pair_codes as _pair_codes
from jaxrt.tools import outputs

DEMO_STEPS, DEMO_N = 2000, 2048
TOML_STEPS = 1000
"""Steps of a scene read from a TOML file when --steps is not given."""

EXAMPLE_SCENE = """\
name = "two-atoms"

[box]
size = [10.0, 10.0, 10.0]
boundary = "periodic"            # per axis: "periodic", "wall" or "free"

[particles]
positions = [[1.0, 1.0, 1.0], [2.2, 1.0, 1.0]]
temperature = 1.0                # or velocities = [[vx, vy, vz], ...]

[[effects]]
kind = "lj"
r_cutoff = 2.5

[integrator]
dt = 0.005
"""
"""A minimal scene file (`run`'s help shows it)."""



def _builtin_lines() -> list[str]:
    """``name  steps  summary`` of each built-in scene (no JAX needed)."""
    from jaxrt.sim.builtin import BUILTIN
    return [f"{name:16s} {steps:5d} steps  "
            f"{factory.__doc__.strip().splitlines()[0]}"
            for name, (factory, steps) in BUILTIN.items()]


def _run_epilog() -> str:
    builtin = "\n".join("  " + line for line in _builtin_lines())
    example = "\n".join(("  " + line).rstrip()
                        for line in EXAMPLE_SCENE.splitlines())
    return (f"built-in scenes (also `jaxrt scenes`):\n{builtin}\n\n"
            "a scene file (TOML), the smallest:\n\n"
            f"{example}\n\n"
            "every table, key and effect, with defaults: `python -m pydoc "
            "jaxrt.sim.toml`.\nOutputs in --out: energies.png, final.png, "
            "snapshots.npz, trajectory.xyz.")


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="jaxrt", description="Run simulations on jaxrt's neighbour "
        "lists; `jaxrt COMMAND --help` for each command.")
    sub = ap.add_subparsers(dest="command", required=True)
    sub.add_parser("scenes", help="list the built-in scenes (for jaxrt "
                   "run NAME): name, default steps, what each is")
    acc = sub.add_parser("accuracy", help="sweep the knobs that trade "
                         "accuracy for time against a float64 reference")
    acc.add_argument("scene", nargs="?", default="lj-fluid",
                     choices=("lj-fluid", "lj-fluid-2d", "dam-break"))
    acc.add_argument("--out", default="jaxrt-accuracy",
                     help="folder for the CSV, PNGs and summary.md "
                     "(default: %(default)s)")
    acc.add_argument("--quick", action="store_true",
                     help="small N, short runs, a subset of values (a CPU "
                     "in a few minutes)")
    acc.add_argument("--budget", type=float, default=None,
                     help="seconds; no new setting starts after them (the "
                     "rest are written as skipped)")
    acc.add_argument("--knobs", default=None,
                     help="comma-separated knob names (default: all that "
                     "apply; see jaxrt.tools.accuracy.KNOBS)")
    acc.add_argument("--n", type=int, default=None,
                     help="particles (lj-fluid, lj-fluid-2d)")
    acc.add_argument("--steps", type=int, default=None,
                     help="steps per run")
    for name in ("run", "demo"):
        if name == "run":
            p = sub.add_parser(
                name, help="run a scene: a TOML file or a built-in name",
                description="Run a scene: a TOML file or a built-in name.",
                epilog=_run_epilog(),
                formatter_class=argparse.RawDescriptionHelpFormatter)
            p.add_argument("scene", help="a .toml file or a built-in name "
                           "(listed below)")
            p.add_argument("--compare-jax-md", action="store_true",
                           help="check jaxrt's list equals jax-md's at every "
                           "chunk and time both rebuilds")
            p.add_argument("--check-brute", action="store_true",
                           help="check the list against a float64 brute "
                           "force at every chunk (on by default for boids)")
            p.add_argument("--dtype", choices=("float32", "float64"),
                           default=None, help="the run's float type "
                           "(default: the scene's)")
            p.add_argument("--devices", type=int, default=None,
                           help="domain decomposition: slabs along x over "
                           "this many devices (jaxrt.sim.domains); on a CPU "
                           "that many fake devices are made")
            p.add_argument("--save-pairs", action="store_true",
                           help="write pairs.npy: the list's pairs (i < j, "
                           "as i * N + j) closer than the cutoff at the "
                           "final positions")
            steps_help = ("time steps to run (default: the built-in "
                          "scene's, listed below; "
                          f"{TOML_STEPS} for a TOML file)")
        else:
            p = sub.add_parser(name, help="LJ fluid NVE, compared with "
                               "jax-md's lists", description="The LJ fluid "
                               "(run lj-fluid), its list checked against "
                               "jax-md's at every chunk.")
            steps_help = f"time steps to run (default: {DEMO_STEPS})"
        p.add_argument("--steps", type=int, default=None, help=steps_help)
        p.add_argument("--out", default="jaxrt-out",
                       help="folder for energies.png, final.png, "
                       "snapshots.npz and trajectory.xyz, made if missing "
                       "(default: %(default)s)")
        p.add_argument("--chunk", type=int, default=None,
                       help="steps per jitted chunk (overflow is checked "
                       "between chunks); default steps/10, at most 100")
        p.add_argument("--backend", default=None,
                       help="neighbour backend (see jaxrt.available_backends)")
        p.add_argument("--n", type=int, default=None,
                       help="particles (lj-fluid, lj-polydisperse and "
                       "boids only)" + ("" if name == "run" else
                                        f"; default: {DEMO_N}"))
    return ap


_TAKES_N = ("lj-fluid", "boids", "lj-polydisperse")
"""Built-in scenes whose factory takes a particle count (--n)."""


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status.

    Arguments and the scene file are checked before JAX, jax-md and Warp
    are imported (`_early_error`), so that a mistake is reported at once.
    """
    from_command_line = argv is None
    args = _parser().parse_args(argv)
    if args.command == "scenes":
        print("\n".join(_builtin_lines()))
        return 0
    if args.command == "accuracy":
        return _accuracy(args)
    if args.command == "demo":
        args.scene, args.compare_jax_md = "lj-fluid", True
        args.steps = args.steps or DEMO_STEPS
        args.n = args.n or DEMO_N
    problem = _early_error(args)
    if problem:
        print(f"jaxrt: {problem}", file=sys.stderr)
        return 2
    warnings.filterwarnings("ignore", message="Explicitly requested dtype")
    devices = getattr(args, "devices", None)
    if devices is not None and from_command_line:
        _fake_cpu_devices(devices)  # it may start the command again
    from jaxrt import sim
    try:
        scene, default_steps = _load(args)
    except sim.SceneError as e:
        print(f"jaxrt: bad scene: {e}", file=sys.stderr)
        return 2
    steps = args.steps or default_steps
    if getattr(args, "dtype", None):
        scene = dataclasses.replace(scene, dtype=args.dtype)
    check_brute = (getattr(args, "check_brute", False)
                   or scene.name in _BRUTE_CHECKED)
    save_pairs = getattr(args, "save_pairs", False)
    if devices is not None:
        if args.compare_jax_md or check_brute:
            print("jaxrt: --devices runs without --compare-jax-md / "
                  "--check-brute", file=sys.stderr)
            return 2
        from jaxrt.sim.domains import DomainError
        try:
            run_decomposed(scene, steps=steps, out=pathlib.Path(args.out),
                           chunk=args.chunk, devices=devices,
                           save_pairs=save_pairs)
        except DomainError as e:
            print(f"jaxrt: --devices {devices}: {e}", file=sys.stderr)
            return 2
        return 0
    run(scene, steps=steps, out=pathlib.Path(args.out), chunk=args.chunk,
        compare_jax_md=args.compare_jax_md, check_brute=check_brute,
        save_pairs=save_pairs)
    return 0


def _early_error(args) -> str | None:
    """What is wrong with ``run``'s (or ``demo``'s) arguments and scene
    file that can be told without JAX, or None: counts below 1, a scene
    that is neither a built-in name nor a file, and the scene file's TOML
    and keys (`jaxrt.sim.toml.check_text`; an effect's parameters are
    checked when the scene is loaded)."""
    from jaxrt.sim.builtin import BUILTIN
    from jaxrt.sim.spec import SceneError
    from jaxrt.sim.toml import check_text
    for flag in ("steps", "chunk", "n", "devices"):
        value = getattr(args, flag, None)
        if value is not None and value < 1:
            return f"--{flag} must be >= 1; got {value}."
    if args.scene in BUILTIN:
        if args.n is not None and args.scene not in _TAKES_N:
            return (f"--n: only {', '.join(_TAKES_N)} take a particle "
                    "count.")
        return None
    path = pathlib.Path(args.scene)
    if not path.is_file():
        return (f"{args.scene!r} is neither a file nor a built-in scene "
                f"({', '.join(BUILTIN)}); `jaxrt run --help` shows how to "
                "write a scene file.")
    if args.n is not None:
        return f"--n: only for the built-in {', '.join(_TAKES_N)}."
    try:
        check_text(path.read_text(), base=path.parent)
    except SceneError as e:
        return f"bad scene: {e}"
    return None


def _fake_cpu_devices(n: int) -> None:
    """On a CPU with fewer than ``n`` devices, start this command again
    with ``n`` host devices (XLA's flag must be set before JAX starts, and
    importing jax-md starts it). An XLA_FLAGS that sets the count wins."""
    import os
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" in flags:
        return
    import jax
    if jax.default_backend() != "cpu" or jax.device_count() >= n:
        return
    env = dict(os.environ, XLA_FLAGS=(
        flags + f" --xla_force_host_platform_device_count={n}").strip())
    sys.stdout.flush()
    os.execve(sys.executable, [sys.executable, "-m", "jaxrt",
                               *sys.argv[1:]], env)


def _accuracy(args) -> int:
    from jaxrt.tools import accuracy
    plan = accuracy.QUICK if args.quick else accuracy.FULL
    if args.n is not None:
        plan = dataclasses.replace(plan, n=args.n)
    if args.steps is not None:
        plan = dataclasses.replace(plan, steps=args.steps)
    names = args.knobs.split(",") if args.knobs else None
    try:
        accuracy.run(args.scene, out=pathlib.Path(args.out), quick=args.quick,
                     budget=args.budget, plan=plan, knob_names=names)
    except ValueError as e:
        print(f"jaxrt accuracy: {e}", file=sys.stderr)
        return 2
    return 0


def _load(args):
    from jaxrt import sim
    kw = {}
    if args.backend:
        kw["backend"] = args.backend
    if args.scene in sim.BUILTIN:  # --n and the file: `_early_error`
        if args.n is not None:
            kw["n"] = args.n
        scene = sim.builtin(args.scene, **kw)
        steps = sim.BUILTIN[args.scene][1]
    else:
        scene, steps = sim.load(pathlib.Path(args.scene)), TOML_STEPS
        if args.backend:
            scene = dataclasses.replace(scene, neighbors=dataclasses.replace(
                scene.neighbors, backend=args.backend))
    sim.check_backend(scene)  # --backend, before any compiling
    return scene, steps


# ---------------------------------------------------------------------------


def _pair_cut(scene, i, j, extra: float = 0.0):
    """The distance under which pair ``(i, j)`` (int arrays) is in the
    scene's list: its cutoff, or ``max(r_i, r_j)`` with the list's radii
    (`jaxrt.sim.compile.list_radii`), plus ``extra``."""
    from jaxrt.sim.compile import list_radii
    radii = list_radii(scene)
    if radii is None:
        return scene.cutoff + extra
    return np.maximum(radii[i], radii[j]) + extra


def _pairs_within(codes: np.ndarray, position: np.ndarray, scene
                  ) -> np.ndarray:
    """The pair codes ``i * N + j`` whose particles are closer than the
    scene's cutoff (per pair with radii, `_pair_cut`) at ``position``
    (minimum image on periodic axes)."""
    r = np.asarray(position, np.float64)
    i, j = np.divmod(codes, len(r))
    d = r[i] - r[j]
    side = np.asarray(scene.box.size, float)
    per = np.asarray(scene.box.periodic)
    d = np.where(per, d - side * np.round(d / np.where(per, side, 1.0)), d)
    return codes[np.sum(d * d, axis=-1) < _pair_cut(scene, i, j) ** 2]


_BRUTE_CHECKED = ("boids", "lj-polydisperse")
"""Built-in scenes whose lists `run` checks against brute force."""


class _BruteCheck:
    """The list against a float64 brute force (minimum image on periodic
    axes) at its build positions, pair for pair."""

    def __init__(self, compiled):
        sc = compiled.scene
        self.scene = sc
        self.skin = sc.neighbors.skin
        self.periodic = np.asarray(sc.box.periodic)
        self.side = np.asarray(sc.box.size, float)
        self.checks = 0

    def pairs(self, position: np.ndarray) -> np.ndarray:
        """Sorted ``i * n + j`` (i < j) within the reach, rows in blocks."""
        r = np.asarray(position, np.float64)
        n = len(r)
        codes = []
        for start in range(0, n, 1024):
            d = r[start:start + 1024, None, :] - r[None, :, :]
            wrap = self.side * np.round(d / np.where(self.periodic,
                                                     self.side, 1.0))
            d = np.where(self.periodic, d - wrap, d)
            rows = np.arange(start, min(start + 1024, n))[:, None]
            reach = _pair_cut(self.scene, rows, np.arange(n)[None, :],
                              self.skin)
            i, j = np.nonzero(np.sum(d * d, axis=-1) < reach ** 2)
            i = i + start
            keep = i < j
            codes.append(i[keep].astype(np.int64) * n + j[keep])
        return np.sort(np.concatenate(codes))

    def compare(self, nbrs, n: int) -> None:
        want = self.pairs(np.asarray(nbrs.reference_position))
        _check_same(_pair_codes(nbrs, n), want, n, "the list", "brute force")
        self.checks += 1


def _check_same(a, b, n: int, name_a: str, name_b: str) -> None:
    """Raise naming up to five pairs where two sorted pair codes differ."""
    if a.shape != b.shape or np.any(a != b):
        only_a = [divmod(int(c), n) for c in np.setdiff1d(a, b)[:5]]
        only_b = [divmod(int(c), n) for c in np.setdiff1d(b, a)[:5]]
        raise RuntimeError(
            f"{name_a} differs from {name_b}: {len(a)} vs {len(b)} pairs; "
            f"only in {name_a}: {only_a}, only in {name_b}: {only_b}")


def _median_time(fn, *args, repeats: int = 5) -> float:
    import jax
    jax.block_until_ready(fn(*args))  # warm: compiled and cached
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


class _JaxMdCheck:
    """jax-md's own list at the same cutoff, to compare and to time."""

    def __init__(self, compiled):
        import jax
        from jax_md import partition
        from jaxrt import sim
        sc = compiled.scene
        fmt = sim.FORMATS[sc.neighbors.format]
        box = np.asarray([s if s > 0 else 1.0 for s in sc.box.size])
        reach = sc.cutoff + sc.neighbors.skin
        # Cell lists in jax-md need a periodic box; elsewhere all pairs.
        brute = not all(sc.box.periodic)
        # threshold 0: any motion rebuilds, so the list is always at the
        # positions it is updated with (same pair rule: d < reach).
        self.fns = partition.neighbor_list(
            compiled.displacement, box, reach, 0.0, format=fmt,
            disable_cell_list=brute)
        # Same cutoff and skin as jaxrt's, for timing a rebuild.
        self.timing_fns = partition.neighbor_list(
            compiled.displacement, box, sc.cutoff, sc.neighbors.skin,
            format=fmt, disable_cell_list=brute)
        self.update = jax.jit(self.fns.update)
        self.nbrs = None
        self.checks = 0

    def compare(self, jaxrt_nbrs, n: int) -> None:
        """Raise if jaxrt's pairs differ from jax-md's at jaxrt's build
        positions."""
        ref = jaxrt_nbrs.reference_position
        if self.nbrs is None:
            self.nbrs = self.fns.allocate(ref)
        else:
            self.nbrs = self.update(ref, self.nbrs)
            if self.nbrs.did_buffer_overflow:
                self.nbrs = self.fns.allocate(ref)
        _check_same(_pair_codes(jaxrt_nbrs, n), _pair_codes(self.nbrs, n), n,
                    "jaxrt's list", "jax-md's")
        self.checks += 1

    def rebuild_times(self, compiled, position) -> tuple[float, float]:
        """Median seconds of a forced, jitted rebuild: (jaxrt, jax-md)."""
        import jax
        moved = position.at[0].add(compiled.scene.neighbors.skin + 0.01)
        ours = compiled.neighbor_fn.allocate(position)
        theirs = self.timing_fns.allocate(position)
        t_ours = _median_time(jax.jit(compiled.neighbor_fn.update), moved,
                              ours)
        t_theirs = _median_time(jax.jit(self.timing_fns.update), moved,
                                theirs)
        return t_ours, t_theirs


def run(scene, *, steps: int, out: pathlib.Path, chunk: int | None = None,
        compare_jax_md: bool = False, check_brute: bool = False,
        save_pairs: bool = False) -> dict:
    """Run ``scene`` for ``steps`` steps, print a summary, write files to
    ``out``. Returns the summary as a dict. ``check_brute``: compare the
    list with a float64 brute force after every chunk."""
    import jax
    from tqdm import tqdm
    if scene.dtype == "float64":  # the scene asks for it; jax's default is 32
        jax.config.update("jax_enable_x64", True)
    from jaxrt import sim

    outputs.xyz_symbols(scene.particles)  # fail before the run, not after it
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    compiled = sim.compile_scene(scene)
    p = scene.particles
    n = p.n
    print(f"scene {scene.name!r}: {n} particles, {p.dim}D, "
          f"{steps} steps of dt = {scene.integrator.dt:.4g}")
    for line in compiled.plan:
        print(f"  - {line}")
    for flag, wanted in (("--compare-jax-md", compare_jax_md),
                         ("--check-brute", check_brute)):
        if wanted and compiled.neighbor_fn is None:
            raise SystemExit(f"jaxrt: {flag} needs a scene with a pair "
                             "effect (it has no neighbour list).")
    checker = _JaxMdCheck(compiled) if compare_jax_md else None
    brute = _BruteCheck(compiled) if check_brute else None

    state, nbrs = compiled.init()
    chunk = chunk or max(1, min(100, steps // 10))
    stats = sim.RunStats()
    frames = [np.asarray(state.position)]
    frame_velocities = [np.asarray(state.velocity)]
    frame_steps = [0]
    # Compile outside the timed loop (the first chunk of each length).
    t = time.perf_counter()
    jax.block_until_ready(compiled.chunk.lower(state, nbrs, steps=chunk)
                          .compile())
    t_compile = time.perf_counter() - t
    for c in (checker, brute):
        if c is not None:
            c.compare(nbrs, n)
    bar = tqdm(total=steps, unit="step", desc=scene.name, smoothing=0.1,
               mininterval=0.5)
    done, t_run = 0, 0.0
    while done < steps:
        k = min(chunk, steps - done)
        t = time.perf_counter()
        state, nbrs = sim.run_chunk(compiled, state, nbrs, steps=k,
                                    stats=stats)
        jax.block_until_ready(state.position)
        t_run += time.perf_counter() - t
        done += k
        bar.update(k)
        for c in (checker, brute):
            if c is not None:
                c.compare(nbrs, n)
        position = np.asarray(state.position)  # one copy to the host
        if not np.all(np.isfinite(position)):
            raise RuntimeError(f"positions became non-finite by step {done}")
        frames.append(position)
        frame_velocities.append(np.asarray(state.velocity))
        frame_steps.append(done)
    bar.close()
    if nbrs is not None:
        from jaxrt.errors import check
        check(nbrs)

    ke = np.concatenate(stats.kinetic).astype(np.float64)
    u = np.concatenate(stats.potential).astype(np.float64)
    mom = np.concatenate(stats.momentum).astype(np.float64)
    e = ke + u
    rows = [("particles", f"{n}"), ("steps", f"{done}"),
            ("steps/s (compiled)", f"{done / t_run:.1f}"),
            ("compile (s)", f"{t_compile:.1f}"),
            ("neighbour updates", f"{done if nbrs is not None else 0}"),
            ("list rebuilds", f"{stats.rebuilds}"),
            ("overflows (redone chunks)", f"{stats.overflows}")]
    summary = dict(steps_per_s=done / t_run, rebuilds=stats.rebuilds,
                   overflows=stats.overflows, steps=done)
    if brute is not None:
        rows.append(("lists equal to brute force",
                     f"yes, {brute.checks} checks (every {chunk} steps)"))
        summary["brute_checks"] = brute.checks
    tri_stats = outputs.triangulation_stats(nbrs)
    if tri_stats is not None:
        rows.append(("triangulation rebuilds from scratch",
                     f"{tri_stats['rebuilds']}"))
        rows.append(("edge flips (total)", f"{tri_stats['flips_total']}"))
        summary["triangulation"] = tri_stats
    if compiled.conservative:
        drift = (e[-1] - e[0]) / n
        rows.append(("energy drift (E_end - E_1) / N", f"{drift:+.3e}"))
        rows.append(("max |E - E_1| / N", f"{np.abs(e - e[0]).max() / n:.3e}"))
        summary["energy_drift_per_particle"] = float(drift)
    else:
        rows.append(("total mass (exact)",
                     f"{p.masses.sum():.6g} (constant by construction)"))
    # One-body effects (gravity, walls) are external forces.
    has_external = any(not x.pairwise for x in scene.effects)
    dmom = np.abs(mom[-1] - mom[0]).max()
    rows.append(("momentum change |P_end - P_1|" +
                 (" (external forces)" if has_external else ""),
                 f"{dmom:.3e}"))
    summary["momentum_change"] = float(dmom)
    if checker is not None:
        t_ours, t_theirs = checker.rebuild_times(compiled, state.position)
        rows += [("lists equal to jax-md's", f"yes, {checker.checks} checks"),
                 ("rebuild jaxrt (ms, median)", f"{1e3 * t_ours:.2f}"),
                 ("rebuild jax-md (ms, median)", f"{1e3 * t_theirs:.2f}"),
                 ("speed-up", f"{t_theirs / t_ours:.2f}x")]
        summary.update(rebuild_jaxrt_s=t_ours, rebuild_jaxmd_s=t_theirs)
    width = max(len(r[0]) for r in rows)
    print()
    for name, val in rows:
        print(f"  {name:<{width}}  {val}")

    outputs.write_outputs(scene, out, state, np.asarray(frames),
                   np.asarray(frame_velocities), frame_steps, ke, u)
    written = "energies.png, final.png, snapshots.npz, trajectory.xyz"
    if save_pairs and nbrs is not None:
        np.save(out / "pairs.npy", _pairs_within(
            _pair_codes(nbrs, n), frames[-1], scene))
        written += ", pairs.npy"
    if tri_stats is not None:
        outputs.write_triangulation(out / "triangulation.png", scene, state, nbrs)
        written += ", triangulation.png"
    print(f"\nwrote {out}/{written} ({time.perf_counter() - t_start:.1f} s "
          "total)")
    return summary


def run_decomposed(scene, *, steps: int, out: pathlib.Path, devices: int,
                   chunk: int | None = None, save_pairs: bool = False
                   ) -> dict:
    """`run` with the box cut into ``devices`` slabs along x
    (`jaxrt.sim.domains.from_scene`); the same outputs and summary rows.
    Raises `jaxrt.sim.domains.DomainError` for a scene it cannot cut."""
    import types
    import jax
    import jax.numpy as jnp
    from tqdm import tqdm
    if scene.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    from jaxrt.sim import domains

    outputs.xyz_symbols(scene.particles)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    dom = domains.from_scene(scene, devices)
    p = scene.particles
    n = p.n
    mass = float(p.masses[0])
    dtype = jnp.dtype(scene.dtype)
    print(f"scene {scene.name!r}: {n} particles, {p.dim}D, "
          f"{steps} steps of dt = {scene.integrator.dt:.4g}")
    print(f"  - domain decomposition: {devices} slabs along x on "
          f"{devices} {jax.devices()[0].platform} devices, slab width "
          f"{dom.width:.4g}, halo width cutoff + skin = {dom.halo_width:.4g}")
    t = time.perf_counter()
    state = dom.distribute(p.positions, p.velocities, dtype=dtype)
    state = jax.jit(dom.forces_into, static_argnums=1)(state, mass)
    print(f"  - per device: {state.capacity} owned slots, "
          f"{state.halo_capacity} halo slots per face, Dense list of "
          f"{state.nbrs.idx.shape[2]} per row ({time.perf_counter() - t:.1f}"
          " s to distribute)")
    chunk = chunk or max(1, min(100, steps // 10))
    run_chunk = domains.chunk_fn(dom, scene.integrator.dt, mass)
    t = time.perf_counter()
    jax.block_until_ready(run_chunk.lower(state, steps=chunk).compile())
    t_compile = time.perf_counter() - t
    frames = [dom.gather(state)]
    frame_velocities = [dom.gather(state, "velocity")]
    frame_steps = [0]
    stats: dict = {}
    kin, pot, moms = [], [], []
    bar = tqdm(total=steps, unit="step", desc=scene.name, smoothing=0.1,
               mininterval=0.5)
    done, t_run = 0, 0.0
    while done < steps:
        k = min(chunk, steps - done)
        t = time.perf_counter()
        state, (ke, u, mom) = domains.run_chunk(dom, run_chunk, state, k,
                                                stats)
        jax.block_until_ready(state.position)
        t_run += time.perf_counter() - t
        done += k
        bar.update(k)
        kin.append(np.asarray(ke))
        pot.append(np.asarray(u))
        moms.append(np.asarray(mom))
        position = dom.gather(state)
        if not np.all(np.isfinite(position)):
            raise RuntimeError(f"positions became non-finite by step {done}")
        frames.append(position)
        frame_velocities.append(dom.gather(state, "velocity"))
        frame_steps.append(done)
    bar.close()
    dom.check(state)
    ke = np.concatenate(kin).astype(np.float64)
    u = np.concatenate(pot).astype(np.float64)
    mom = np.concatenate(moms).astype(np.float64)
    e = ke + u
    rebuilds = int(np.asarray(state.rebuilds)[0])
    rows = [("particles", f"{n}"), ("devices (slabs along x)", f"{devices}"),
            ("steps", f"{done}"),
            ("steps/s (compiled)", f"{done / t_run:.1f}"),
            ("compile (s)", f"{t_compile:.1f}"),
            ("list rebuilds (with migration)", f"{rebuilds}"),
            ("overflows (redone chunks)", f"{stats.get('redone', 0)}")]
    conservative = dom.accel is None
    if conservative:
        rows += [("energy drift (E_end - E_1) / N",
                  f"{(e[-1] - e[0]) / n:+.3e}"),
                 ("max |E - E_1| / N", f"{np.abs(e - e[0]).max() / n:.3e}")]
    else:
        rows.append(("total mass (exact)", f"{p.masses.sum():.6g} "
                     "(constant by construction)"))
    dmom = np.abs(mom[-1] - mom[0]).max()
    has_external = any(not x.pairwise for x in scene.effects)
    rows.append(("momentum change |P_end - P_1|" +
                 (" (external forces)" if has_external else ""),
                 f"{dmom:.3e}"))
    width = max(len(r[0]) for r in rows)
    print()
    for name, val in rows:
        print(f"  {name:<{width}}  {val}")
    final = types.SimpleNamespace(velocity=frame_velocities[-1])
    outputs.write_outputs(scene, out, final, np.asarray(frames),
                   np.asarray(frame_velocities), frame_steps, ke, u)
    written = "energies.png, final.png, snapshots.npz, trajectory.xyz"
    if save_pairs:
        np.save(out / "pairs.npy", _pairs_within(dom.pairs(state),
                                                 frames[-1], scene))
        written += ", pairs.npy"
    print(f"\nwrote {out}/{written} ({time.perf_counter() - t_start:.1f} s "
          "total)")
    return dict(steps_per_s=done / t_run, rebuilds=rebuilds,
                overflows=stats.get("redone", 0), steps=done,
                    momentum_change=float(dmom))


if __name__ == "__main__":
    raise SystemExit(main())
