"""The sorted cell list (``backend="cell"``): the search
(`jaxrt.backends.cell.search`), its GPU kernels
(`jaxrt.backends.cell.kernel`) and per-particle radius classes
(`jaxrt.backends.cell.radius_classes`)."""
from jaxrt.backends.cell.search import Cell

__all__ = ["Cell"]
