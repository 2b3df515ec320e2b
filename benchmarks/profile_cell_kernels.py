"""A driver for Nsight Compute (#18): the two cell kernels at N = 10^6 on
roofline.py's LJ system, a few calls each after compilation, so that

    ncu --kernel-name regex:jaxrt_cell --launch-skip 2 --launch-count 2 \\
        --section SpeedOfLight --section Occupancy --section WarpStateStats \\
        --section SchedulerStats --section LaunchStats \\
        python benchmarks/profile_cell_kernels.py

reports the fused LJ forces' walk (``jaxrt_cell_pair_sums``) and the list
rebuild's candidate kernel (``jaxrt_cell_walk``): occupancy, issue-slot use
and stall reasons, what the roofline's times alone cannot say. Times
nothing itself (benchmarks/roofline.py does).

    python benchmarks/profile_cell_kernels.py --n 8000     # CPU smoke
"""
from __future__ import annotations

import argparse


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--calls", type=int, default=4)
    args = parser.parse_args(argv)
    import jax
    import jax.numpy as jnp
    from jax_md import partition
    import jaxrt
    import roofline
    from jaxrt.backends import Cell
    from jaxrt.energy import lennard_jones_fused
    R, box, disp = roofline._system(args.n, jnp.float32)
    energy_fn = lennard_jones_fused(disp, box, r_onset=2.0, r_cutoff=2.5,
                                    backend=Cell(kernel="auto"))
    forces = jax.jit(jax.grad(energy_fn))
    for _ in range(args.calls):
        forces(R).block_until_ready()
    neighbor_fn = jaxrt.neighbor_list(disp, box, 2.5, dr_threshold=0.0,
                                      format=partition.Dense,
                                      backend=Cell(kernel="auto"))
    nbrs = neighbor_fn.allocate(R)
    update = jax.jit(lambda R: nbrs.update(R).idx)
    for _ in range(args.calls):
        update(R).block_until_ready()
    print(f"profile_cell_kernels: N = {R.shape[0]}, {args.calls} calls each")


if __name__ == "__main__":
    main()
