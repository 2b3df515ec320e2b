"""The ray-traced methods' half-box rule, without Warp: a periodic pair is
reported through its nearest image only (`jaxrt.backends.rt.periodic`'s
gamma rays), so the search radius must stay below half of every periodic
side. The list-free energies apply the same rule on every backend.
"""
from __future__ import annotations


# Cutoffs must stay this far (relatively) below half the side, so that
# rounding of box centres can never make two images both canonical-looking.
CUTOFF_MARGIN = 2.0 ** -16


def cutoff_fits(cutoff: float, side: float) -> bool:
    """Does ``cutoff`` allow gamma rays on a periodic axis of ``side``?"""
    return side > 0 and cutoff < 0.5 * side * (1.0 - CUTOFF_MARGIN)


def cutoff_error(cutoff: float, side: float, axis: int) -> str:
    return (f"the search radius r_cutoff + dr_threshold = {cutoff:g} must be "
            f"below half the periodic box side {side:g} on axis {axis} for the "
            "ray-traced backends (they report each pair through its nearest "
            "image only). Use backend='cell' or backend='brute' (they list "
            "each pair once, through the image the displacement picks, as "
            "jax-md does), a larger box, or a smaller r_cutoff / "
            "dr_threshold.")


def check_cutoff(cutoff: float, side, periodic) -> None:
    """Raise ValueError unless ``cutoff`` is below half of every periodic side
    (`cutoff_fits`), naming the first axis where it is not."""
    for a, p in enumerate(periodic):
        if p and not cutoff_fits(cutoff, float(side[a])):
            raise ValueError(cutoff_error(cutoff, float(side[a]), a))
