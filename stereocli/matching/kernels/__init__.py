"""numba kernels used by the matching stages, each with a pure-numpy reference in the tests.

The kernel modules take their decorators and threads from :mod:`stereocli.runtime` (numba,
started on first use; the kernels compiled ahead of time).
"""
