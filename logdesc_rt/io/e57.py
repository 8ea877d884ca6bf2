"""E57 point clouds through pye57 (optional: ``pip install "logdesc-rt[e57]"``).

pye57 (MIT) wraps libE57Format (BSL-1.0), the reference implementation of ASTM E2807: an
XML tree plus binary sections in 1 KiB pages, each with a CRC-32, compressed vectors for the
points. Far too much to write ourselves for one reader; pye57 ships wheels with the library
inside, so it is an optional extra.

Reading: every scan of the file (an E57 file holds one or more ``data3D`` scans, each with
its own pose), Cartesian or spherical, with its pose applied, so all points land in the file's
frame; points flagged invalid are dropped; the scans are concatenated in file order.
Writing: one scan, plus ``intensity`` and ``red``, ``green``, ``blue`` (0-255) when given; E57
has no field for other per-point attributes, so those are refused. pye57 writes coordinates
in single precision, so they are stored relative to the cloud's centre, which the scan's pose
holds in double precision: coordinates read back within about 6e-8 of the cloud's extent
(not bit for bit), wherever the cloud sits.

Errors are raised as plain exceptions here; :mod:`logdesc_rt.io` turns them into
:class:`~logdesc_rt.errors.PointCloudFileError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._common import MissingLibraryError

MAGIC = b"ASTM-E57"
EXTRA = "e57"
INSTALL_HINT = 'pip install "logdesc-rt[e57]" (pye57)'
ATTRIBUTE_FIELDS = {"intensity": "intensity", "red": "colorRed", "green": "colorGreen", "blue": "colorBlue"}


def _pye57():
    try:
        import pye57
    except ImportError as error:
        raise MissingLibraryError(f"E57 files need pye57, which is not installed: {INSTALL_HINT}") from error
    return pye57


def check_available() -> None:
    """Raise :class:`MissingLibraryError` unless pye57 is installed."""
    _pye57()


def _scans(path: Path, **fields) -> list[dict]:
    """read_scan's dict of every scan (pose applied, invalid points dropped)."""
    with path.open("rb") as file:
        signature = file.read(len(MAGIC))
    if signature != MAGIC:
        raise ValueError(f"not an E57 file (it starts with {signature!r}, not {MAGIC!r})")
    pye57 = _pye57()
    try:
        reader = pye57.E57(str(path), mode="r")
    except Exception as error:  # libE57's E57Exception, or RuntimeError from the binding
        raise ValueError(f"corrupt E57 file: {error}") from error
    try:
        return [
            reader.read_scan(index, ignore_missing_fields=True, transform=True, **fields)
            for index in range(reader.scan_count)
        ]
    except Exception as error:
        raise ValueError(f"corrupt E57 scan data: {error}") from error
    finally:
        reader.close()


def read_xyz(path: Path) -> np.ndarray:
    """x, y, z of every scan in an E57 file, in the file's frame: (N, 3) float64, N may be 0.

    Raises:
        MissingLibraryError: pye57 is not installed.
        ValueError: not an E57 file, or corrupt content (libE57 checks every page's CRC).
    """
    parts = [np.column_stack([scan["cartesianX"], scan["cartesianY"], scan["cartesianZ"]]) for scan in _scans(path)]
    if not parts:
        return np.empty((0, 3))
    return np.concatenate(parts).astype(np.float64)


def read_attributes(path: Path) -> dict[str, np.ndarray]:
    """``intensity`` and ``red``, ``green``, ``blue`` when every scan of the file has them."""
    scans = _scans(path, intensity=True, colors=True)
    attributes = {}
    for name, field in ATTRIBUTE_FIELDS.items():
        if scans and all(field in scan for scan in scans):
            attributes[name] = np.concatenate([np.asarray(scan[field]) for scan in scans])
    return attributes


def write(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> None:
    """Write (N, 3) float64 ``points`` as one E57 scan (pose: a shift to the centre), with ``intensity`` and
    ``red`` / ``green`` / ``blue`` when given.

    Raises:
        MissingLibraryError: pye57 is not installed.
        ValueError: an attribute E57 has no field for, or colours outside 0-255.
        OSError: the file cannot be written.
    """
    other = [name for name in attributes if name not in ATTRIBUTE_FIELDS]
    if other:
        raise ValueError(
            f"E57 has no field for attribute(s) {', '.join(other)}; it keeps intensity and red, green, blue only "
            "(write PLY, PCD, LAS, XYZ/TXT/CSV or NPY to keep them)"
        )
    colours = [name for name in ("red", "green", "blue") if name in attributes]
    if colours and len(colours) != 3:
        raise ValueError("E57 colours need red, green and blue together")
    # pye57 stores coordinates in single precision: store them relative to the cloud's centre,
    # which goes (in double precision) into the scan's pose.
    centre = (points.min(axis=0) + points.max(axis=0)) / 2.0
    local = points - centre
    data = {"cartesianX": local[:, 0].copy(), "cartesianY": local[:, 1].copy(), "cartesianZ": local[:, 2].copy()}
    for name in colours:
        values = np.asarray(attributes[name])
        if values.min() < 0 or values.max() > 255 or not np.array_equal(values, np.round(values)):
            raise ValueError(f"attribute {name!r}: E57 colours are integers 0-255")
        data[ATTRIBUTE_FIELDS[name]] = values.astype(np.uint8)
    if "intensity" in attributes:
        data["intensity"] = np.asarray(attributes["intensity"], dtype=np.float64)
    pye57 = _pye57()
    if path.exists():
        path.unlink()  # an existing file is replaced, as the other formats do
    writer = pye57.E57(str(path), mode="w")
    try:
        writer.write_scan_raw(data, name=path.stem, rotation=np.array([1.0, 0.0, 0.0, 0.0]), translation=centre)
    finally:
        writer.close()
