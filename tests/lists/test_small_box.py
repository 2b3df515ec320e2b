"""Small periodic boxes: a cutoff of half a periodic height or more.

The rule (jax-md's): the list holds every pair whose distance under the
caller's displacement is below the cutoff, once, through the image the
displacement picks. The oracle is that displacement itself, evaluated in
float64 on every pair (`displacement_pairs`); `cell` (its portable path and
its kernel in Pallas' interpreter) and `brute` must give exactly its set, in
every layout, with one `SmallBoxWarning` per list. The backends that cannot
(ray-traced, Delaunay) refuse, naming `cell` and `brute`.
"""
from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax_md import energy, partition, space

import jaxrt
from jaxrt import backends
from jaxrt.lists.neighbors import SmallBoxWarning
from oracle import (assert_layout, brute_pairs, brute_pairs_general,
                    brute_pairs_radii, expected_pairs, list_pairs)

FORMATS = [partition.Dense, partition.Sparse, partition.OrderedSparse]
PORTABLE = backends.Cell(kernel="xla")
INTERPRETED = backends.Cell(kernel="interpret")


def displacement_pairs(displacement, R, cutoff, mask_self=True, **kwargs):
    """Set of (i, j) with ``|displacement(R_i, R_j, **kwargs)| < cutoff``,
    the caller's displacement evaluated in float64 on every pair."""
    with jax.enable_x64(True):
        R64 = jnp.asarray(np.asarray(R, np.float64))
        kw = {k: jnp.asarray(np.asarray(v, np.float64))
              for k, v in kwargs.items()}
        d = jax.vmap(jax.vmap(lambda a, b: displacement(a, b, **kw),
                              (None, 0)), (0, None))(R64, R64)
        d2 = np.asarray(jnp.sum(d * d, axis=-1))
    keep = d2 < float(cutoff) ** 2
    if mask_self:
        np.fill_diagonal(keep, False)
    i, j = np.nonzero(keep)
    return set(zip(i.tolist(), j.tolist()))


def _triclinic(dim: int, scale: float) -> np.ndarray:
    """A sheared box (lattice vectors as columns), float32 values."""
    box = np.eye(dim) * scale
    box[0, 1] = 0.6 * scale
    if dim == 3:
        box[0, 2], box[1, 2] = 0.3 * scale, -0.4 * scale
    return box.astype(np.float32)


def _scene(name):
    """``(displacement, box, cutoff, positions, fractional, numpy oracle)``
    for the scenes below; 40 particles each."""
    rng = np.random.default_rng(sum(map(ord, name)))
    kind, dim, size, cutoff = SCENES[name]
    if kind == "orthorhombic":
        side = np.asarray(size, np.float32) * np.ones(dim, np.float32)
        R = (rng.uniform(0, 1, (40, dim)) * side).astype(np.float32)
        disp, _ = space.periodic(side)
        return (disp, side, cutoff, R, False,
                lambda: brute_pairs(R, cutoff, side, True))
    box = _triclinic(dim, size)
    f = rng.uniform(0, 1, (40, dim)).astype(np.float32)
    fractional = kind == "triclinic fractional"
    R = f if fractional else (f @ box.T).astype(np.float32)
    disp, _ = space.periodic_general(jnp.asarray(box),
                                     fractional_coordinates=fractional)
    return (disp, box, cutoff, R, fractional,
            lambda: brute_pairs_general(f, box, cutoff))


# A small axis has one cell across (cells are at least the cutoff wide
# across, and at least a quarter of it along x, where a periodic row of at
# most 9 cells is one whole run): every particle is a candidate there once.
SCENES = {
    # name: (kind, dim, side or box scale, cutoff)
    # jax-md's LJ small box
    "L5-c3": ("orthorhombic", 3, 5.0, 3.0),
    # cutoff far above the side (jax-md's Behler-Parrinello test): every
    # pair, through its minimum image
    "L1.5-c8.5": ("orthorhombic", 3, 1.5, 8.5),
    # exactly half the side: the smallest cutoff that makes a box small
    "L4-c2": ("orthorhombic", 3, 4.0, 2.0),
    "2d-L3-c2.9": ("orthorhombic", 2, 3.0, 2.9),
    # per axis: x large, y small, z two cells (offsets aliasing, not small)
    "mixed": ("orthorhombic", 3, (9.0, 2.5, 6.0), 2.2),
    "triclinic fractional": ("triclinic fractional", 3, 3.0, 2.0),
    "2d triclinic": ("triclinic", 2, 3.0, 2.5),
    "triclinic c8.5": ("triclinic", 3, 1.5, 8.5),
}

# One layout per scene in the default run (each layout is a compile, ~3 s
# on CI's cores), every layout of every scene in the slow run.
_DEFAULT = {"L5-c3": 0, "L1.5-c8.5": 1, "mixed": 2,
            "triclinic fractional": 1, "2d triclinic": 0}
_INTERPRETED = {"L5-c3": 2, "mixed": 1}


def _cases():
    for name, (kind, *_) in SCENES.items():
        engines = [("cell", PORTABLE), ("brute", "brute")]
        if kind == "orthorhombic":  # the kernel computes orthorhombic images
            engines.append(("interpret", INTERPRETED))
        for label, backend in engines:
            for k, fmt in enumerate(FORMATS):
                default = (label == "brute" and k == 0
                           or label == "cell" and _DEFAULT.get(name) == k
                           or label == "interpret"
                           and _INTERPRETED.get(name) == k)
                yield pytest.param(
                    name, backend, fmt,
                    id=f"{name}-{label}-{fmt.name}",
                    marks=() if default else (pytest.mark.slow,))


@pytest.mark.parametrize("name,backend,fmt", list(_cases()))
def test_small_box_list_is_the_displacements(name, backend, fmt):
    disp, box, cutoff, R, fractional, numpy_oracle = _scene(name)
    if backend is INTERPRETED:
        from jaxrt.backends.cell import kernel as _cell_kernel
        if not _cell_kernel.fits(1, 1, 1):
            pytest.skip("this JAX has no Pallas Triton backend")
    with pytest.warns(SmallBoxWarning, match="jaxrt.pairs"):
        nbrs = jaxrt.neighbor_list(disp, box, cutoff, format=fmt,
                                   backend=backend,
                                   fractional_coordinates=fractional
                                   ).allocate(jnp.asarray(R))
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)  # a candidate met twice would be listed twice
    want = displacement_pairs(disp, R, cutoff)
    assert list_pairs(nbrs) == expected_pairs(fmt, want)
    # The independent float64 oracle (no tie at half a period here).
    assert want == numpy_oracle()
    if name == "L1.5-c8.5":  # every pair
        assert len(want) == len(R) * (len(R) - 1)


def test_warning_once_per_list_and_none_for_a_large_box():
    side = 5.0
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(0), (30, 3)) * side
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fns = jaxrt.neighbor_list(disp, side, 2.6, backend="brute")
        nbrs = fns.allocate(R)
        nbrs = fns.update(R + 0.1, nbrs)
        fns.allocate(R * 0.9)
        jaxrt.neighbor_list(disp, side, 2.4, backend="brute").allocate(R)
    small = [w for w in caught if issubclass(w.category, SmallBoxWarning)]
    assert len(small) == 1
    text = str(small[0].message)
    assert "axis 0 (L/2 = 2.5)" in text and "once" in text
    assert "other periodic images" in text and "jaxrt.pairs" in text
    # It points at the caller's line, not into jaxrt.
    assert small[0].filename == __file__
    # A second list warns again.
    with pytest.warns(SmallBoxWarning):
        jaxrt.neighbor_list(disp, side, 2.6, backend="brute").allocate(R)


def test_a_backend_without_small_boxes_refuses_naming_cell_and_brute():
    """A backend of one's own lacks the ``small_boxes`` capability, so the
    front refuses for it; the named backends are the ray-traced ones
    (test_bvh, test_never_wrong) and Delaunay."""
    from test_neighbors import TwentyLineBrute
    side = 4.0
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(1), (20, 2)) * side
    for backend in [TwentyLineBrute()] + (
            ["delaunay"] if "delaunay" in jaxrt.available_backends() else []):
        with pytest.raises(ValueError, match=(
                r"axis 0 \(L/2 = 2\), which backend=.* needs.*"
                r"backend='cell' or backend='brute'")):
            jaxrt.neighbor_list(disp, side, 2.0, backend=backend).allocate(R)


@pytest.mark.skipif("bvh" not in jaxrt.available_backends(),
                    reason="needs Warp")
def test_bvh_refuses_a_small_box_naming_cell():
    side = 4.0
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(2), (20, 3)) * side
    with pytest.raises(ValueError,
                       match=r"backend='bvh' needs.*backend='cell'"):
        jaxrt.neighbor_list(disp, side, 2.5, backend="bvh").allocate(R)


@pytest.mark.parametrize("kind", [
    "orthorhombic", pytest.param("triclinic", marks=pytest.mark.slow)])
def test_a_box_shrinking_under_update_keeps_the_list_exact(kind):
    """Fractional positions, the box passed to a jitted update: the grid
    is recomputed from the box at every call, down to one cell across and
    a cutoff above the side; no error bit, no overflow (the buffers were
    sized at the smallest box, where every pair is listed)."""
    cutoff = 2.6
    shape = np.eye(3) if kind == "orthorhombic" else _triclinic(3, 1.0)
    boxes = [s * shape for s in (2.0, 10.0, 6.0, 4.0, 2.0)]
    disp, _ = space.periodic_general(jnp.asarray(boxes[0], jnp.float32))
    frac = jax.random.uniform(jax.random.PRNGKey(3), (50, 3))
    fns = jaxrt.neighbor_list(disp, boxes[0], cutoff, backend=PORTABLE,
                              fractional_coordinates=True,
                              format=partition.Sparse)
    with pytest.warns(SmallBoxWarning):
        nbrs = fns.allocate(frac, box=jnp.asarray(boxes[0], jnp.float32))
    update = jax.jit(fns.update)
    sizes = []
    for box in boxes[1:]:
        box = jnp.asarray(box, jnp.float32)
        nbrs = update(frac, nbrs, box=box)
        assert int(nbrs.error.code) == 0
        want = displacement_pairs(disp, frac, cutoff, box=box)
        assert list_pairs(nbrs) == want
        sizes.append(len(want))
    assert sizes[0] < sizes[1] < sizes[2] < sizes[3] == 50 * 49


@pytest.mark.parametrize("fmt", [partition.Dense] + [
    pytest.param(f, marks=pytest.mark.slow) for f in FORMATS[1:]])
def test_lennard_jones_small_box_energy_equals_all_pairs(fmt):
    """jax-md's own check: the LJ energy on the list equals the all-pairs
    energy under the same displacement (box 5, cutoff 2.5 + skin 0.5)."""
    side = np.float32(5.0)
    disp, _ = space.periodic(side)
    R = jax.random.uniform(jax.random.PRNGKey(1), (10, 3)) * side
    exact = energy.lennard_jones_pair(disp)(R)
    neighbor_fn, energy_fn = energy.lennard_jones_neighbor_list(
        disp, side, format=fmt, neighbor_list_fn=jaxrt.neighbor_list)
    with pytest.warns(SmallBoxWarning):
        nbrs = neighbor_fn.allocate(R)
    # The same float32 terms summed in another order: each partial sum
    # rounds by at most eps times the sum of magnitudes so far.
    with jax.enable_x64(True):
        R64 = jnp.asarray(np.asarray(R, np.float64))
        dr = space.distance(space.map_product(disp)(R64, R64))
        terms = energy.multiplicative_isotropic_cutoff(
            energy.lennard_jones, 2.0, 2.5)(dr)
        magnitude = float(jnp.sum(jnp.where(jnp.eye(len(R)) > 0, 0,
                                            jnp.abs(terms))))
    bound = len(R) ** 2 * float(jnp.finfo(jnp.float32).eps) * magnitude
    assert abs(float(energy_fn(R, nbrs)) - float(exact)) <= bound
    assert magnitude > 0  # the scene has pairs in range


def test_per_particle_radii_in_a_small_box():
    """The cell list's radius classes in a box less than twice the largest
    radius across: each pair within max(r_i, r_j) through its minimum
    image, once."""
    rng = np.random.default_rng(5)
    side = 3.0
    R = rng.uniform(0, side, (40, 3)).astype(np.float32)
    radii = rng.uniform(0.1, 2.0, 40).astype(np.float32)
    disp, _ = space.periodic(side)
    with pytest.warns(SmallBoxWarning):
        nbrs = jaxrt.neighbor_list(disp, side, 2.0, backend=PORTABLE,
                                   radii=radii, format=partition.Sparse
                                   ).allocate(jnp.asarray(R))
    assert not nbrs.did_buffer_overflow
    assert_layout(nbrs)
    assert list_pairs(nbrs) == brute_pairs_radii(R, radii, side, True)
