"""The cell list's sorted grid, by public-internal names: what the radius
classes (`jaxrt.backends.cell.radius_classes`) and the list-free energies'
cell walk (`jaxrt.energy.listfree`) share with the search
(`jaxrt.backends.cell.search`, where the bodies live for now).

* ``REACH``: (reach along x, reach across) in cells of the default stencil.
* ``grid(cart, geometry, query, reach, ...)``: wrapped positions, integer
  cells and cells per axis.
* ``key(cell, cells)``: each cell's row-major index.
* ``table_size(n)``, ``static_cells(...)``: sizes of the cell-start table.
* ``cell_starts(sorted_key, table)``: where each cell starts in sorted order.
* ``runs(...)``, ``run_images(...)``, ``image_axes(...)``: the stencil's
  runs of consecutive cells, and their periodic images.
* ``select(words, width, payload, group)``: the set bits of candidate words.
"""
from jaxrt.backends.cell.search import (REACH, cell_starts, grid, image_axes,
                                        key, run_images, runs, select,
                                        static_cells, table_size)

__all__ = ["REACH", "cell_starts", "grid", "image_axes", "key", "run_images",
           "runs", "select", "static_cells", "table_size"]
