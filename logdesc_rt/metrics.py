"""Registration and matching metrics as the paper reports them (DCP's and MDGAT's definitions).

Registration (paper Tables 1-5, following DCP), over B test pairs:

- RMSE(R), MAE(R): root mean square and mean absolute difference of the three Euler angles
  (degrees, scipy ``as_euler('zyx')`` as in DCP) between predicted and true rotation,
  averaged over all 3 B angle differences.
- RMSE(t), MAE(t): the same over the 3 B translation components (cloud units).
- L_R: isotropic rotation error ``arccos((trace(R_gt^T R) - 1) / 2)`` in degrees; L_t:
  ``||t - t_gt||``; L_RMSE: mean distance between the source points moved by the predicted
  and by the true transform. Each averaged over the pairs.

Matching (MDGAT): see :func:`matching_metrics`.

Transformations are (4, 4) (or (B, 4, 4)) and map source into target: ``y = R x + t``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation


def _as_matrices(array, trailing: tuple[int, ...], name: str) -> np.ndarray:
    """``array`` as float64 with the given trailing shape, finite; raises ValueError."""
    matrices = np.asarray(array, dtype=np.float64)
    if matrices.ndim < len(trailing) or matrices.shape[matrices.ndim - len(trailing):] != trailing:
        raise ValueError(f"{name}: shape {matrices.shape} does not end in {trailing}")
    if not np.all(np.isfinite(matrices)):
        raise ValueError(f"{name}: contains NaN or inf")
    return matrices


def euler_angles_deg(rotations) -> np.ndarray:
    """Euler angles (degrees) of rotation matrices in DCP's convention.

    Args:
        rotations: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) float64: scipy ``Rotation.from_matrix(R).as_euler('zyx', degrees=True)``,
        i.e. [angle about z, about y, about x] of the intrinsic z-y-x sequence.
    """
    matrices = _as_matrices(rotations, (3, 3), "rotations")
    batch_shape = matrices.shape[:-2]
    angles = Rotation.from_matrix(matrices.reshape(-1, 3, 3)).as_euler("zyx", degrees=True)
    return angles.reshape(*batch_shape, 3)


def rotation_error_deg(rotation_pred, rotation_gt) -> np.ndarray:
    """Isotropic rotation error (the paper's L_R), in degrees.

    Args:
        rotation_pred, rotation_gt: (..., 3, 3) rotation matrices (broadcastable).

    Returns:
        (...) float64 in [0, 180]: ``arccos((trace(R_gt^T R_pred) - 1) / 2)``, the cosine
        clipped to [-1, 1] so rounding cannot produce NaN.
    """
    predicted = _as_matrices(rotation_pred, (3, 3), "rotation_pred")
    truth = _as_matrices(rotation_gt, (3, 3), "rotation_gt")
    trace = np.sum(truth * predicted, axis=(-2, -1))  # trace(A^T B) = sum_ij A_ij B_ij
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def translation_error(translation_pred, translation_gt) -> np.ndarray:
    """Euclidean translation error ``||t_pred - t_gt||`` (the paper's L_t), cloud units.

    Args:
        translation_pred, translation_gt: (..., 3) (broadcastable).

    Returns:
        (...) float64.
    """
    predicted = _as_matrices(translation_pred, (3,), "translation_pred")
    truth = _as_matrices(translation_gt, (3,), "translation_gt")
    return np.linalg.norm(predicted - truth, axis=-1)


def transformed_source_rmse(source, transformation_pred, transformation_gt) -> np.ndarray | float:
    """The paper's L_RMSE: mean distance between source points moved by two transforms.

    Despite the name (the paper's), this is the *mean* Euclidean distance
    ``mean_i ||(R_p x_i + t_p) - (R_g x_i + t_g)||``, not a root mean square.

    Args:
        source: (N, 3) points with (4, 4) transforms, or (B, N, 3) with (B, 4, 4).
        transformation_pred: predicted transform(s), source -> target.
        transformation_gt: true transform(s).

    Returns:
        float for one pair, (B,) float64 for a batch; cloud units.
    """
    points = _as_matrices(source, (3,), "source")
    predicted = _as_matrices(transformation_pred, (4, 4), "transformation_pred")
    truth = _as_matrices(transformation_gt, (4, 4), "transformation_gt")
    if points.ndim < 2 or points.shape[:-2] != predicted.shape[:-2] or predicted.shape != truth.shape:
        raise ValueError(
            f"transformed_source_rmse: source {points.shape} needs transforms of shape "
            f"{points.shape[:-2] + (4, 4)}; got {predicted.shape} and {truth.shape}"
        )
    difference = predicted - truth  # (x moved by T_p) - (x moved by T_g) = dR x + dt
    offsets = np.einsum("...ij,...nj->...ni", difference[..., :3, :3], points) + difference[..., None, :3, 3]
    distances = np.linalg.norm(offsets, axis=-1).mean(axis=-1)
    return float(distances) if distances.ndim == 0 else distances


def twin_distance(shape, transformation_pred, transformation_gt) -> float:
    """How far apart two poses put a whole object, up to the object's own symmetries.

    The mean two-sided closest-point distance between ``shape`` moved by the prediction and
    moved by the truth, over the shape's radius (largest distance from its centroid). Unlike
    :func:`transformed_source_rmse` it pairs each point with the *nearest* point of the other
    copy, so a pose that differs from the truth by a symmetry of the shape (a bottle turned
    about its axis, a table by a half-turn) scores about the sampling's spacing, while a pose
    that moves the object visibly scores the size of that motion. The pose estimation
    literature's ADD-S, made two-sided and relative (``benchmarks/results/symmetry_twins``).

    Args:
        shape: (P, 3) points of the complete object in the source frame (P of several
            thousand; P >= 2, not all equal).
        transformation_pred, transformation_gt: (4, 4) source -> target transforms.

    Returns:
        float >= 0: that distance in units of the shape's radius.
    """
    from pykdtree.kdtree import KDTree  # deferred: the other metrics need no k-d tree

    points = _as_matrices(shape, (3,), "shape")
    if points.ndim != 2 or len(points) < 2:
        raise ValueError(f"twin_distance: shape must be (P, 3) with P >= 2, got {points.shape}")
    radius = float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())
    if radius == 0.0:
        raise ValueError("twin_distance: the shape's points are all equal")
    predicted = _as_matrices(transformation_pred, (4, 4), "transformation_pred")
    truth = _as_matrices(transformation_gt, (4, 4), "transformation_gt")
    moved_pred = points @ predicted[:3, :3].T + predicted[:3, 3]
    moved_truth = points @ truth[:3, :3].T + truth[:3, 3]
    forward, _ = KDTree(moved_truth).query(moved_pred, k=1)
    backward, _ = KDTree(moved_pred).query(moved_truth, k=1)
    return float((forward.mean() + backward.mean()) / (2.0 * radius))


def _wrap_degrees(angles: np.ndarray) -> np.ndarray:
    """Angles mapped into [-180, 180)."""
    return (angles + 180.0) % 360.0 - 180.0


def registration_metrics(
    transformations_pred,
    transformations_gt,
    sources: np.ndarray | Sequence[np.ndarray] | None = None,
) -> dict[str, float]:
    """The paper's registration metrics over a set of test pairs (DCP's definitions).

    Args:
        transformations_pred: (B, 4, 4) (or (4, 4)) predicted transforms, source -> target.
        transformations_gt: same shape, true transforms.
        sources: optional source clouds for L_RMSE: a (B, N, 3) array or B arrays (N_b, 3).

    Returns:
        dict of floats:
        ``rmse_r``, ``mae_r``: over the 3 B Euler-angle differences (degrees, 'zyx'). Each
        difference is wrapped into [-180, 180), so 179 vs -179 counts as 2 degrees; DCP does
        not wrap, which only matters when an angle crosses +-180 (never within ModelNet40's
        45-degree range).
        ``rmse_t``, ``mae_t``: over the 3 B translation-component differences.
        ``l_r`` (degrees), ``l_t``, ``l_rmse``: means over pairs of :func:`rotation_error_deg`,
        :func:`translation_error` and :func:`transformed_source_rmse`; ``l_rmse`` is NaN
        when ``sources`` is None.
    """
    predicted = _as_matrices(transformations_pred, (4, 4), "transformations_pred").reshape(-1, 4, 4)
    truth = _as_matrices(transformations_gt, (4, 4), "transformations_gt").reshape(-1, 4, 4)
    if predicted.shape != truth.shape:
        raise ValueError(
            f"registration_metrics: {predicted.shape[0]} predicted but {truth.shape[0]} true transforms"
        )
    angle_differences = _wrap_degrees(
        euler_angles_deg(predicted[:, :3, :3]) - euler_angles_deg(truth[:, :3, :3])
    )
    translation_differences = predicted[:, :3, 3] - truth[:, :3, 3]
    if sources is None:
        l_rmse = float("nan")
    else:
        if len(sources) != len(predicted):
            raise ValueError(
                f"registration_metrics: {len(sources)} source clouds for {len(predicted)} transforms"
            )
        l_rmse = float(
            np.mean(
                [
                    transformed_source_rmse(cloud, predicted[index], truth[index])
                    for index, cloud in enumerate(sources)
                ]
            )
        )
    return {
        "rmse_r": float(np.sqrt(np.mean(angle_differences**2))),
        "mae_r": float(np.mean(np.abs(angle_differences))),
        "rmse_t": float(np.sqrt(np.mean(translation_differences**2))),
        "mae_t": float(np.mean(np.abs(translation_differences))),
        "l_r": float(np.mean(rotation_error_deg(predicted[:, :3, :3], truth[:, :3, :3]))),
        "l_t": float(np.mean(translation_error(predicted[:, :3, 3], truth[:, :3, 3]))),
        "l_rmse": l_rmse,
    }


# A pair counts as registered when both errors are below these (the benchmarks' and the
# evaluation's criterion; the translation relative to the object's radius).
SUCCESS_ROTATION_DEG = 5.0
SUCCESS_TRANSLATION_FRACTION = 0.05

# A ground-truth label for a point that is neither matched nor unmatched (two samplings of one
# surface: near a counterpart, but not one-to-one; logdesc_rt.synthetic's resampled pairs).
IGNORED = -2


def _as_match_vector(matches, name: str, allow_ignored: bool = False) -> np.ndarray:
    array = np.asarray(matches)
    if array.ndim != 1 or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"{name}: expected a 1-D integer array, got shape {array.shape} dtype {array.dtype}")
    lowest = IGNORED if allow_ignored else -1
    if np.any(array < lowest):
        allowed = f">= 0, -1 (unmatched) or {IGNORED} (ignored)" if allow_ignored else ">= 0 or -1 (unmatched)"
        raise ValueError(f"{name}: entries must be a target index {allowed}")
    return array.astype(np.int64)


def matching_metrics(pred_match, gt_match) -> dict[str, float]:
    """Matching precision, accuracy and recall as MDGAT (and the paper's Table 1) define them.

    For each of the M source points: ``pred_match[i]`` is the predicted target index, or -1
    when the point is left unmatched (dustbin); ``gt_match[i]`` is its true counterpart, or
    -1 when it has none (outside the overlap), or ``IGNORED`` (-2) when it is unlabelled: such
    points count in none of the three ratios. A predicted match is *correct* when it equals
    the true counterpart.

    - precision = correct predicted matches / predicted matches (``pred >= 0``)
    - recall = correct predicted matches / true matches (``gt >= 0``)
    - accuracy = (correct predicted matches + points correctly left unmatched, i.e.
      ``pred == gt == -1``) / M

    Args:
        pred_match: (M,) int, target index or -1.
        gt_match: (M,) int, target index, -1 or ``IGNORED``.

    Returns:
        dict with floats ``precision``, ``accuracy``, ``recall`` in [0, 1]. A ratio whose
        denominator is 0 (nothing predicted, no true matches, M = 0) is NaN, so averaging
        with ``np.nanmean`` skips it instead of counting it as 0 or 1.
    """
    predicted = _as_match_vector(pred_match, "pred_match")
    truth = _as_match_vector(gt_match, "gt_match", allow_ignored=True)
    if predicted.shape != truth.shape:
        raise ValueError(f"matching_metrics: pred_match {predicted.shape} and gt_match {truth.shape} differ")
    labelled = truth != IGNORED
    predicted, truth = predicted[labelled], truth[labelled]
    matched = predicted >= 0
    correct = int(np.count_nonzero(matched & (predicted == truth)))
    correctly_unmatched = int(np.count_nonzero(~matched & (truth == -1)))

    def ratio(numerator: int, denominator: int) -> float:
        return numerator / denominator if denominator else float("nan")

    return {
        "precision": ratio(correct, int(np.count_nonzero(matched))),
        "accuracy": ratio(correct + correctly_unmatched, len(predicted)),
        "recall": ratio(correct, int(np.count_nonzero(truth >= 0))),
    }
