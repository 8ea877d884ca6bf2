import sys; sys.path.insert(0, ".")
import numpy as np
from tests.test_verification import _plate_with_a_ridge, _rigid
from scipy.spatial.transform import Rotation
from logdesc_rt.verification import PoseVerifier
from logdesc_rt.config import VerificationConfig
from logdesc_rt.metrics import rotation_error_deg
for sp, tp in ((512, 2048), (768, 2048), (1000, 4000), (2000, 8000), (512, 8000)):
    out = []
    for axis_deg in (20.0, 65.0, 140.0):
        rng = np.random.default_rng(3)
        source = _plate_with_a_ridge(rng)
        truth = _rigid([0.3, -0.5, 0.9], [0.4, -0.2, 0.1])
        target = source @ truth[:3, :3].T + truth[:3, 3] + rng.normal(scale=0.003, size=source.shape)
        axis = np.array([np.cos(np.radians(axis_deg)), np.sin(np.radians(axis_deg)), 0.0])
        centre = source.mean(axis=0)
        flip = np.eye(4); flip[:3, :3] = Rotation.from_rotvec(np.pi * axis).as_matrix(); flip[:3, 3] = centre - flip[:3, :3] @ centre
        matched = source[:50]
        args = (source, target, matched, matched @ truth[:3, :3].T + truth[:3, 3], np.full(50, 0.5), 1.0)
        best = PoseVerifier(*args, VerificationConfig(source_points=sp, target_points=tp)).verify([("fsr", truth @ flip)]).best
        out.append((best.estimators[0], round(float(rotation_error_deg(best.verified_transformation[:3, :3], truth[:3, :3])), 1)))
    print(sp, tp, out)
