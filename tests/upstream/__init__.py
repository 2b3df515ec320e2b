"""jax-md's own tests, taken from its sdist and run on jaxrt's list
(``README.md`` here; the tests are in ``tests/test_jax_md_acceptance.py``)."""
