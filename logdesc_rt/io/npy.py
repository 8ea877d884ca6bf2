"""NPY: an (N, 3) or (N, >3) numeric array (first three columns), never unpickled."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import file_error


def read(path: Path) -> np.ndarray:
    """First three columns of an (N, >=3) array: (N, 3) in the file's dtype."""
    # Memory-mapping checks the header's shape against the file size before anything is
    # allocated, so a corrupt header cannot ask for terabytes; allow_pickle=False keeps
    # object arrays (arbitrary code on load) out.
    try:
        loaded = np.load(path, mmap_mode="r", allow_pickle=False)
    except OSError:
        raise
    except Exception as error:
        # The header is a Python literal parsed with tokenize and ast: on corrupt bytes they
        # raise SyntaxError, tokenize.TokenError, RecursionError... beyond PARSE_ERRORS.
        raise file_error(path, f"cannot parse as NPY: {error}") from error
    if not isinstance(loaded, np.ndarray):  # an .npz archive under an .npy name
        loaded.close()
        raise file_error(path, "is an .npz archive, not a single .npy array")
    if loaded.ndim != 2 or loaded.shape[1] < 3:
        raise file_error(path, f"array has shape {loaded.shape}; expected (N, 3) or (N, >3) with x, y, z first")
    if loaded.dtype.fields is not None:
        raise file_error(path, f"array has structured dtype {loaded.dtype}; expected plain numbers")
    return np.array(loaded[:, :3])  # copy out of the memory map


def write(path: Path, points: np.ndarray) -> None:
    # An open file, because np.save(name) appends ".npy" to a name ending in ".NPY".
    with path.open("wb") as file:
        np.save(file, points, allow_pickle=False)


def write_with_attributes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    table = np.column_stack([points, *[np.asarray(v, dtype=np.float64) for v in attributes.values()]])
    with path.open("wb") as file:
        np.save(file, table, allow_pickle=False)
