"""Pairs ``(i, j, S)`` with lattice shifts in any cell, for ML graphs: one
system (`jaxrt.pairs.search`), flat batches in jraph's layout
(`jaxrt.pairs.batch`), ASE in and out (`jaxrt.pairs.ase`); the search
program (`jaxrt.pairs.program`, with `jaxrt.pairs.cells`,
`jaxrt.pairs.blocks`, `jaxrt.pairs.rows` and `jaxrt.pairs.prefix`), the
host search of small systems
(`jaxrt.pairs.host`) and the argument checks (`jaxrt.pairs.checks`) behind
them."""
from jaxrt.pairs.ase import neighbor_list as ase_neighbor_list
from jaxrt.pairs.ase import batch_from_ase, pairs_from_ase, pairs_to_ase
from jaxrt.pairs.batch import BatchPairs, pairs_batch, pairs_batch_sizes
from jaxrt.pairs.search import (ErrorBit, Float32Warning, Pairs, PairsError,
                                PairSizes, pairs, pairs_sizes)

__all__ = ["BatchPairs", "ErrorBit", "Float32Warning", "PairSizes", "Pairs",
           "PairsError", "ase_neighbor_list", "batch_from_ase", "pairs",
           "pairs_batch", "pairs_batch_sizes", "pairs_from_ase",
           "pairs_sizes", "pairs_to_ase"]
