"""Scan poses of a Stanford 3D Scanning Repository scan set (its ``.conf`` file).

The repository's range-scan sets (Bunny, Dragon, Happy Buddha, Armadillo) place each scan in a
common frame with a ``.conf`` file written by its alignment tool (scanalyze). Its lines read

    camera tx ty tz qx qy qz qw          (a viewpoint: ignored)
    bmesh NAME tx ty tz qx qy qz qw      (the scan NAME's pose)

The quaternion aligns the scans only with the sign of its scalar part flipped (checked on the
Bunny against the scans' overlap; ``../shared/data/README.md``): a point p of scan NAME lies at
``R p + t`` in the common frame, ``R = Rotation.from_quat([qx, qy, qz, -qw])`` (SciPy's scalar-
last order).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ._common import check_readable_file, file_error, read_text


def read_stanford_conf(path) -> dict[str, np.ndarray]:
    """Scan file name -> (4, 4) float64 pose mapping the scan's points into the common frame.

    Args:
        path: the scan set's ``.conf`` file.

    Returns:
        One pose per ``bmesh`` line, keyed by the file name as written (e.g. ``"bun000.ply"``),
        in the file's units (metres for the Stanford scans).

    Raises:
        PointCloudFileError: the file is missing or unreadable, a ``bmesh`` line lacks its
            seven numbers or holds a non-finite or zero quaternion, a name repeats, or no scan
            is listed; the message names the file and the line.
    """
    path = Path(path)
    check_readable_file(path)
    poses: dict[str, np.ndarray] = {}
    for number, line in enumerate(read_text(path).splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0] != "bmesh":
            continue
        try:
            name, values = fields[1], [float(value) for value in fields[2:9]]
        except (IndexError, ValueError) as error:
            raise file_error(path, f"line {number}: expected 'bmesh NAME tx ty tz qx qy qz qw'") from error
        if len(values) != 7 or not all(math.isfinite(value) for value in values):
            raise file_error(path, f"line {number}: expected seven finite numbers after 'bmesh {name}'")
        if name in poses:
            raise file_error(path, f"line {number}: scan {name} is listed twice")
        tx, ty, tz, qx, qy, qz, qw = values
        if math.hypot(qx, qy, qz, qw) < 1e-12:
            raise file_error(path, f"line {number}: the quaternion of {name} is zero")
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat([qx, qy, qz, -qw]).as_matrix()
        pose[:3, 3] = (tx, ty, tz)
        poses[name] = pose
    if not poses:
        raise file_error(path, "no 'bmesh' line: not a scan set's .conf file")
    return poses
