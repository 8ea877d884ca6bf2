"""Stanford Bunny scans with their ground-truth poses, for tests (``../shared/data``)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from logdesc_rt.io import read_point_cloud, read_stanford_conf


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
    poses = read_stanford_conf(folder / "bun.conf")
    clouds = []
    generator = np.random.default_rng(seed)
    for name in (source, target):
        cloud = _read(str(folder / f"{name}.ply"))
        if points is not None and points < len(cloud):
            cloud = cloud[np.sort(generator.choice(len(cloud), points, replace=False))]
        clouds.append(np.array(cloud))
    truth = np.linalg.inv(poses[f"{target}.ply"]) @ poses[f"{source}.ply"]
    return clouds[0], clouds[1], truth
