"""Energies without a list: Lennard-Jones (`jaxrt.energy.listfree.lj`) and
SPH (`jaxrt.energy.listfree.sph`), summed while walking the cell grid or a
BVH, differentiable in positions."""
