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


def pytest_configure(config):
    """Compile the Warp kernels once, in a subprocess, before any test.

    Warp compiles CPU kernels in-process with its own LLVM (warp-clang);
    on a fresh machine the first test worker to load a kernel module would
    do that next to XLA's LLVM, and the suite's later XLA compiles then
    crashed twice (a segfault and an abort inside backend_compile) after
    the kernels changed. With the kernel cache filled here, workers only
    load compiled binaries.
    """
    import os
    import subprocess
    import sys
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return  # the controller did it
    modules = ("jaxrt.rt.aabb", "jaxrt.rt.epsilon", "jaxrt.rt.spheres",
               "jaxrt.rt.squares", "jaxrt.rt.orcs")
    code = ("import importlib, warp as wp\n"
            f"for m in {modules!r}:\n"
            "    importlib.import_module(m)\n"
            "    wp.load_module(module=m, device='cpu')\n")
    try:
        subprocess.run([sys.executable, "-c", code], check=False,
                       capture_output=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired):
        pass  # the tests then compile the kernels themselves


try:
    import pytest  # noqa: E402
except ImportError:  # pragma: no cover
    pytest = None
else:
    @pytest.fixture(autouse=True, scope="module")
    def _free_compiled_programs():
        """Drop JAX's compiled programs after each test file.

        A worker compiles hundreds of programs that no later file calls; in
        a full run each worker grew past 5 GB, and workers have died inside
        XLA's compiler (aborts, segfaults) late in long runs. Files share
        few programs, so recompiling those is cheap.
        """
        yield
        import gc
        jax.clear_caches()
        gc.collect()
