"""numba kernels used by the matching stages (each with a pure-numpy reference in the tests)."""


def prange_only() -> dict:
    """``parallel=`` option of a kernel whose only parallel loops are its ``prange`` loops.

    With ``parallel=True`` numba also turns every array allocation or expression in the kernel
    (``np.full``, ``np.zeros``, copies, sums) into a parallel loop of its own: each one is
    compiled separately (about a quarter of a second of the first run each) and launched on the
    threads for microseconds of work. (A fresh dict per call: numba consumes it.)
    """
    return {"comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False, "numpy": False,
            "stencil": False, "fusion": False, "prange": True}
