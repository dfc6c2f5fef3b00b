"""The numba parallel options every training kernel (projection, rasteriser, SSIM) compiles with, and the
pipeline their per-chunk bodies compile with."""

from __future__ import annotations

from numba.core.compiler import Compiler
from numba.core.cpu_options import ParallelOptions

# parallel with prange alone: the other passes make each np.zeros a gufunc of its own, seconds of compile for
# microseconds of work. An options object, not a dict: numba empties a dict as it reads it, and a second signature
# would get them all.
PRANGE_ONLY = ParallelOptions({"comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False,
                               "numpy": False, "stencil": False, "fusion": False})


class NoAlias(Compiler):
    """numba's pipeline with LLVM `noalias` on array arguments, which numba gives a prange body it finds free of
    aliases but offers no option for. No array a chunk function writes overlaps another it gets; without the flag
    LLVM reloads inputs after every store."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.state.flags.noalias = True
