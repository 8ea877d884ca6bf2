"""Stanford Bunny scans with their ground-truth poses, for tests (``../shared/data``)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from logdesc_rt.io import read_point_cloud


def scan_poses(bunny_dir: Path) -> dict[str, np.ndarray]:
    """Scan file name -> (4, 4) pose placing the scan in the common frame (metres).

    ``bun.conf`` lines read ``bmesh NAME tx ty tz qx qy qz qw``; the rotation is the
    quaternion with the sign of ``qw`` flipped (verified in the data README).
    """
    poses = {}
    for line in (bunny_dir / "bun.conf").read_text().splitlines():
        words = line.split()
        if not words or words[0] != "bmesh":
            continue
        tx, ty, tz, qx, qy, qz, qw = map(float, words[2:9])
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat([qx, qy, qz, -qw]).as_matrix()
        pose[:3, 3] = [tx, ty, tz]
        poses[words[1]] = pose
    return poses


@lru_cache(maxsize=16)
def _read(path: str) -> np.ndarray:
    points = read_point_cloud(path)
    points.setflags(write=False)
    return points


def bunny_pair(
    data_root: Path, source: str, target: str, points: int | None = None, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two real scans in their own frames (metres) and the true pose source -> target.

    Args:
        data_root: the shared data folder (``tests/conftest.py``'s ``shared_data``).
        source, target: scan names, e.g. "bun000".
        points: keep this many points of each scan, drawn uniformly without replacement with
            ``default_rng(seed)``; None keeps all (~40k).

    Returns:
        source (N, 3), target (M, 3) float64 and the (4, 4) transform ``inv(T_target) @ T_source``.
    """
    folder = data_root / "stanford_bunny" / "data"
    poses = scan_poses(folder)
    clouds = []
    generator = np.random.default_rng(seed)
    for name in (source, target):
        cloud = _read(str(folder / f"{name}.ply"))
        if points is not None and points < len(cloud):
            cloud = cloud[np.sort(generator.choice(len(cloud), points, replace=False))]
        clouds.append(np.array(cloud))
    truth = np.linalg.inv(poses[f"{target}.ply"]) @ poses[f"{source}.ply"]
    return clouds[0], clouds[1], truth
