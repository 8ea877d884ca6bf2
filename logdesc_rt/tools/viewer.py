"""Interactive 3D views of a registration or an aligned scan set: one self-contained HTML file.

The page opens offline in any browser (plotly.js is embedded, about 4.7 MB; nothing is fetched
when it opens) and turns, zooms and pans with the mouse. Each cloud is a legend entry that a
click toggles; the buttons at the top switch between ready-made views:

    after    the target, and the source moved by the pose coloured by its distance to the
             nearest target point (clipped at the correspondence distance): a right pose is
             dark where the clouds overlap, a wrong one bright everywhere
    before   the source and the target as given
    matches  the target beside a shifted copy of the moved source, with the learned matches
             as lines: those that agree with the pose are green (all parallel, of one length),
             those that do not red

The title carries the verdict, confidence, fitness, inlier RMSE, the estimator, the reason of
a failure and, when the truth is given, the rotation and translation errors. Clouds above
``max_points`` are thinned for the page by a seeded subset, and the legend says how many of how
many points are shown. For an aligned scan set, every placed scan gets its own colour and the
pose graph's pairs are drawn between the scans' centres (green: used, red: pruned).

Drawing uses plotly (MIT; WebGL scatter plots), an optional extra: ``pip install
"logdesc-rt[plot]"``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from pykdtree.kdtree import KDTree

from ..sampling import seeded_subset
from .plotting import matches_agreeing, registration_title

VIEW_SUFFIXES = (".html", ".htm")
DEFAULT_MAX_POINTS = 20_000  # per cloud shown on the page; WebGL draws this many smoothly
MAX_MATCH_LINES = 400
_MARKER_SIZE = 2
_SCAN_PALETTE = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
)


def _plotly():
    try:
        import plotly.graph_objects as go
    except ImportError as error:
        raise RuntimeError('3D views need plotly, which is not installed: pip install "logdesc-rt[plot]"') from error
    return go


def check_view_available(path: str | Path) -> None:
    """Raise ValueError unless ``path`` has an HTML suffix and plotly is installed (before any work)."""
    path = Path(path)
    if path.suffix.lower() not in VIEW_SUFFIXES:
        raise ValueError(f"--view {path}: unsupported suffix {path.suffix!r}; supported: {', '.join(VIEW_SUFFIXES)}")
    try:
        _plotly()
    except RuntimeError as error:
        raise ValueError(f"--view: {error}") from error


def _shown_label(name: str, shown: int, total: int) -> str:
    return f"{name} ({total:,} points)" if shown == total else f"{name} ({shown:,} of {total:,} points shown)"


def write_registration_view(
    path: str | Path,
    source: np.ndarray,
    target: np.ndarray,
    result=None,
    *,
    transformation: np.ndarray | None = None,
    true_transformation: np.ndarray | None = None,
    max_points: int = DEFAULT_MAX_POINTS,
    seed: int = 0,
) -> Path:
    """Write the interactive view of a registration (module doc) to ``path`` (.html).

    Args:
        path: the HTML file to write.
        source, target: (N, 3) / (M, 3) clouds as registered (user units); ``result``'s
            correspondence indices refer to them.
        result: a :class:`~logdesc_rt.registration.RegistrationResult`: its pose, verdict and
            matches. Without it, ``transformation`` is drawn alone.
        transformation: (4, 4) source -> target; default ``result.transformation``.
        true_transformation: optional (4, 4) ground truth: its errors go into the title.
        max_points: per cloud, at most this many points on the page (seeded subset).
        seed: seeds the subsets of points and of match lines.

    Returns:
        The path written.
    """
    go = _plotly()
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if transformation is None:
        if result is None:
            raise ValueError("write_registration_view: give a result or a transformation")
        transformation = result.transformation
    transformation = np.asarray(transformation, dtype=np.float64)
    generator = np.random.default_rng(seed)
    aligned = source @ transformation[:3, :3].T + transformation[:3, 3]
    source_shown = seeded_subset(len(source), max_points, generator)
    target_shown = seeded_subset(len(target), max_points, generator)
    if result is not None:
        limit = float(result.max_correspondence_distance)
    else:
        limit = 0.05 * float(np.linalg.norm(target - target.mean(axis=0), axis=1).max())
    residual, _ = KDTree(target).query(aligned[source_shown], k=1)

    traces, views = [], {"after": [], "before": [], "matches": []}

    def add(trace, *in_views: str) -> None:
        for name, members in views.items():
            members.append(name in in_views)
        traces.append(trace)

    def cloud(points, name, colour, **marker):
        return go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers", name=name,
                            marker={"size": _MARKER_SIZE, "color": colour, **marker}, hoverinfo="skip")

    target_label = _shown_label("target", len(target_shown), len(target))
    add(cloud(target[target_shown], target_label, "#9aa4b1", opacity=0.6), "after", "before", "matches")
    add(cloud(source[source_shown], _shown_label("source as given", len(source_shown), len(source)), "#ff7f0e"),
        "before")
    add(cloud(aligned[source_shown], _shown_label("source moved, colour = distance to target", len(source_shown),
                                                  len(source)),
              np.minimum(residual, limit), colorscale="Viridis", cmin=0.0, cmax=limit,
              colorbar={"title": {"text": "distance to target"}, "len": 0.6}), "after")

    pairs = np.zeros((0, 2), dtype=np.int64) if result is None else np.asarray(result.correspondences)
    if len(pairs):
        extent = max(np.ptp(source, axis=0).max(), np.ptp(target, axis=0).max())
        shift = np.array([1.3 * extent, 0.0, 0.0])  # the moved source beside the target
        beside = aligned + shift
        add(cloud(beside[source_shown], "source moved, shifted beside the target", "#ff7f0e", opacity=0.4),
            "matches")
        agrees = matches_agreeing(source, target, transformation, pairs, limit)
        drawn = seeded_subset(len(pairs), MAX_MATCH_LINES, generator)
        for wanted, name, colour in ((True, "agree with the pose", "#2ca02c"), (False, "disagree", "#d62728")):
            chosen = drawn[agrees[drawn] == wanted]
            count = int(np.count_nonzero(agrees == wanted))
            label = f"matches that {name}: {count}" if wanted else f"matches that disagree: {count}"
            if len(chosen) < count:
                label += f" ({len(chosen)} drawn)"
            add(_segments(go, beside[pairs[chosen, 0]], target[pairs[chosen, 1]], label, colour), "matches")

    if not len(pairs):
        del views["matches"]  # nothing to show beside the target
    title = registration_title(result, transformation, true_transformation, separator="<br>") or "registration"
    good = result is None or result.success
    figure = go.Figure(data=traces)
    _layout(figure, title, "#1b5e20" if good else "#b71c1c", views, default="after")
    return _write(figure, path)


def write_alignment_view(
    path: str | Path,
    scans: Sequence[np.ndarray],
    result,
    *,
    max_points: int = 60_000,
    seed: int = 0,
) -> Path:
    """Write the interactive view of an aligned scan set (module doc) to ``path`` (.html).

    Args:
        path: the HTML file to write.
        scans: the scans as given to :func:`~logdesc_rt.align.align`, (Ni, 3) each, in
            ``result.names``' order.
        result: the :class:`~logdesc_rt.align.AlignmentResult`.
        max_points: at most this many points on the page, shared evenly by the placed scans.
        seed: seeds the subsets.

    Returns:
        The path written.
    """
    go = _plotly()
    if len(scans) != len(result.names):
        raise ValueError(f"write_alignment_view: {len(scans)} scans for {len(result.names)} names")
    generator = np.random.default_rng(seed)
    placed = [index for index, name in enumerate(result.names) if name in result.poses]
    per_scan = max(1, max_points // max(1, len(placed)))
    traces, centres = [], {}
    for order, index in enumerate(placed):
        points = np.asarray(scans[index], dtype=np.float64)
        pose = result.poses[result.names[index]]
        moved = points @ pose[:3, :3].T + pose[:3, 3]
        shown = seeded_subset(len(moved), per_scan, generator)
        centres[index] = moved.mean(axis=0)
        name = Path(result.names[index]).name + (" (reference)" if result.names[index] == result.reference else "")
        traces.append(go.Scatter3d(
            x=moved[shown, 0], y=moved[shown, 1], z=moved[shown, 2], mode="markers",
            name=_shown_label(name, len(shown), len(moved)), hoverinfo="skip",
            marker={"size": _MARKER_SIZE, "color": _SCAN_PALETTE[order % len(_SCAN_PALETTE)]},
        ))
    for kept, colour in ((True, "#2ca02c"), (False, "#d62728")):
        edges = [edge for edge in result.edges
                 if edge.kept == kept and edge.first in centres and edge.second in centres]
        if edges:
            starts = np.array([centres[edge.first] for edge in edges])
            ends = np.array([centres[edge.second] for edge in edges])
            label = f"pairs used in the pose graph: {len(edges)}" if kept else f"pairs pruned: {len(edges)}"
            traces.append(_segments(go, starts, ends, label, colour, width=4))
    title = f"{len(placed)} of {len(result.names)} scans aligned, coloured by scan"
    if result.disconnected:
        title += "; disconnected: " + ", ".join(Path(name).name for name in result.disconnected)
    figure = go.Figure(data=traces)
    _layout(figure, title, "#b71c1c" if result.disconnected else "#1b5e20", views=None)
    return _write(figure, path)


def _segments(go, starts: np.ndarray, ends: np.ndarray, name: str, colour: str, width: float = 2):
    """One line trace of many segments (None between them breaks the line)."""
    count = len(starts)
    xyz = np.full((3 * count, 3), np.nan)
    xyz[0::3], xyz[1::3] = starts, ends
    coordinates = [[None if np.isnan(value) else float(value) for value in xyz[:, axis]] for axis in range(3)]
    return go.Scatter3d(x=coordinates[0], y=coordinates[1], z=coordinates[2], mode="lines", name=name,
                        line={"color": colour, "width": width}, hoverinfo="skip")


def _layout(figure, title: str, colour: str, views: dict[str, list[bool]] | None, default: str | None = None) -> None:
    figure.update_layout(
        title={"text": title, "font": {"color": colour, "size": 15}, "x": 0.01},
        scene={"aspectmode": "data", "xaxis": {"title": "x"}, "yaxis": {"title": "y"}, "zaxis": {"title": "z"}},
        legend={"itemsizing": "constant", "x": 0.0, "y": 0.9},
        margin={"l": 0, "r": 0, "t": 100, "b": 0},
        template="plotly_white",
    )
    if views:
        for trace, shown in zip(figure.data, views[default]):
            trace.visible = True if shown else "legendonly"
        figure.update_layout(updatemenus=[{
            "type": "buttons", "direction": "right", "x": 0.0, "xanchor": "left", "y": 1.0, "yanchor": "top",
            "buttons": [
                {"label": name, "method": "restyle",
                 "args": [{"visible": [True if shown else "legendonly" for shown in members]}]}
                for name, members in views.items()
            ],
        }])


def _write(figure, path: str | Path) -> Path:
    path = Path(path)
    # include_plotlyjs=True embeds plotly.js: the page needs no network when it opens.
    figure.write_html(path, include_plotlyjs=True, full_html=True,
                      config={"displaylogo": False, "responsive": True}, default_height="96vh")
    return path
