"""Before/after pictures of registrations with the bundled model (FSR), beside Open3D's.

Four pairs: ModelNet10 test pairs 0 and 1 under the noisy + partial protocol (the pairs
of ``accuracy_modelnet.py``), and two real Stanford Bunny scan pairs chosen by the rule
of ``bunny.py`` (measured overlap >= 30 %): the kept pair with the largest overlap and
the one with the smallest. Each picture has three panels: the clouds as given (target
blue, source orange), the source moved by ``logdesc_rt.Registrar.register(...,
estimator="fsr")``, and, when Open3D is installed, the source moved by Open3D FPFH +
FGR (``fpfh_fgr`` of ``methods.py``, tuned parameters). Every "after" title gives the
rotation error L_R (degrees) and the translation error (dataset units for ModelNet,
millimetres for the bunny).

    python benchmarks/gallery.py [--out DIR] [--threads N]

Writes ``<out>/gallery/*.png`` (default ``benchmarks/results/gallery/``).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from bunny import (  # noqa: E402
    DEFAULT_MIN_OVERLAP,
    load_scans,
    real_scan_pairs,
    select_scan_pairs,
)
from common import RESULTS, BenchmarkPair, modelnet10_test_pairs  # noqa: E402
from methods import MethodRunner, open3d_available  # noqa: E402

from logdesc_rt import Registrar  # noqa: E402
from logdesc_rt.errors import RegistrationError  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402

MODELNET_PAIRS = (0, 1)  # indices of the ModelNet10 test pairs shown


@dataclass(frozen=True)
class Panel:
    """One "after" panel: a method's pose and its errors.

    Attributes:
        method: label shown in the title.
        transformation: (4, 4) predicted pose source -> target, user frame.
        rotation_error_deg: L_R against the ground truth, degrees.
        translation_error: norm of the translation error, user units.
    """

    method: str
    transformation: np.ndarray
    rotation_error_deg: float
    translation_error: float


def score(pair: BenchmarkPair, method: str, transformation: np.ndarray) -> Panel:
    """The errors of a pose on a pair, as a :class:`Panel`."""
    transformation = np.asarray(transformation, dtype=np.float64)
    rotation = float(rotation_error_deg(transformation[:3, :3], pair.T_gt[:3, :3]))
    translation = float(np.linalg.norm(transformation[:3, 3] - pair.T_gt[:3, 3]))
    return Panel(method, transformation, rotation, translation)


def plot_pair(
    pair: BenchmarkPair,
    panels: list[Panel],
    path: Path,
    title: str,
    unit: tuple[str, float],
    vertical_axis: str = "z",
) -> None:
    """Write a PNG: the clouds as given, then one panel per method's aligned source.

    Args:
        pair: the clouds (user frame) and the ground truth.
        panels: the methods' poses and errors.
        path: PNG to write.
        title: figure title.
        unit: (name, factor) for translation errors, e.g. ("mm", 1000.0) for metres.
        vertical_axis: the axis drawn upwards ("y" for the bunny scans, whose up is +y).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    unit_name, unit_factor = unit
    columns = [("before (as given)", pair.source)]
    for panel in panels:
        pose = panel.transformation
        moved = pair.source @ pose[:3, :3].T + pose[:3, 3]
        error = f"{unit_factor * panel.translation_error:.3g} {unit_name}".strip()
        columns.append(
            (f"after {panel.method}\nL_R = {panel.rotation_error_deg:.2f} deg, "
             f"L_t = {error}", moved)
        )
    figure = plt.figure(figsize=(4.6 * len(columns), 4.8))
    for column, (panel_title, moved) in enumerate(columns):
        axes = figure.add_subplot(1, len(columns), column + 1, projection="3d")
        for points, colour, label in ((pair.target, "tab:blue", "target"),
                                      (moved, "tab:orange", "source")):
            axes.scatter(*points.T, s=1.5, c=colour, label=label, depthshade=False)
        axes.set_title(panel_title, fontsize=10)
        axes.view_init(elev=20, azim=-60, vertical_axis=vertical_axis)
        # Equal scale on the three axes, so shapes are not stretched.
        both = np.concatenate([pair.target, moved])
        axes.set_box_aspect(np.ptp(both, axis=0) + 1e-9)
        axes.tick_params(labelsize=6)
        if column == 0:
            axes.legend(loc="upper left", markerscale=6, fontsize=8)
    figure.suptitle(title)
    figure.tight_layout(rect=(0, 0, 1, 0.93))  # leave the top strip to the suptitle
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def gallery_pairs() -> list[tuple[BenchmarkPair, str, str, tuple[str, float], str]]:
    """(pair, file stem, title, translation unit, vertical axis) for every picture."""
    chosen = []
    modelnet = modelnet10_test_pairs(["partial"], count=max(MODELNET_PAIRS) + 1)
    for pair in modelnet:
        if pair.index in MODELNET_PAIRS:
            chosen.append((
                pair,
                f"modelnet10_partial_{pair.index:03d}_{pair.name}",
                f"ModelNet10 test pair {pair.index} ({pair.name}), noisy + partial "
                "(768 of 1024 points)",
                ("", 1.0),
                "z",
            ))
    scans = load_scans()
    selection = select_scan_pairs(scans, DEFAULT_MIN_OVERLAP)
    # The easiest and the hardest of the kept pairs, by overlap.
    extremes = [max(selection, key=lambda p: p.overlap),
                min(selection, key=lambda p: p.overlap)]
    for scan_pair, pair in zip(extremes, real_scan_pairs(scans, extremes), strict=True):
        source, target = scans[scan_pair.source].stem, scans[scan_pair.target].stem
        chosen.append((
            pair,
            f"bunny_{source}_to_{target}",
            f"Stanford Bunny scans {source} -> {target}: overlap "
            f"{100 * scan_pair.overlap:.0f} %, true rotation "
            f"{scan_pair.angle_deg:.0f} deg "
            "(1024 points each, metres)",
            ("mm", 1e3),
            "y",
        ))
    return chosen


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RESULTS,
                        help="results folder; pictures go to <out>/gallery/")
    parser.add_argument("--threads", type=int, default=None,
                        help="onnxruntime threads (default: all cores)")
    args = parser.parse_args(argv)

    registrar = Registrar(threads=args.threads)
    fgr = MethodRunner(["fpfh_fgr"]) if open3d_available() else None
    if fgr is None:
        print("open3d is not installed (pip install open3d): no FPFH + FGR panel",
              file=sys.stderr)
    for pair, stem, title, unit, vertical_axis in gallery_pairs():
        try:
            pose = registrar.register(pair.source, pair.target, estimator="fsr",
                                      seed=pair.index).transformation
            label = "logdesc-rt (FSR)"
        except RegistrationError:  # too few matches: show the clouds unmoved
            pose, label = np.eye(4), "logdesc-rt (FSR): failed, identity"
        panels = [score(pair, label, pose)]
        if fgr is not None:
            results = fgr.run(pair.source, pair.target, seed=pair.index)  # seeds Open3D
            pose = results["fpfh_fgr"].transformation
            panels.append(score(pair, "Open3D FPFH + FGR", pose))
        path = args.out / "gallery" / f"{stem}.png"
        plot_pair(pair, panels, path, title, unit, vertical_axis)
        errors = ", ".join(
            f"{p.method}: L_R {p.rotation_error_deg:.2f} deg" for p in panels
        )
        print(f"{path}  ({errors})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
