"""The one decorator for the package's compiled kernels (numba, no compiler needed at install).

Kernels are compiled on their first call and cached on disk: next to the source when the
package directory is writable, else in numba's user-wide cache (``NUMBA_CACHE_DIR`` or the
user's cache directory). Where no cache directory can be written at all, the kernels are
compiled in every process instead (about a second per process); nothing fails.
"""

from __future__ import annotations

from numba import njit


def jit(function):
    """``numba.njit(cache=True, nogil=True)``, or without the cache where no cache directory is
    writable. ``nogil``: the runtime computes the geometry of two clouds in two threads, which
    then run at once instead of taking turns on the interpreter lock."""
    try:
        return njit(cache=True, nogil=True)(function)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True)(function)
