"""Fixtures of the energy tests."""
import jax
import pytest


@pytest.fixture
def x64():
    """float64 for the test."""
    with jax.enable_x64(True):
        yield
