"""The benchmarks, a package so that tests import them (``from benchmarks
import figure8``) and ``python3 -m benchmarks.NAME`` runs one from the
repository's root; ``python3 benchmarks/NAME.py`` works too. Every script
uses one harness (`benchmarks._harness`); RESULTS.md holds the numbers."""
