"""Every test under tests/stability carries the ``stability`` marker
(registered in pyproject.toml). The default run (``-m 'not slow'``) keeps
the fast part; ``-m "stability and slow"`` runs the long cases."""
import pathlib

import jax
import pytest

_HERE = pathlib.Path(__file__).parent.resolve()


def pytest_collection_modifyitems(config, items):
    for item in items:
        if _HERE in pathlib.Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.stability)


@pytest.fixture
def x64():
    """float64 for the test (the global flag: Warp's and Qhull's callbacks
    run in other threads, where the enable_x64 context would not hold)."""
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", before)
