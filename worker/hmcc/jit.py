"""How hmcc compiles its inner loops: numba, cached on disk, without the GIL.

The stages work on a few hundred matches, where a numpy call costs 1-10 us whatever its size;
a compiled loop does the same work in a fraction of that. Compiled code is cached beside the
module (or in ``NUMBA_CACHE_DIR`` where that is not writable), so only the first process on a
machine pays the compilation (about 30 s for everything); it releases the GIL, so the threads
of the embedded queue run in parallel. ``error_model="numpy"``: a division by zero gives inf or
nan as in numpy, which the callers check, instead of raising.
"""

from __future__ import annotations

import numba

__all__ = ["compiled", "compiled_reassociating"]

compiled = numba.njit(cache=True, nogil=True, error_model="numpy")

#: The same, free to reorder sums (LLVM's ``reassoc`` and ``contract``: no NaN or infinity
#: assumptions): a 128-term dot product is then summed in SIMD lanes instead of one add after
#: another (about 10 times faster in the guided matcher), its last bits depending on the order.
compiled_reassociating = numba.njit(
    cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"}
)
