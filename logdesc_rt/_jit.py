"""The one decorator for the package's compiled kernels (numba, no compiler needed at install).

Kernels are compiled on their first call and cached on disk: next to the source when the
package directory is writable, else in numba's user-wide cache (``NUMBA_CACHE_DIR`` or the
user's cache directory). Where no cache directory can be written at all, the kernels are
compiled in every process instead (about a second per process); nothing fails.
"""

from __future__ import annotations

from numba import njit


def jit(function):
    """``numba.njit(cache=True)``, or ``njit()`` where no cache directory is writable."""
    try:
        return njit(cache=True)(function)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit()(function)
