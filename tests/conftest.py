"""Test-suite settings.

Hypothesis is derandomised (each test's examples follow from its name, so
a failure in CI is a failure on every machine) and keeps no example
database; the ``slow`` tests run many more examples of the same
properties.

The suite compiles hundreds of small XLA programs and runs each once or a
few times on tiny systems, so LLVM's optimisation passes cost far more than
they save: the CPU backend is told not to run them (set before JAX starts;
an ``XLA_FLAGS`` already in the environment wins). Semantics are unchanged
(XLA's CPU backend does not enable fast-math either way), and every
comparison with jax-md compiles both sides under the same flags.
"""
import os

if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_backend_optimization_level=0").strip()

# On GPUs XLA rounds float32 matrix products to TF32 by default, so jax-md's
# periodic_general metric (a matrix product) is only good to ~1e-3 there and
# the float64 oracles would disagree with it near the cutoff. jaxrt copes
# (`jaxrt._space`'s slack); the oracles need the metric exact.
import jax  # noqa: E402

jax.config.update("jax_default_matmul_precision", "highest")

try:  # a test dependency; GPU machines may run the suite's other files
    import hypothesis  # noqa: E402
except ImportError:
    pass
else:
    hypothesis.settings.register_profile("jaxrt", derandomize=True,
                                         database=None, deadline=None,
                                         print_blob=True)
    hypothesis.settings.load_profile("jaxrt")
