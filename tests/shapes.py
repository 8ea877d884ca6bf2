"""Synthetic shapes with analytic geometry, for tests."""

from __future__ import annotations

import numpy as np


def fibonacci_sphere(count: int, radius: float = 1.0) -> np.ndarray:
    """(count, 3) nearly uniform points on a sphere centred at the origin."""
    index = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * index / count)
    azimuth = np.pi * (1.0 + 5.0**0.5) * index
    return radius * np.stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1
    )


def random_rigid_transform(rng: np.random.Generator, translation_scale: float = 1.0) -> np.ndarray:
    """(4, 4) uniformly random rotation and a Gaussian translation."""
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    pose[:3, 3] = rng.normal(scale=translation_scale, size=3)
    return pose


def twisted_bar(count: int, turns: float = 1.0, seed: int = 0) -> np.ndarray:
    """(count, 3) seeded points on the surface of a 0.8 x 0.4 x 2 bar twisted by ``turns`` full
    turns about its long axis (z): a chiral shape, whose mirror image twists the other way,
    at every point."""
    rng = np.random.default_rng(seed)
    half_width, half_height = 0.4, 0.2
    side = rng.integers(0, 4, count)
    across = rng.uniform(-1.0, 1.0, count)
    x = np.where(side < 2, np.where(side == 0, -half_width, half_width), across * half_width)
    y = np.where(side >= 2, np.where(side == 2, -half_height, half_height), across * half_height)
    z = rng.uniform(-1.0, 1.0, count)
    angle = turns * np.pi * z  # z runs over 2 units: `turns` full turns in all
    return np.stack([np.cos(angle) * x - np.sin(angle) * y, np.sin(angle) * x + np.cos(angle) * y, z], axis=1)
