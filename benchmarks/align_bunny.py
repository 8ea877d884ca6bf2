"""The 10 Stanford Bunny scans aligned from scratch: logdesc-rt's align() against Open3D's
multiway registration, every scan's global pose against bun.conf.

    python benchmarks/align_bunny.py [--seed 0] [--workers 2] [--out benchmarks/results]

Protocol. The scans' order is shuffled with ``--seed`` (no initial poses, nothing from
``bun.conf`` reaches the methods). Each method's poses are in its reference scan's frame:
Open3D's is the first scan of the shuffled order, logdesc-rt's ``AlignmentResult.reference`` (the
first scan of the largest set its verified pairs connect). Truth: scan k's pose in the
reference's frame is ``inv(T_ref) @ T_k`` (``bun.conf``,
quaternion with qw's sign flipped: ``../shared/data/README.md``). Per scan: the rotation
error (degrees, isotropic) and the translation error (mm, norm of the pose's translation
difference; the scans sit in scanner frames near their centroids). A scan a method leaves
unconnected to the reference counts as failed, not as an error of some size. The issue's
goal: every scan within 1 degree and 1 mm.

Methods, all on the full scans (30k-40k points each), all 45 pairs:

- ``logdesc-rt align``: :func:`logdesc_rt.align` (all pairs for 10 scans; pairs kept when
  verification says ``success``; robust pose graph), pairwise ``refine=None`` and
  ``refine="point_to_plane"``, local backend with ``--workers`` processes.
- ``Open3D multiway`` (0.20's reconstruction-system recipe): voxel-downsampled scans,
  FPFH + RANSAC per pair (Open3D's tutorial checkers), optionally point-to-plane ICP;
  pairs rejected as in Open3D's ``register_fragments`` (identity result, or overlap from
  the information matrix < 30 %); a pose graph of the accepted pairs (uncertain edges, the
  information matrix per edge), nodes initialised along a spanning tree of the accepted
  edges (Open3D composes an odometry chain instead, but a shuffled order has no such
  chain), optimised by ``global_optimization`` (Levenberg-Marquardt, edge prune threshold
  0.25). Voxel: 2.5 % of the mean scan radius, with the tutorial's multipliers (normals 2x,
  FPFH 5x, RANSAC and ICP distance 1.5x): chosen once, not tuned on these scans.

Wall times are of this run on the 2-core machine, with whatever else ran beside it (the report
does not know): indicative only. Writes ``<out>/align_bunny.{md,json}`` and ``<out>/align_bunny.png`` (the
merged clouds coloured by scan).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import DATA_ROOT, RESULTS, command_line, machine_info, write_report  # noqa: E402

from logdesc_rt.align import AlignConfig, align, merge_scans  # noqa: E402
from logdesc_rt.io import read_point_cloud, read_stanford_conf  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402
from logdesc_rt.sampling import voxel_downsample  # noqa: E402

BUNNY_DIR = DATA_ROOT / "stanford_bunny" / "data"
GOAL_DEG, GOAL_MM = 1.0, 1.0
EDGE_RIGHT_DEG = 5.0  # an edge is "right" when its rotation is within this of the truth


def scan_errors(estimated: dict[str, np.ndarray | None], truth: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per scan: rotation error (deg) and translation error (mm), or failed (no pose)."""
    rows = {}
    for name, true_pose in truth.items():
        pose = estimated.get(name)
        if pose is None:
            rows[name] = {"connected": False, "rotation_deg": None, "translation_mm": None}
            continue
        rows[name] = {
            "connected": True,
            "rotation_deg": float(rotation_error_deg(pose[:3, :3], true_pose[:3, :3])),
            "translation_mm": float(1e3 * np.linalg.norm(pose[:3, 3] - true_pose[:3, 3])),
        }
    return rows


def summary(rows: dict[str, dict], reference: str) -> dict:
    others = {name: row for name, row in rows.items() if name != reference}
    connected = [row for row in others.values() if row["connected"]]
    rot = np.array([row["rotation_deg"] for row in connected]) if connected else np.array([np.nan])
    trans = np.array([row["translation_mm"] for row in connected]) if connected else np.array([np.nan])
    within = sum(1 for row in connected if row["rotation_deg"] < GOAL_DEG and row["translation_mm"] < GOAL_MM)
    within5 = sum(1 for row in connected if row["rotation_deg"] < 5.0 and row["translation_mm"] < 5.0)
    return {
        "scans": len(others),
        "connected": len(connected),
        "within_1deg_1mm": within,
        "within_5deg_5mm": within5,
        "rotation_deg_median": float(np.median(rot)),
        "rotation_deg_max": float(np.max(rot)),
        "translation_mm_median": float(np.median(trans)),
        "translation_mm_max": float(np.max(trans)),
    }


# ---------------------------------------------------------------------------- logdesc-rt
def run_logdesc(paths: list[Path], refine: str | None, workers: int, seed: int) -> dict:
    start = time.perf_counter()
    result = align([str(p) for p in paths], names=[p.name for p in paths],
                   config=AlignConfig(refine=refine, seed=seed), workers=workers, progress=False)
    seconds = time.perf_counter() - start
    return {"result": result, "poses": dict(result.poses), "seconds": seconds}


# ---------------------------------------------------------------------------- Open3D
def run_open3d(clouds: dict[str, np.ndarray], names: list[str], icp: bool, seed: int) -> dict:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    registration = o3d.pipelines.registration
    start = time.perf_counter()
    radius = float(np.mean([np.linalg.norm(c - c.mean(0), axis=1).max() for c in clouds.values()]))
    voxel = 0.025 * radius
    distance = 1.5 * voxel
    down, features = {}, {}
    for name in names:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(clouds[name]))
        cloud = cloud.voxel_down_sample(voxel)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        down[name] = cloud
        features[name] = registration.compute_fpfh_feature(
            cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
        )
    o3d.utility.random.seed(seed)
    edges = []  # (s, t, T_st: s -> t, information)
    for s in range(len(names)):
        for t in range(s + 1, len(names)):
            source, target = down[names[s]], down[names[t]]
            result = registration.registration_ransac_based_on_feature_matching(
                source, target, features[names[s]], features[names[t]], True, distance,
                registration.TransformationEstimationPointToPoint(False), 3,
                [registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 registration.CorrespondenceCheckerBasedOnDistance(distance)],
                registration.RANSACConvergenceCriteria(100000, 0.999),
            )
            transformation = np.asarray(result.transformation)
            if icp:
                transformation = np.asarray(registration.registration_icp(
                    source, target, distance, transformation, registration.TransformationEstimationPointToPlane()
                ).transformation)
            information = registration.get_information_matrix_from_point_clouds(
                source, target, distance, transformation
            )
            if np.trace(transformation) == 4.0:
                continue
            if information[5, 5] / min(len(source.points), len(target.points)) < 0.3:
                continue
            edges.append((s, t, transformation, information))
    # Initial node poses: breadth-first from the reference along accepted edges.
    initial: dict[int, np.ndarray] = {0: np.eye(4)}
    frontier = [0]
    while frontier:
        node = frontier.pop(0)
        for s, t, transformation, _ in edges:
            if s == node and t not in initial:
                initial[t] = initial[s] @ np.linalg.inv(transformation)
                frontier.append(t)
            elif t == node and s not in initial:
                initial[s] = initial[t] @ transformation
                frontier.append(s)
    graph = registration.PoseGraph()
    for index in range(len(names)):
        graph.nodes.append(registration.PoseGraphNode(initial.get(index, np.eye(4))))
    for s, t, transformation, information in edges:
        graph.edges.append(registration.PoseGraphEdge(s, t, transformation, information, uncertain=True))
    registration.global_optimization(
        graph,
        registration.GlobalOptimizationLevenbergMarquardt(),
        registration.GlobalOptimizationConvergenceCriteria(),
        registration.GlobalOptimizationOption(
            max_correspondence_distance=distance, edge_prune_threshold=0.25, reference_node=0
        ),
    )
    seconds = time.perf_counter() - start
    poses = {names[i]: (np.asarray(graph.nodes[i].pose) if i in initial else None) for i in range(len(names))}
    return {"poses": poses, "seconds": seconds, "accepted_pairs": len(edges), "kept_edges": len(graph.edges),
            "voxel_m": voxel}


# ---------------------------------------------------------------------------- report
def edge_table(result, truth: dict[str, np.ndarray]) -> list[dict]:
    rows = []
    for edge in result.edges:
        first, second = result.names[edge.first], result.names[edge.second]
        true_relative = np.linalg.inv(truth[first]) @ truth[second]
        rows.append({
            "source": second, "target": first, "kept": edge.kept, "confidence": edge.confidence,
            "error_deg": float(rotation_error_deg(edge.transformation[:3, :3], true_relative[:3, :3])),
            "error_mm": float(1e3 * np.linalg.norm(edge.transformation[:3, 3] - true_relative[:3, 3])),
            "residual_rotation_deg": edge.residual_rotation_deg if np.isfinite(edge.residual_rotation_deg) else None,
        })
    return rows


def finite_or_none(value):
    """``value`` with NaN / inf floats as None, recursively (JSON has neither)."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_none(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(item) for item in value]
    return value


def picture(path: Path, panels: list[tuple[str, np.ndarray, np.ndarray]], names: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = plt.get_cmap("tab10")
    figure = plt.figure(figsize=(6 * len(panels), 6))
    for k, (title, points, labels) in enumerate(panels):
        axes = figure.add_subplot(1, len(panels), k + 1, projection="3d")
        rng = np.random.default_rng(0)
        shown = rng.choice(len(points), min(len(points), 25000), replace=False) if len(points) else []
        for index in np.unique(labels[shown]) if len(points) else []:
            mask = labels[shown] == index
            axes.scatter(*points[shown][mask].T[[0, 2, 1]], s=0.3, color=colours(int(index) % 10),
                         label=names[int(index)])
        axes.set_title(title, fontsize=9)
        axes.view_init(elev=15, azim=-60)
        axes.set_axis_off()
        axes.legend(markerscale=15, fontsize=6, loc="upper left")
    figure.tight_layout()
    figure.savefig(path, dpi=130)
    plt.close(figure)


def merged(clouds, names, poses, voxel):
    parts, labels = [], []
    for index, name in enumerate(names):
        if poses.get(name) is not None:
            pose = poses[name]
            parts.append(clouds[name] @ pose[:3, :3].T + pose[:3, 3])
            labels.append(np.full(len(clouds[name]), index))
    if not parts:
        return np.zeros((0, 3)), np.zeros(0, dtype=int)
    points, labels = np.concatenate(parts), np.concatenate(labels)
    kept = voxel_downsample(points, voxel)
    return points[kept], labels[kept]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0, help="shuffles the scan order and seeds every method")
    parser.add_argument("--workers", type=int, default=2, help="logdesc-rt's local worker processes")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    truth_world = read_stanford_conf(BUNNY_DIR / "bun.conf")
    paths = sorted(BUNNY_DIR.glob("*.ply"))
    order = np.random.default_rng(args.seed).permutation(len(paths))
    paths = [paths[i] for i in order]
    names = [p.name for p in paths]
    first = names[0]

    def truth_in_frame_of(reference: str) -> dict[str, np.ndarray]:
        return {name: np.linalg.inv(truth_world[reference]) @ truth_world[name] for name in names}

    truth = truth_in_frame_of(first)
    clouds = {p.name: read_point_cloud(p) for p in paths}
    print(f"order: {names}", flush=True)

    methods: dict[str, dict] = {}
    for label, refine in (("logdesc-rt align", None), ("logdesc-rt align + ICP", "point_to_plane")):
        run = run_logdesc(paths, refine, args.workers, args.seed)
        result = run["result"]
        methods[label] = {
            "poses": run["poses"], "seconds": run["seconds"],
            "verified_pairs": len(result.edges), "kept_edges": sum(e.kept for e in result.edges),
            "pruned_edges": sum(not e.kept for e in result.edges),
            "edges": edge_table(result, truth), "disconnected": result.disconnected,
            "alignment": result.to_json(), "result": result, "reference": result.reference,
        }
        print(f"{label}: {run['seconds']:.1f} s, {len(result.edges)} of {result.candidate_pairs} pairs verified, "
              f"disconnected {result.disconnected}", flush=True)
    try:
        for label, icp in (("Open3D FPFH + RANSAC + pose graph", False),
                           ("Open3D FPFH + RANSAC + ICP + pose graph", True)):
            methods[label] = run_open3d(clouds, names, icp, args.seed)
            print(f"{label}: {methods[label]['seconds']:.1f} s, {methods[label]['accepted_pairs']} pairs accepted",
                  flush=True)
        open3d_note = ""
    except ImportError:
        open3d_note = "Open3D is not installed: its rows are missing (pip install open3d)."

    for method in methods.values():
        reference = method.setdefault("reference", first)  # Open3D's: node 0, the first scan
        method["scans"] = scan_errors(method["poses"], truth_in_frame_of(reference))
        method["summary"] = summary(method["scans"], reference)

    # ------------------------------------------------------------------ markdown
    lines = [
        "# Stanford Bunny: 10 scans aligned from scratch",
        "",
        f"Command: `{command_line()}`. Scan order (shuffled, seed {args.seed}): {', '.join(names)}; "
        "reference (identity): " + ", ".join(f"{label} {m['reference']}" for label, m in methods.items())
        + ". Truth from `bun.conf`; no initial poses. Goal of issue 14: "
        f"every scan within {GOAL_DEG:g} degree and {GOAL_MM:g} mm. Wall times: this run on a 2-core machine, "
        "with whatever else ran beside it: indicative only. " + open3d_note,
        "",
        "| method | connected scans (of 9) | within 1 deg & 1 mm | within 5 deg & 5 mm "
        "| rotation error median / max (deg) "
        "| translation error median / max (mm) | pairs kept (of 45) | wall time (s) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for label, method in methods.items():
        s = method["summary"]
        kept = method.get("kept_edges", method.get("accepted_pairs"))
        lines.append(
            f"| {label} | {s['connected']} | {s['within_1deg_1mm']} | {s['within_5deg_5mm']} | "
            f"{s['rotation_deg_median']:.2f} / {s['rotation_deg_max']:.2f} | {s['translation_mm_median']:.2f} / "
            f"{s['translation_mm_max']:.2f} | {kept} | {method['seconds']:.0f} |"
        )
    lines += ["", "Per scan: rotation error (deg) / translation error (mm) in the method's reference frame; `-` = not "
              "connected to the reference.", "",
              "| scan | " + " | ".join(methods) + " |", "| --- |" + " ---: |" * len(methods)]
    for name in names:
        cells = []
        for method in methods.values():
            row = method["scans"][name]
            if name == method["reference"]:
                cells.append("reference")
            else:
                cells.append(
                    "-" if not row["connected"] else f"{row['rotation_deg']:.2f} / {row['translation_mm']:.2f}"
                )
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    for label in ("logdesc-rt align", "logdesc-rt align + ICP"):
        method = methods[label]
        lines += ["", f"{label}: the {method['verified_pairs']} pairs verification accepted (of 45), against the truth "
                  f"(right: rotation within {EDGE_RIGHT_DEG:g} deg); pruned = dropped by the pose graph as "
                  "inconsistent.", "",
                  "| source -> target | confidence | edge error (deg / mm) | right | kept |",
                  "| --- | ---: | ---: | --- | --- |"]
        for edge in method["edges"]:
            lines.append(f"| {edge['source']} -> {edge['target']} | {edge['confidence']:.3f} | "
                         f"{edge['error_deg']:.2f} / "
                         f"{edge['error_mm']:.2f} | {'yes' if edge['error_deg'] < EDGE_RIGHT_DEG else 'NO'} | "
                         f"{'yes' if edge['kept'] else 'pruned'} |")
    lines += ["", "Only pairs verification accepts enter the pose graph; a scan whose every pair is rejected stays "
              "disconnected: reported, not placed.", "",
              "Picture: `align_bunny.png` (merged clouds, voxel-thinned, coloured by scan)."]
    markdown = "\n".join(lines) + "\n"

    payload = {
        "command": command_line(), "machine": machine_info(), "seed": args.seed, "order": names,
        "goal": {"rotation_deg": GOAL_DEG, "translation_mm": GOAL_MM},
        "methods": {
            label: {key: value for key, value in method.items() if key not in ("poses", "result")}
            | {"poses": {n: (None if p is None else p.tolist()) for n, p in method["poses"].items()}}
            for label, method in methods.items()
        },
    }
    md_path, json_path = write_report("align_bunny", markdown, finite_or_none(payload), args.out)

    voxel = 0.002
    panels = []
    ours = methods["logdesc-rt align + ICP"]
    points, labels = merge_scans([str(p) for p in paths], ours["result"], voxel_size=voxel)
    panels.append((f"logdesc-rt align + ICP: {ours['summary']['connected']} of 9 scans connected", points, labels))
    for label in ("Open3D FPFH + RANSAC + ICP + pose graph",):
        if label in methods:
            points, labels = merged(clouds, names, methods[label]["poses"], voxel)
            panels.append((f"{label}: {methods[label]['summary']['connected']} of 9 connected", points, labels))
    points, labels = merged(clouds, names, truth, voxel)
    panels.append(("ground truth (bun.conf)", points, labels))
    picture(args.out / "align_bunny.png", panels, names)
    print(markdown)
    print(f"wrote {md_path}, {json_path}, {args.out / 'align_bunny.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
