"""Pictures of a registration that tell right from wrong at a glance (optional: matplotlib).

matplotlib is not a run-time dependency: ``pip install matplotlib`` (or the ``plot`` extra,
``pip install "logdesc-rt[plot]"``) enables pictures.

Three panels: the clouds as given; the source moved by the pose, each point coloured by its
distance to the nearest target point (residual, clipped at the correspondence distance: a right
pose is dark where the clouds overlap, a wrong one is bright everywhere); and the learned
correspondences between the two clouds drawn side by side, green where the pose agrees with
the match, red where it does not. The title gives the verdict, confidence, fitness and inlier
RMSE (and the rotation error when the truth is known). Clouds are drawn from seeded subsets of
at most ``max_points`` points, so a 200k-point scan draws in about as long as a 1k-point one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pykdtree.kdtree import KDTree

from ..sampling import seeded_subset

DEFAULT_MAX_POINTS = 5000  # per cloud, drawn
MAX_LINES = 150  # correspondences drawn


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise RuntimeError("pictures need matplotlib: pip install matplotlib") from error
    return plt


def registration_title(result, transformation: np.ndarray, true_transformation: np.ndarray | None = None,
                       separator: str = "; ") -> str:
    """A picture's or a page's title, its parts joined by ``separator``: verdict, confidence, fitness, inlier RMSE,
    estimator and reason (from ``result``, if given), rotation and translation errors (if the
    truth is given). Empty when there is neither."""
    parts = []
    if result is not None:
        verdict = "SUCCESS" if result.success else "NOT A SUCCESS"
        rmse = "n/a" if not np.isfinite(result.inlier_rmse) else f"{result.inlier_rmse:.3g}"
        parts.append(f"{verdict} (confidence {result.confidence:.2f}), fitness {result.fitness:.2f}, "
                     f"inlier RMSE {rmse}, pose from {result.pose_estimator}")
        if result.reason:
            parts.append(result.reason)
    if true_transformation is not None:
        from ..metrics import rotation_error_deg

        error = float(rotation_error_deg(transformation[:3, :3], true_transformation[:3, :3]))
        offset = float(np.linalg.norm(transformation[:3, 3] - true_transformation[:3, 3]))
        parts.append(f"rotation error {error:.2f} deg, translation error {offset:.3g}")
    return separator.join(parts)


def matches_agreeing(source: np.ndarray, target: np.ndarray, transformation: np.ndarray, pairs: np.ndarray,
                     limit: float) -> np.ndarray:
    """(K,) bool: whether each match [source_index, target_index] agrees with the pose, i.e. the
    moved source point lies within 2 x ``limit`` (the correspondence distance) of its target point."""
    moved = source[pairs[:, 0]] @ transformation[:3, :3].T + transformation[:3, 3]
    return np.linalg.norm(moved - target[pairs[:, 1]], axis=1) < 2 * limit


def plot_registration(
    source: np.ndarray,
    target: np.ndarray,
    transformation: np.ndarray,
    path: str | Path,
    *,
    result=None,
    true_transformation: np.ndarray | None = None,
    max_points: int = DEFAULT_MAX_POINTS,
    seed: int = 0,
) -> None:
    """Write a picture (PNG, PDF or SVG by suffix) of a registration.

    Args:
        source, target: (N, 3) / (M, 3) clouds as given (user units).
        transformation: (4, 4) pose source -> target.
        path: the file to write.
        result: optional :class:`~logdesc_rt.registration.RegistrationResult`: adds the
            verdict, confidence, fitness, RMSE and the correspondence panel.
        true_transformation: optional (4, 4) ground truth: adds the rotation error to the title.
        max_points: per cloud, at most this many points are drawn (seeded subset).
        seed: seeds that subset and the choice of correspondences drawn.
    """
    plt = _pyplot()
    generator = np.random.default_rng(seed)
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    rotation, translation = transformation[:3, :3], transformation[:3, 3]
    aligned = source @ rotation.T + translation
    source_shown = seeded_subset(len(source), max_points, generator)
    target_shown = seeded_subset(len(target), max_points, generator)
    residual, _ = KDTree(target).query(aligned[source_shown], k=1)
    if result is not None:
        limit = float(result.max_correspondence_distance)
    else:
        limit = 0.05 * float(np.linalg.norm(target - target.mean(axis=0), axis=1).max())

    panels = 3 if result is not None and len(result.correspondences) else 2
    figure = plt.figure(figsize=(5.5 * panels, 5.5))
    before = figure.add_subplot(1, panels, 1, projection="3d")
    before.scatter(*target[target_shown].T, s=1, c="tab:blue", label="target")
    before.scatter(*source[source_shown].T, s=1, c="tab:orange", label="source")
    before.set_title("before")
    before.legend(loc="upper right", markerscale=6)
    _equal_axes(before, np.concatenate([target[target_shown], source[source_shown]]))

    after = figure.add_subplot(1, panels, 2, projection="3d")
    after.scatter(*target[target_shown].T, s=1, c="lightgrey", label="target")
    colours = after.scatter(*aligned[source_shown].T, s=2, c=np.minimum(residual, limit), cmap="viridis",
                            vmin=0.0, vmax=limit, label="source, moved")
    figure.colorbar(colours, ax=after, shrink=0.6, label="distance to target (clipped)")
    after.set_title("after: source coloured by residual")
    _equal_axes(after, np.concatenate([target[target_shown], aligned[source_shown]]))

    if panels == 3:
        _correspondence_panel(figure.add_subplot(1, panels, 3, projection="3d"), source, target, transformation,
                              result, limit, generator, source_shown, target_shown)

    title = registration_title(result, transformation, true_transformation)
    if title:
        figure.suptitle(title, color="darkgreen" if result is None or result.success else "darkred")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _correspondence_panel(axes, source, target, transformation, result, limit, generator, source_shown, target_shown):
    """Source and target side by side, the learned matches as lines: green agrees with the pose."""
    pairs = result.correspondences
    extent = max(np.ptp(source, axis=0).max(), np.ptp(target, axis=0).max())
    shift = np.array([1.3 * extent, 0.0, 0.0])
    source_centred = source - source.mean(axis=0)
    target_placed = target - target.mean(axis=0) + shift
    axes.scatter(*source_centred[source_shown].T, s=1, c="tab:orange", alpha=0.3)
    axes.scatter(*target_placed[target_shown].T, s=1, c="tab:blue", alpha=0.3)
    agrees = matches_agreeing(source, target, transformation, pairs, limit)
    drawn = seeded_subset(len(pairs), MAX_LINES, generator)
    for index in drawn:
        start, end = source_centred[pairs[index, 0]], target_placed[pairs[index, 1]]
        axes.plot(*np.stack([start, end]).T, linewidth=0.5, color="tab:green" if agrees[index] else "tab:red")
    axes.set_title(f"{len(pairs)} matches, {agrees.mean():.0%} agree with the pose")
    _equal_axes(axes, np.concatenate([source_centred[source_shown], target_placed[target_shown]]))


def _equal_axes(axes, points: np.ndarray) -> None:
    axes.set_box_aspect(np.ptp(points, axis=0) + 1e-9)


def plot_alignment(
    points: np.ndarray,
    scan: np.ndarray,
    names: list[str],
    path: str | Path,
    *,
    disconnected: list[str] | None = None,
    max_points: int = 4 * DEFAULT_MAX_POINTS,
    seed: int = 0,
) -> None:
    """Write an overview picture (PNG, PDF or SVG by suffix) of an aligned scan set.

    Args:
        points: (M, 3) merged cloud in the first scan's frame, user units (e.g. from
            :func:`~logdesc_rt.align.merge_scans`).
        scan: (M,) int, the index into ``names`` of the scan each point came from.
        names: one name per scan (the legend).
        path: the file to write.
        disconnected: names of the scans left out (no pose); listed in the title.
        max_points: at most this many points are drawn (seeded subset).
        seed: seeds that subset.
    """
    plt = _pyplot()
    points = np.asarray(points, dtype=np.float64)
    scan = np.asarray(scan)
    shown = seeded_subset(len(points), max_points, np.random.default_rng(seed))
    figure = plt.figure(figsize=(7.5, 7.0))
    axes = figure.add_subplot(1, 1, 1, projection="3d")
    colours = len(names) if len(names) > 10 else 10
    palette = plt.get_cmap("tab10" if colours == 10 else "tab20")
    for index in np.unique(scan[shown]):
        chosen = shown[scan[shown] == index]
        axes.scatter(*points[chosen].T, s=1, color=palette(int(index) % min(colours, 20)),
                     label=Path(names[int(index)]).name)
    if len(np.unique(scan)) <= 20:
        axes.legend(loc="upper right", markerscale=6, fontsize="small")
    _equal_axes(axes, points[shown])
    title = f"{len(np.unique(scan))} of {len(names)} scans aligned, coloured by scan"
    if disconnected:
        title += f"; disconnected: {', '.join(Path(name).name for name in disconnected)}"
    figure.suptitle(title, color="darkred" if disconnected else "darkgreen")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
