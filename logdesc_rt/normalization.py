"""Mapping a pair of user clouds into the network's frame, and the pose back.

The network is trained on objects inside the unit sphere; users bring metre-scale scans placed
anywhere. Both clouds are mapped by similarity transforms that share one scale (so a rigid
motion stays rigid):

    x' = (x - c_source) / s        y' = (y - c_target) / s

with c the centroid of each cloud and s chosen so that the larger of the two clouds' radii
(largest distance of a point from its own centroid) becomes ``target_radius``. Centring each
cloud on its own centroid removes most of the translation before the network sees the pair.
Stray points (:mod:`.outliers`: far from every surface) count in neither the centroid nor the
radius, so one return 100 radii away no longer shrinks the object to a speck. Training applies
the very same mapping to its pairs, so the network never sees anything else.

If the network's pose maps x' to y' = R x' + t', then in the user's frame

    y = R x + (s t' + c_target - R c_source),

which :meth:`PairNormalization.pose_to_user_frame` applies exactly (no approximation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import NormalizationConfig
from .outliers import stray_point_mask
from .validation import as_points


def centre_and_radius(
    points: np.ndarray, config: NormalizationConfig = NormalizationConfig()
) -> tuple[np.ndarray, float]:
    """The centroid (3,) of (N, 3) ``points`` and their radius about it (the largest distance),
    stray points (``config.stray_*``) left out of both."""
    kept = points[~stray_point_mask(points, config)]
    centre = kept.mean(axis=0)
    return centre, float(np.linalg.norm(kept - centre, axis=1).max())


@dataclass(frozen=True)
class PairNormalization:
    """The similarity transforms of one (source, target) pair.

    Attributes:
        source_centre: (3,) centroid of the source, user units.
        target_centre: (3,) centroid of the target, user units.
        scale: user units per network unit (s above), > 0.
    """

    source_centre: np.ndarray
    target_centre: np.ndarray
    scale: float

    @classmethod
    def fit(
        cls, source, target, config: NormalizationConfig = NormalizationConfig()
    ) -> "PairNormalization":
        """Choose the centres and the shared scale for a pair of (N, 3) / (M, 3) clouds.

        Stray points (``config.stray_*``) are left out of both the centres and the radius.
        """
        source_centre, source_radius = centre_and_radius(as_points(source, name="source"), config)
        target_centre, target_radius = centre_and_radius(as_points(target, name="target"), config)
        return cls.from_extents(source_centre, source_radius, target_centre, target_radius, config)

    @classmethod
    def from_extents(
        cls, source_centre: np.ndarray, source_radius: float, target_centre: np.ndarray, target_radius: float,
        config: NormalizationConfig = NormalizationConfig(),
    ) -> "PairNormalization":
        """The pair's transforms from each cloud's :func:`centre_and_radius` (what :meth:`fit`
        does after computing them; the runtime computes them for the two clouds at once)."""
        radius = max(source_radius, target_radius)
        # A single point (radius 0) has no scale; keep 1 rather than divide by zero. Callers that
        # need geometry reject such clouds themselves.
        scale = float(radius / config.target_radius) if radius > 0 else 1.0
        return cls(source_centre=source_centre, target_centre=target_centre, scale=scale)

    def source_to_network(self, source: np.ndarray) -> np.ndarray:
        """(N, 3) source points, user units -> network units."""
        return (np.asarray(source, dtype=np.float64) - self.source_centre) / self.scale

    def target_to_network(self, target: np.ndarray) -> np.ndarray:
        """(M, 3) target points, user units -> network units."""
        return (np.asarray(target, dtype=np.float64) - self.target_centre) / self.scale

    def length_to_network(self, length: float) -> float:
        """A distance in user units (e.g. an inlier threshold) -> network units."""
        return length / self.scale

    def pose_to_user_frame(self, network_pose: np.ndarray) -> np.ndarray:
        """(4, 4) pose between the normalised clouds -> (4, 4) pose between the user's clouds."""
        rotation = network_pose[:3, :3]
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = self.scale * network_pose[:3, 3] + self.target_centre - rotation @ self.source_centre
        return pose

    def pose_to_network_frame(self, user_pose: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`pose_to_user_frame` (used to express ground truth for training)."""
        rotation = user_pose[:3, :3]
        pose = np.eye(4)
        pose[:3, :3] = rotation
        pose[:3, 3] = (user_pose[:3, 3] - self.target_centre + rotation @ self.source_centre) / self.scale
        return pose
