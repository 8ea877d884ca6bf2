"""End-to-end time and peak memory on large clouds: a real 40k x 40k scan pair, 120k x 120k and 300k x 300k pairs.

    python benchmarks/large_clouds.py [--threads 2] [--rounds 3] [--model-dir DIR] [--stem large_clouds] [--no-open3d]

Cases, each run in a fresh process (so that peak resident memory, ``ru_maxrss``, is the case's
own), with and without point-to-plane ICP on the full clouds. Each process registers the small
demo pair first (untimed in the table, its time recorded as ``warm_up_s``): loading the compiled
kernels and the networks' first run happen once per process, whatever the clouds.

- ``bunny_40k``: the real Stanford Bunny scans bun000 -> bun045 as they are (about 40k points
  each, metres, their own scanner frames), truth from ``bun.conf``;
- ``merged_120k`` and ``merged_300k``: all ten Bunny scans placed in the common frame (about
  360k points); the source is 120,000 (300,000) of them and the target another 120,000
  (300,000) (independent uniform draws, ``default_rng([SEED, 1])`` / ``[SEED, 2]``), the
  target moved by a 30 degree turn about a skew axis and 0.05 m, then both shifted 1 km from
  the origin. 120k x 120k in metres is the size of a LiDAR scan pair (no LiDAR data
  is in ../shared: these are the merged real scans). Timing is the point; the error is
  reported so that a fast wrong answer does not pass for a result.

Beside each case, in its own fresh process, Open3D as its users run it on large clouds: both
clouds voxel-downsampled (2.5 % of the target's radius), normals and FPFH on the voxels
(2x / 5x the voxel), RANSAC on the FPFH matches (distance 1.5x the voxel, edge length 0.9,
100,000 iterations, confidence 0.999), then point-to-plane ICP on the full clouds (normals of
the full target from its 30 nearest within 2x the voxel) at the correspondence distance
``register(refine=...)`` uses, 5 % of the radius, 30 iterations. Its time includes all of it.

With ``--rounds N`` every case runs N times, Open3D and logdesc-rt alternating within each
round, so that a drift of the machine's speed reaches both alike: each row is the round of median
time (its ``rounds_s`` lists all N), and each Open3D row's ratio is the median of the N rounds'
own ratios (``ratio_rounds``).

Quiet machine wanted: nothing else running. Writes benchmarks/results/<stem>.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402
from common import command_line, machine_info, write_report  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

SEED = 20261130
CASES = ("bunny_40k", "merged_120k", "merged_300k")
MERGED_SIZES = {"merged_120k": 120_000, "merged_300k": 300_000}
OPEN3D_VOXEL_FRACTION = 0.025  # of the target's radius: Open3D's tutorials' scale for FPFH
REFINEMENTS = (None, "point_to_plane")
MERGED_TURN_DEG = 30.0
FAR_AWAY_M = 1000.0


def build_case(case: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(source (N, 3), target (M, 3), true (4, 4) pose source -> target), metres."""
    from bunny import load_scans, relative_pose, transform

    scans = load_scans()
    if case == "bunny_40k":
        source, target = (next(s for s in scans if s.stem == name) for name in ("bun000", "bun045"))
        return source.points, target.points, relative_pose(source, target)
    merged = np.concatenate([transform(scan.points, scan.pose) for scan in scans])
    count = MERGED_SIZES[case]
    source = merged[np.random.default_rng([SEED, 1]).choice(len(merged), count, replace=False)]
    target = merged[np.random.default_rng([SEED, 2]).choice(len(merged), count, replace=False)]
    motion = np.eye(4)
    axis = np.array([1.0, 2.0, 0.5]) / np.sqrt(5.25)  # a skew unit axis
    motion[:3, :3] = Rotation.from_rotvec(np.radians(MERGED_TURN_DEG) * axis).as_matrix()
    motion[:3, 3] = (0.05, -0.02, 0.03)
    target = transform(target, motion)
    shift = np.full(3, FAR_AWAY_M)
    to_source_far, from_target_far = np.eye(4), np.eye(4)
    to_source_far[:3, 3], from_target_far[:3, 3] = -shift, shift
    # Truth: un-shift the source, apply the motion, shift again.
    return source + shift, target + shift, from_target_far @ motion @ to_source_far


def run_case(case: str, refine: str | None, threads: int, model_dir: str | None) -> dict:
    """One case in this process: time the registration and read the peak memory."""
    from logdesc_rt import Registrar
    from logdesc_rt.metrics import rotation_error_deg

    source, target, truth = build_case(case)
    baseline_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    registrar = Registrar(model_dir, threads=threads)
    # One warm-up registration of a small pair first: the one-time costs of a process (loading
    # the compiled kernels, the networks' first run) are start-up, reported apart.
    from logdesc_rt.demo import make_demo_pair

    demo = make_demo_pair()
    started = time.perf_counter()
    registrar.register(demo.source, demo.target, refine=refine)
    warm_up = time.perf_counter() - started
    started = time.perf_counter()
    result = registrar.register(source, target, refine=refine)
    seconds = time.perf_counter() - started
    scale = float(np.linalg.norm(target - target.mean(axis=0), axis=1).max())
    centroid = np.append(source.mean(axis=0), 1.0)
    return {
        "case": case,
        "refine": refine,
        "source_points": len(source),
        "target_points": len(target),
        "seconds": seconds,
        "warm_up_s": warm_up,
        "timings_s": result.timings,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "peak_rss_before_mib": baseline_mib,
        "rotation_error_deg": float(rotation_error_deg(result.transformation[:3, :3], truth[:3, :3])),
        # At the source's centroid: at the origin, 1 km away, any rotation error would read as
        # metres of translation.
        "translation_error_m": float(np.linalg.norm(centroid @ (result.transformation - truth)[:3].T)),
        "scale_m": scale,
        "success": result.success,
        "confidence": result.confidence,
    }


def run_open3d(case: str, threads: int) -> dict:
    """Open3D's voxel FPFH + RANSAC, then point-to-plane ICP on the full clouds (module docstring)."""
    import open3d as o3d

    from logdesc_rt.metrics import rotation_error_deg

    source, target, truth = build_case(case)
    baseline_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    registration = o3d.pipelines.registration
    started = time.perf_counter()
    scale = float(np.linalg.norm(target - target.mean(axis=0), axis=1).max())
    voxel = OPEN3D_VOXEL_FRACTION * scale
    clouds, features = [], []
    for points in (source, target):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        down = cloud.voxel_down_sample(voxel)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        features.append(registration.compute_fpfh_feature(
            down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
        ))
        clouds.append((cloud, down))
    coarse = registration.registration_ransac_based_on_feature_matching(
        clouds[0][1], clouds[1][1], features[0], features[1], True, 1.5 * voxel,
        registration.TransformationEstimationPointToPoint(False), 3,
        [
            registration.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            registration.CorrespondenceCheckerBasedOnDistance(1.5 * voxel),
        ],
        registration.RANSACConvergenceCriteria(100000, 0.999),
    )
    coarse_seconds = time.perf_counter() - started
    refined = open3d_point_to_plane(clouds[0][0], clouds[1][0], coarse.transformation, scale)
    seconds = time.perf_counter() - started
    centroid = np.append(source.mean(axis=0), 1.0)
    rows = []
    for label, pose, elapsed in (("Open3D FPFH + RANSAC", coarse.transformation, coarse_seconds),
                                 ("Open3D FPFH + RANSAC + ICP", refined.transformation, seconds)):
        pose = np.asarray(pose)
        rows.append({
            "case": case, "method": label, "source_points": len(source), "target_points": len(target),
            "seconds": elapsed, "threads": threads, "voxel_m": voxel,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "peak_rss_before_mib": baseline_mib,
            "rotation_error_deg": float(rotation_error_deg(pose[:3, :3], truth[:3, :3])),
            "translation_error_m": float(np.linalg.norm(centroid @ (pose - truth)[:3].T)),
        })
    return {"open3d": rows}


def open3d_point_to_plane(source_cloud, target_cloud, start: np.ndarray, scale: float):
    """Open3D's point-to-plane ICP on full clouds as both Open3D rows run it: target normals from
    the 30 nearest within twice the voxel, 5 % of the radius ``scale`` as the distance (what
    ``register(refine=...)`` uses), 30 iterations. Returns Open3D's registration result."""
    import open3d as o3d

    registration = o3d.pipelines.registration
    voxel = OPEN3D_VOXEL_FRACTION * scale
    target_cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    return registration.registration_icp(
        source_cloud, target_cloud, 0.05 * scale, start,
        registration.TransformationEstimationPointToPlane(), registration.ICPConvergenceCriteria(max_iteration=30),
    )


def open3d_icp_placement_check(case: str = "merged_120k") -> list[dict]:
    """Open3D's point-to-plane ICP from the truth turned 1 degree (about the target's centroid),
    on the case's clouds where they are (1 km from the origin) and moved back to the origin:
    whether the placement alone decides its result."""
    import open3d as o3d

    from logdesc_rt.metrics import rotation_error_deg

    source, target, truth = build_case(case)
    checks = []
    for label, offset in (("at the origin", -np.full(3, FAR_AWAY_M)), ("1 km from the origin", np.zeros(3))):
        moved_source, moved_target = source + offset, target + offset
        shift, unshift = np.eye(4), np.eye(4)
        shift[:3, 3], unshift[:3, 3] = offset, -offset
        moved_truth = shift @ truth @ unshift
        scale = float(np.linalg.norm(moved_target - moved_target.mean(axis=0), axis=1).max())
        turn = np.eye(4)
        turn[:3, :3] = Rotation.from_rotvec(np.radians(1.0) * np.array([0.6, 0.8, 0.0])).as_matrix()
        about, back = np.eye(4), np.eye(4)
        about[:3, 3], back[:3, 3] = moved_target.mean(axis=0), -moved_target.mean(axis=0)
        start = about @ turn @ back @ moved_truth
        cloud = lambda points: o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))  # noqa: E731
        pose = np.asarray(open3d_point_to_plane(cloud(moved_source), cloud(moved_target), start, scale).transformation)
        checks.append({"case": case, "placement": label,
                       "rotation_error_deg": float(rotation_error_deg(pose[:3, :3], moved_truth[:3, :3]))})
    return checks


def markdown(rows: list[dict], args, open3d_rows: list[dict] | None = None, placement: list[dict] | None = None) -> str:
    stages = ("load", "subsample", "geometry", "descriptors", "matcher", "matching", "pose", "verification",
              "refinement", "evaluation")
    lines = [
        "# Large clouds: end-to-end time and peak memory",
        "",
        f"`{command_line()}`; model `{args.model_dir or 'bundled'}`, {args.threads} onnxruntime threads, "
        "each case in a fresh process after one warm-up registration of the small demo pair. The networks see "
        "the model's working size per cloud (farthest-point subsets); subsampling, verification, ICP and the "
        "fitness evaluation read bounded seeded subsets of the full clouds (docs: Large clouds).",
        "",
        "| case | points | ICP | total s | " + " | ".join(stages) + " | peak RSS MiB | rotation error deg | "
        "error at the source centroid mm | success |",
        "| --- | --- | --- | ---: | " + " | ".join("---:" for _ in stages) + " | ---: | ---: | ---: | --- |",
    ]
    for row in rows:
        cells = [f"{row['timings_s'].get(stage, 0.0):.2f}" for stage in stages]
        lines.append(
            f"| {row['case']} | {row['source_points']} x {row['target_points']} | {row['refine'] or 'none'} | "
            f"{row['seconds']:.2f} | " + " | ".join(cells) + f" | {row['peak_rss_mib']:.0f} | "
            f"{row['rotation_error_deg']:.2f} | {1e3 * row['translation_error_m']:.1f} | {row['success']} |"
        )
    lines += ["", "Stage times in seconds (`RegistrationResult.timings`); peak RSS includes the Python "
              "interpreter, the clouds and the loaded model."]
    if open3d_rows:
        lines += [
            "",
            "## Open3D on the same cases",
            "",
            "Voxel FPFH + RANSAC, then point-to-plane ICP on the full clouds (module docstring), each case in "
            "its own fresh process with OMP_NUM_THREADS = --threads. ratio = Open3D's time / logdesc-rt's total "
            "on the same case, without ICP for the coarse row and with ICP for the refined one (> 1: logdesc-rt is "
            "faster; with several rounds, the median of the rounds' ratios and their range). Open3D's "
            "point-to-plane ICP linearises the rotation about the origin: the merged cases sit "
            "1 km from it (as georeferenced scans do), where its steps go wrong.",
            "",
            "| case | method | voxel m | seconds | ratio | peak RSS MiB | rotation error deg "
            "| error at the source centroid mm |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for row in open3d_rows:
            ratios = row.get("ratio_rounds", [])
            ratio = f"{float(np.median(ratios)):.2f}x" if ratios else "—"
            if len(ratios) > 1:
                ratio += f" ({min(ratios):.2f}-{max(ratios):.2f})"
            lines.append(
                f"| {row['case']} | {row['method']} | {row['voxel_m']:.4f} | {row['seconds']:.2f} | {ratio} | "
                f"{row['peak_rss_mib']:.0f} | {row['rotation_error_deg']:.2f} | "
                f"{1e3 * row['translation_error_m']:.1f} |"
            )
    if placement:
        lines += ["", "Open3D's point-to-plane ICP from the truth turned 1 degree, the same clouds where they are and "
                  "moved to the origin (`open3d_icp_placement_check`): "
                  + "; ".join(f"{c['placement']} {c['rotation_error_deg']:.3f} deg" for c in placement) + "."]
    return "\n".join(lines) + "\n"


def median_rounds(round_rows: list[list[dict]], round_open3d_rows: list[list[dict]]) -> tuple[list[dict], list[dict]]:
    """Our rows and Open3D's, each the round of median time for its case (and ICP or method),
    with ``rounds_s`` (every round's seconds, in order); each Open3D row with ``ratio_rounds``:
    its seconds over ours (without ICP for the coarse row, with ICP for the refined one) in the
    same round."""

    def median_row(rounds_of_one: list[dict]) -> dict:
        seconds = [row["seconds"] for row in rounds_of_one]
        middle = sorted(range(len(seconds)), key=seconds.__getitem__)[(len(seconds) - 1) // 2]
        return {**rounds_of_one[middle], "rounds_s": seconds}

    rows = [median_row([rows[i] for rows in round_rows]) for i in range(len(round_rows[0]))]
    open3d_rows = []
    for i in range(len(round_open3d_rows[0])):
        rounds_of_one = [peers[i] for peers in round_open3d_rows]
        row = median_row(rounds_of_one)
        ratios = []
        for peer, ours in zip(rounds_of_one, round_rows):
            wanted = (peer["case"], peer["method"].endswith("ICP"))
            match = [r["seconds"] for r in ours if (r["case"], bool(r["refine"])) == wanted]
            if match:
                ratios.append(peer["seconds"] / match[0])
        open3d_rows.append({**row, "ratio_rounds": ratios})
    return rows, open3d_rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--model-dir", default=None)
    parser.add_argument("--stem", default="large_clouds")
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--no-open3d", action="store_true", help="leave out the Open3D rows")
    parser.add_argument("--rounds", type=int, default=1,
                        help="run every case this many times, Open3D and ours alternating (median rows)")
    parser.add_argument("--one", nargs=2, metavar=("CASE", "REFINE"), help=argparse.SUPPRESS)  # worker mode
    args = parser.parse_args(argv)
    if args.one:
        case, refine = args.one
        if refine == "open3d":
            print(json.dumps(run_open3d(case, args.threads)))
        elif refine == "placement":
            print(json.dumps(open3d_icp_placement_check(case)))
        else:
            print(json.dumps(run_case(case, None if refine == "none" else refine, args.threads, args.model_dir)))
        return 0
    if args.rounds < 1:
        parser.error("--rounds must be >= 1")
    round_rows, round_open3d_rows = [], []  # per round: our rows, Open3D's rows
    environment = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    for round_index in range(args.rounds):
        rows, open3d_rows = [], []
        for case in args.cases:
            if not args.no_open3d:
                command = [sys.executable, __file__, "--threads", str(args.threads), "--one", case, "open3d"]
                output = subprocess.run(command, capture_output=True, text=True, check=True, env=environment).stdout
                open3d_rows += json.loads(output.strip().splitlines()[-1])["open3d"]
                print(f"round {round_index + 1} {case} Open3D: {open3d_rows[-1]['seconds']:.2f} s, "
                      f"{open3d_rows[-1]['rotation_error_deg']:.2f} deg", flush=True)
            for refine in REFINEMENTS:
                command = [sys.executable, __file__, "--threads", str(args.threads), "--one", case, refine or "none"]
                if args.model_dir:
                    command += ["--model-dir", args.model_dir]
                output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
                rows.append(json.loads(output.strip().splitlines()[-1]))
                print(f"round {round_index + 1} {case} {refine}: {rows[-1]['seconds']:.2f} s, "
                      f"{rows[-1]['peak_rss_mib']:.0f} MiB, {rows[-1]['rotation_error_deg']:.2f} deg", flush=True)
        round_rows.append(rows)
        round_open3d_rows.append(open3d_rows)
    rows, open3d_rows = median_rounds(round_rows, round_open3d_rows)
    placement = []
    if not args.no_open3d:
        command = [sys.executable, __file__, "--one", "merged_120k", "placement"]
        placement = json.loads(
            subprocess.run(
                command, capture_output=True, text=True, check=True, env=environment
            ).stdout.strip().splitlines()[-1]
        )
    write_report(args.stem, markdown(rows, args, open3d_rows, placement),
                 {"command": command_line(), "machine": machine_info(), "rows": rows, "open3d_rows": open3d_rows,
                  "open3d_icp_placement": placement})
    return 0


if __name__ == "__main__":
    sys.exit(main())
