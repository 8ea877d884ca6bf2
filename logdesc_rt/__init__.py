"""logdesc-rt: LoGDesc point-cloud registration on the CPU, without PyTorch.

    import logdesc_rt
    result = logdesc_rt.register(source, target)   # (N, 3) arrays or file paths
    result.transformation                          # 4 x 4, source -> target frame
"""

from __future__ import annotations

from . import errors
from .align import AlignConfig, AlignmentResult, align
from .batch import register_many
from .config import GeometryConfig, MatchingConfig, NormalizationConfig, RuntimeConfig
from .geometry import PointGeometry, compute_geometry
from .io import read_point_cloud, write_point_cloud
from .registration import (
    Descriptors,
    PairMatches,
    PreparedPair,
    Registrar,
    RegistrationResult,
    describe,
    register,
)

__version__ = "0.2.0"

__all__ = [
    "AlignConfig",
    "AlignmentResult",
    "Descriptors",
    "GeometryConfig",
    "MatchingConfig",
    "NormalizationConfig",
    "PairMatches",
    "PointGeometry",
    "PreparedPair",
    "Registrar",
    "RegistrationResult",
    "RuntimeConfig",
    "align",
    "compute_geometry",
    "describe",
    "errors",
    "read_point_cloud",
    "register",
    "register_many",
    "write_point_cloud",
]
