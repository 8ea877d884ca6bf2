"""Refinement backends: the package's ICP against small_gicp and Open3D, same pairs, same starts.

Issue 24 asks whether small_gicp (pip ``small-gicp``, MIT: multithreaded point-to-plane ICP
and GICP) refines faster than ``logdesc_rt.refinement.icp`` at equal accuracy. Each case is a
real pair with ground truth, started from the truth perturbed by a seeded rigid motion
(rotation ``--start-deg`` about a random axis, translation ``--start-fraction`` of the radius
in a random direction), the job ICP has after a right coarse pose:

- Bunny: the 10 neighbouring real scan pairs (bun000 -> bun045 ...; ~40k x 40k, metres), truth
  from ``bun.conf``.
- 200k: the Bunny's mesh sampled to 200,000 points twice (different seeds, the second moved),
  the large-cloud size of ``large_clouds.py``.

Every backend gets the correspondence distance ``register(refine=...)`` uses (5 % of the
larger radius), 30 iterations at most, no downsampling (small_gicp: convergence at 1e-5 rad and 1e-5
of the distance), ``--threads`` threads where it has
them. Ours runs as ``register()`` runs it (``refinement.refine_pose`` with the default
``RefinementConfig``: adaptive distance halving, iterating on a seeded subset of at most
20,000 source points against the whole target); the others on every point, in one stage.
Rotation / translation errors are to the truth; time is wall time per pair.

    python benchmarks/icp_backends.py [--threads 2] [--out DIR]

Writes ``<out>/icp_backends.{md,json}``. Backends that are not installed are left out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import DATA_ROOT, RESULTS, command_line, machine_info, write_report  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from logdesc_rt.config import RefinementConfig  # noqa: E402
from logdesc_rt.io import read_mesh, read_point_cloud, read_stanford_conf  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402
from logdesc_rt.refinement import refine_pose  # noqa: E402

NEIGHBOURS = ("bun000", "bun045", "bun090", "bun180", "bun270", "bun315", "bun000")
EXTRA_PAIRS = (("top2", "top3"), ("chin", "bun000"), ("ear_back", "bun180"))


def _perturbation(rng: np.random.Generator, degrees: float, offset: float) -> np.ndarray:
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix()
    motion[:3, 3] = offset * direction / np.linalg.norm(direction)
    return motion


def _ours(source, target, initial, distance, threads):
    return refine_pose(source, target, initial, distance, RefinementConfig(method="point_to_plane")).transformation


def _small_gicp(kind: str):
    def run(source, target, initial, distance, threads):
        import small_gicp

        # Full clouds, as ours: no voxel downsampling (its one-call API requires a voxel > 0), so
        # clouds, KD-trees and normals / covariances are built here (timed with the rest).
        clouds = []
        for points in (target, source):
            cloud = small_gicp.PointCloud(np.ascontiguousarray(points, dtype=np.float64))
            tree = small_gicp.KdTree(cloud, num_threads=threads)
            small_gicp.estimate_normals_covariances(cloud, tree, num_neighbors=20, num_threads=threads)
            clouds.append((cloud, tree))
        (target_cloud, target_tree), (source_cloud, _) = clouds
        result = small_gicp.align(target_cloud, source_cloud, target_tree, initial, registration_type=kind,
                                  max_correspondence_distance=distance, num_threads=threads,
                                  max_iterations=RefinementConfig.max_iterations,
                                  rotation_epsilon=1e-5, translation_epsilon=1e-5 * distance)
        return np.asarray(result.T_target_source)

    return run


def _open3d(source, target, initial, distance, threads):
    import open3d as o3d

    registration = o3d.pipelines.registration
    source_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    target_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    target_cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=20))
    result = registration.registration_icp(
        source_cloud, target_cloud, distance, initial, registration.TransformationEstimationPointToPlane(),
        registration.ICPConvergenceCriteria(max_iteration=RefinementConfig.max_iterations))
    return np.asarray(result.transformation)


def backends() -> dict:
    found = {"logdesc-rt icp (point-to-plane, adaptive, <= 20k source points)": _ours}
    try:
        import small_gicp  # noqa: F401

        found["small_gicp PLANE_ICP"] = _small_gicp("PLANE_ICP")
        found["small_gicp GICP"] = _small_gicp("GICP")
    except ImportError:
        pass
    try:
        import open3d  # noqa: F401

        found["Open3D point-to-plane ICP"] = _open3d
    except ImportError:
        pass
    return found


def cases(data_root: Path):
    folder = data_root / "stanford_bunny"
    poses = read_stanford_conf(folder / "data" / "bun.conf")
    pairs = list(zip(NEIGHBOURS, NEIGHBOURS[1:])) + list(EXTRA_PAIRS)
    for first, second in pairs:
        source = read_point_cloud(folder / "data" / f"{first}.ply")
        target = read_point_cloud(folder / "data" / f"{second}.ply")
        truth = np.linalg.inv(poses[f"{second}.ply"]) @ poses[f"{first}.ply"]
        yield f"{first} -> {second}", "Bunny 40k", source, target, truth
    mesh = read_mesh(folder / "reconstruction" / "bun_zipper.ply")
    rng = np.random.default_rng(200)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    truth[:3, 3] = rng.uniform(-0.2, 0.2, size=3)
    source = mesh.sample(200_000, seed=1)
    target = mesh.sample(200_000, seed=2) @ truth[:3, :3].T + truth[:3, 3]
    yield "mesh 200k -> 200k", "200k", source, target, truth


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--start-deg", type=float, default=3.0)
    parser.add_argument("--start-fraction", type=float, default=0.03)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--data-root", type=Path, default=DATA_ROOT)
    args = parser.parse_args(argv)
    methods = backends()
    rows = []
    for index, (name, group, source, target, truth) in enumerate(cases(args.data_root)):
        radius = max(np.linalg.norm(cloud - cloud.mean(axis=0), axis=1).max() for cloud in (source, target))
        distance = RefinementConfig.distance_fraction * radius
        start = truth @ _perturbation(np.random.default_rng([24, index]), args.start_deg,
                                      args.start_fraction * radius)
        centre = source.mean(axis=0)
        for method, run in methods.items():
            began = time.perf_counter()
            pose = run(source, target, start, distance, args.threads)
            seconds = time.perf_counter() - began
            rotation = float(rotation_error_deg(pose[:3, :3], truth[:3, :3]))
            translation = float(
                np.linalg.norm(pose[:3, :3] @ centre + pose[:3, 3] - truth[:3, :3] @ centre - truth[:3, 3])
            )
            rows.append({"pair": name, "group": group, "method": method, "rotation_error_deg": rotation,
                         "translation_error_fraction": translation / radius, "seconds": seconds,
                         "points": [len(source), len(target)]})
            print(f"{name:22s} {method:42s} {rotation:7.3f} deg {1e3 * translation:7.2f} mm {seconds:6.2f} s",
                  flush=True)

    lines = ["# Refinement backends: our ICP against small_gicp and Open3D", "",
             f"Start: the truth perturbed by {args.start_deg:g} deg and {args.start_fraction:.0%} of the radius "
             "(seeded); correspondence distance 5 % of the larger radius; 30 iterations at most; no downsampling; "
             f"{args.threads} threads. Errors to the truth (translation: where the source's centre lands, as a "
             "fraction of the radius).", "",
             "| clouds | method | median rotation error (deg) | median translation error (% radius) | "
             "median s / pair | worst rotation error (deg) |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    summary = {}
    for group in dict.fromkeys(row["group"] for row in rows):
        for method in methods:
            mine = [row for row in rows if row["group"] == group and row["method"] == method]
            entry = {
                "pairs": len(mine),
                "median_rotation_error_deg": float(np.median([row["rotation_error_deg"] for row in mine])),
                "median_translation_error_fraction": float(
                    np.median([row["translation_error_fraction"] for row in mine])
                ),
                "median_seconds": float(np.median([row["seconds"] for row in mine])),
                "worst_rotation_error_deg": float(np.max([row["rotation_error_deg"] for row in mine])),
            }
            summary[f"{group} / {method}"] = entry
            lines.append(f"| {group} ({len(mine)}) | {method} | {entry['median_rotation_error_deg']:.3f} | "
                         f"{100 * entry['median_translation_error_fraction']:.3f} | {entry['median_seconds']:.3f} | "
                         f"{entry['worst_rotation_error_deg']:.3f} |")
    lines += ["", f"Command: `{command_line()}`", ""]
    md, _ = write_report("icp_backends", "\n".join(lines),
                         {"command": command_line(), "machine": machine_info(), "summary": summary, "rows": rows},
                         args.out)
    print(f"wrote {md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
