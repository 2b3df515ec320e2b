# The upstream file matches pytest's ``*_test.py`` pattern, but run by
# itself it would test jax-md's own list: tests/lists/test_jax_md_acceptance.py
# runs its cases on jaxrt's instead.
collect_ignore = ["jax_md_partition_test.py"]
