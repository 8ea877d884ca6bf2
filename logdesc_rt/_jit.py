"""The one decorator for the package's compiled kernels (numba, no compiler needed at install).

Kernels are compiled on their first call and cached on disk, in the user's cache directory
(numba's user-wide cache: ``$XDG_CACHE_HOME`` or ``~/.cache``, folder ``numba``), never inside
the installed package: files written there at run time would outlive ``pip uninstall`` and, left
behind in site-packages, shadow a later editable install of the package. Where that directory
cannot be written, numba's usual places are tried (``NUMBA_CACHE_DIR``, next to the source); where
none can be written, the kernels are compiled in every process instead (about 5 s); nothing fails.
"""

from __future__ import annotations

from pathlib import Path

from numba import njit

_PACKAGE_DIR = str(Path(__file__).resolve().parent)


def _cache_in_the_user_directory() -> None:
    """Put this package's kernels first in numba's list of cache locations: the user-wide one."""
    try:
        from numba.core.caching import CacheImpl, UserWideCacheLocator
    except ImportError:  # another numba layout: keep its defaults
        return

    class PackageKernelsLocator(UserWideCacheLocator):
        """numba's user-wide cache, for this package's source files only."""

        @classmethod
        def from_function(cls, py_func, py_file):
            if not str(Path(py_file).resolve()).startswith(_PACKAGE_DIR):
                return None
            return super().from_function(py_func, py_file)

    if not any(locator.__name__ == PackageKernelsLocator.__name__ for locator in CacheImpl._locator_classes):
        CacheImpl._locator_classes.insert(0, PackageKernelsLocator)


_cache_in_the_user_directory()


def jit(function=None, *, inline: bool = False):
    """``numba.njit(cache=True, nogil=True)``, or without the cache where no cache directory is
    writable. ``nogil``: the runtime computes the geometry of two clouds in two threads, which
    then run at once instead of taking turns on the interpreter lock. ``@jit(inline=True)``: a
    small helper compiled into each kernel that calls it (numba's ``inline="always"``), where a
    call per point would cost more than the helper's arithmetic."""
    options = {"nogil": True, **({"inline": "always"} if inline else {})}

    def compiled(function):
        try:
            return njit(cache=True, **options)(function)
        except RuntimeError:  # numba: "cannot cache function ...: no locator available"
            return njit(**options)(function)

    return compiled if function is None else compiled(function)
