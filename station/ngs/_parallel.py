"""The numba parallel options every training kernel (projection, rasteriser, SSIM) compiles with."""

from __future__ import annotations

from numba.core.cpu_options import ParallelOptions

# parallel with prange alone: the other passes make each np.zeros a gufunc of its own, seconds of compile for
# microseconds of work. An options object, not a dict: numba empties a dict as it reads it, and a second signature
# would get them all.
PRANGE_ONLY = ParallelOptions({"comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False,
                               "numpy": False, "stencil": False, "fusion": False})
