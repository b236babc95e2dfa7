"""numba kernels used by the matching stages (each with a pure-numpy reference in the tests)."""
