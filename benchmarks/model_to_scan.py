"""Model to scan: register the Stanford Bunny's reconstructed mesh to each of its real scans.

The user's case of a known object's model (a CAD mesh, a reference mesh) aligned to a scan of
it. The source is the mesh ``reconstruction/bun_zipper.ply`` (35,947 vertices, 69,451
triangles), read as a mesh and sampled on its surface as ``register`` samples a mesh path
(:data:`logdesc_rt.io.DEFAULT_SURFACE_SAMPLES` points, area-weighted, seed 0); the target is
each of the ten real range scans (``data/bun*.ply``, ~40k points, metres, its own scanner
frame). The reconstruction lies in the scans' common frame; the samples are then placed anywhere
(a seeded random rigid motion ``M`` per scan: any rotation, translation up to 0.5 m), as a CAD
model's frame has nothing to do with a scanner's. The true pose is ``inv(T_scan) @ inv(M)``
with ``T_scan`` from ``bun.conf`` (without ``M``, the identity would be right for ``bun000``).

Methods, in the same run on the same clouds (``benchmarks/methods.py``): ``register()`` as a
user calls it (estimator "auto", verified), without and with point-to-plane ICP; Open3D FPFH +
RANSAC, without and with ICP (its parameters tuned on simulated range scans of validation shapes,
``methods.SCAN_TUNING_FILE``: the targets are real scans).
Success: rotation error < 5 deg and translation error < 5 % of the mesh's radius (5.8 mm), the
project's criterion; the translation error is measured where the object lands (the model's centre
moved by the estimate against by the truth). Times are wall time per scan on this machine.

The Bunny is a test set: nothing here is tuned or selected on it.

    python benchmarks/model_to_scan.py [--threads 2] [--out DIR] [--model-dir DIR]

Writes ``<out>/model_to_scan.{md,json}``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import (  # noqa: E402
    DATA_ROOT,
    RESULTS,
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_FRACTION,
    command_line,
    machine_info,
    model_description,
    project_relative,
    write_report,
)
from methods import (  # noqa: E402
    SCAN_TUNING_FILE,
    FpfhParameters,
    MethodRunner,
    open3d_available,
    parameters_dict,
    runnable_methods,
)
from scipy.spatial.transform import Rotation  # noqa: E402

from logdesc_rt.io import DEFAULT_SURFACE_SAMPLES, read_mesh, read_point_cloud, read_stanford_conf  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402

LEARNED = ("logdesc_auto", "logdesc_auto_icp")
CLASSICAL = ("fpfh_ransac", "fpfh_ransac_icp")
LABELS = {
    "logdesc_auto": "logdesc-rt register()",
    "logdesc_auto_icp": "logdesc-rt register() + ICP",
    "fpfh_ransac": "Open3D FPFH + RANSAC",
    "fpfh_ransac_icp": "Open3D FPFH + RANSAC + ICP",
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--data-root", type=Path, default=DATA_ROOT)
    parser.add_argument("--model-dir", type=Path, default=None, help="an exported model (default: the bundled one)")
    args = parser.parse_args(argv)

    folder = args.data_root / "stanford_bunny"
    mesh = read_mesh(folder / "reconstruction" / "bun_zipper.ply")
    source = mesh.sample(DEFAULT_SURFACE_SAMPLES, seed=0)
    radius = float(np.linalg.norm(source - source.mean(axis=0), axis=1).max())
    poses = read_stanford_conf(folder / "data" / "bun.conf")
    methods = runnable_methods(LEARNED + CLASSICAL)
    runner = MethodRunner(methods, FpfhParameters.tuned(SCAN_TUNING_FILE), threads=args.threads,
                          model_dir=args.model_dir)

    rows = []
    for index, (scan_name, scan_pose) in enumerate(poses.items()):
        target = read_point_cloud(folder / "data" / scan_name)
        rng = np.random.default_rng([7, index])
        motion = np.eye(4)
        motion[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        motion[:3, 3] = rng.uniform(-0.5, 0.5, size=3)
        placed = source @ motion[:3, :3].T + motion[:3, 3]
        truth = np.linalg.inv(scan_pose) @ np.linalg.inv(motion)
        centre = placed.mean(axis=0)
        results = runner.run(placed, target, seed=0)
        for method, result in results.items():
            T = np.asarray(result.transformation)
            rotation = float(rotation_error_deg(T[:3, :3], truth[:3, :3]))
            # Where the object lands: its centre under the estimate against under the truth (a
            # difference of translation vectors would count rotation error times the distance
            # of the placed model from the origin).
            translation = float(np.linalg.norm(T[:3, :3] @ centre + T[:3, 3] - truth[:3, :3] @ centre - truth[:3, 3]))
            rows.append({
                "scan": scan_name, "method": method, "target_points": len(target),
                "rotation_error_deg": rotation, "translation_error_mm": 1e3 * translation,
                "success": rotation < SUCCESS_ROTATION_DEG and translation < SUCCESS_TRANSLATION_FRACTION * radius,
                "flagged_success": result.flagged_success, "seconds": float(result.seconds), "failed": result.failed,
            })
            print(f"{scan_name} {method:18s} L_R {rotation:7.2f} deg  L_t {1e3 * translation:7.2f} mm  "
                  f"{result.seconds:6.2f} s", flush=True)

    summary = {}
    for method in methods:
        mine = [row for row in rows if row["method"] == method]
        summary[method] = {
            "success": float(np.mean([row["success"] for row in mine])),
            "median_rotation_error_deg": float(np.median([row["rotation_error_deg"] for row in mine])),
            "median_seconds": float(np.median([row["seconds"] for row in mine])),
        }
        flagged = [row for row in mine if row["flagged_success"]]
        if flagged or method in LEARNED:
            summary[method]["flagged"] = len(flagged)
            summary[method]["right_when_flagged"] = (
                float(np.mean([row["success"] for row in flagged])) if flagged else None)

    lines = [
        "# Model to scan: the Bunny's mesh registered to each real scan",
        "",
        f"Source: `reconstruction/bun_zipper.ply` read as a mesh ({len(mesh.vertices):,} vertices, "
        f"{len(mesh.faces):,} triangles), {DEFAULT_SURFACE_SAMPLES} points sampled on its surface (area-weighted, "
        "seed 0), as `register()` reads a mesh file, then placed anywhere (a seeded random rigid motion per scan). "
        "Target: each real scan (~40k points, metres, its own frame). "
        "Truth: `inv(T_scan) @ inv(M)` (`bun.conf`, the motion M). "
        "L_t: the model's centre moved by the estimate against by the truth. "
        f"Success: L_R < {SUCCESS_ROTATION_DEG:g} deg and L_t < "
        f"{SUCCESS_TRANSLATION_FRACTION:.0%} of the mesh's radius "
        f"({1e3 * SUCCESS_TRANSLATION_FRACTION * radius:.1f} mm).",
        "",
        f"Model: {model_description(args.model_dir)}",
        "",
        f"Open3D parameters (network units, object radius = 1; `{project_relative(SCAN_TUNING_FILE)}`, chosen by "
        f"`tune_open3d.py` on simulated scans of validation shapes): {parameters_dict(runner.parameters)}",
        "",
        "| method | success | median L_R (deg) | median s / scan | flagged success | right when flagged |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, row in summary.items():
        flagged = row.get("flagged")
        right = row.get("right_when_flagged")
        lines.append(
            f"| {LABELS[method]} | {row['success']:.0%} | {row['median_rotation_error_deg']:.2f} | "
            f"{row['median_seconds']:.2f} | {'' if flagged is None else flagged} | "
            f"{'' if right is None else f'{right:.0%}'} |")
    lines += ["", "Per scan (L_R deg / L_t mm / s):", "",
              "| scan | " + " | ".join(LABELS[m] for m in methods) + " |",
              "| --- | " + " | ".join("---:" for _ in methods) + " |"]
    for scan_name in poses:
        cells = []
        for method in methods:
            row = next(r for r in rows if r["scan"] == scan_name and r["method"] == method)
            mark = "" if row["success"] else " ✗"
            cells.append(f"{row['rotation_error_deg']:.2f} / {row['translation_error_mm']:.1f} / "
                         f"{row['seconds']:.2f}{mark}")
        lines.append(f"| {scan_name} | " + " | ".join(cells) + " |")
    lines += ["", f"Command: `{command_line()}`", ""]
    if not open3d_available():
        lines.append("Open3D is not installed: its rows are missing.")
    payload = {"command": command_line(), "machine": machine_info(), "summary": summary, "rows": rows,
               "surface_samples": DEFAULT_SURFACE_SAMPLES, "mesh_radius_m": radius}
    md, _ = write_report("model_to_scan", "\n".join(lines), payload, args.out)
    print(f"wrote {md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
