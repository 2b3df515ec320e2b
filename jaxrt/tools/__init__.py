"""Tools around the library, never imported by ``import jaxrt``: the
``jaxrt`` command (`jaxrt.tools.cli`) and the accuracy sweep
(`jaxrt.tools.accuracy`)."""
