"""Energies on jax-md neighbour lists: Lennard-Jones and SPH.

Everything here is jit-able and differentiable with respect to positions and
parameters, and works on Dense, Sparse and OrderedSparse lists from
`jaxrt.neighbor_list` or `jax_md.partition.neighbor_list`.

LJ (`jaxrt.energy.lj`): `lennard_jones`, `lennard_jones_truncated`,
`lennard_jones_radii` (per-particle radii, seed 003),
`lennard_jones_pair_neighbor_list`, `lennard_jones_neighbor_list`.
Without a list (`jaxrt.energy.listfree.lj`, seed 003 ORCS): `lennard_jones_fused`
(energy, first derivatives from one traversal), `lennard_jones_perse_step`
(ORCS-persé leapfrog step).
SPH (`jaxrt.energy.sph`): kernels `CubicSpline`, `QuinticSpline`,
`WendlandC2`, `WendlandC4` (or `kernel(name, h, dim=)`), `density`, `Tait`,
`acceleration` -> `Acceleration`.
Without a list (`jaxrt.energy.listfree.sph`): `density_fused`,
`acceleration_fused` (the same results, a walk over the cell grid; first
derivatives from a second walk).
"""
from jaxrt.energy import lj, sph
from jaxrt.energy.listfree import lj as fused
from jaxrt.energy.listfree import sph as sph_fused
from jaxrt.energy.listfree.lj import (
    FusedInputError,
    FusedSums,
    HigherOrderError,
    lennard_jones_fused,
    lennard_jones_perse_step,
)
from jaxrt.energy.lj import (
    TRUNCATIONS,
    lennard_jones,
    lennard_jones_neighbor_list,
    lennard_jones_pair_neighbor_list,
    lennard_jones_radii,
    lennard_jones_truncated,
)
from jaxrt.energy.sph import (
    KERNELS,
    Acceleration,
    CubicSpline,
    Kernel,
    QuinticSpline,
    Tait,
    WendlandC2,
    WendlandC4,
    acceleration,
    density,
    kernel,
)
from jaxrt.energy.listfree.sph import acceleration_fused, density_fused

__all__ = [
    "KERNELS",
    "TRUNCATIONS",
    "Acceleration",
    "FusedInputError",
    "FusedSums",
    "HigherOrderError",
    "CubicSpline",
    "Kernel",
    "QuinticSpline",
    "Tait",
    "WendlandC2",
    "WendlandC4",
    "acceleration",
    "acceleration_fused",
    "density",
    "density_fused",
    "fused",
    "kernel",
    "lennard_jones",
    "lennard_jones_fused",
    "lennard_jones_neighbor_list",
    "lennard_jones_pair_neighbor_list",
    "lennard_jones_perse_step",
    "lennard_jones_radii",
    "lennard_jones_truncated",
    "lj",
    "sph",
    "sph_fused",
]
