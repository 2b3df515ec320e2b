"""jax-md's three list layouts, shared by the backends that write them and
the energies and pairs that read them: Dense rows to edges on the GPU
(`jaxrt.layouts.edge_kernel`) and per-edge sums (`jaxrt.layouts.edges`)."""
