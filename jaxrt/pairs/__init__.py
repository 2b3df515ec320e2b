"""Pairs ``(i, j, S)`` with lattice shifts in any cell, for ML graphs
(`jaxrt.pairs.search`), and ASE in and out (`jaxrt.pairs.ase`)."""
from jaxrt.pairs.ase import neighbor_list as ase_neighbor_list
from jaxrt.pairs.ase import pairs_from_ase, pairs_to_ase
from jaxrt.pairs.search import (ErrorBit, Pairs, PairsError, PairSizes,
                                pairs, pairs_sizes)

__all__ = ["ErrorBit", "PairSizes", "Pairs", "PairsError",
           "ase_neighbor_list", "pairs", "pairs_from_ase", "pairs_sizes",
           "pairs_to_ase"]
