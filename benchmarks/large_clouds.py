"""End-to-end time and peak memory on large clouds: a real 40k x 40k scan pair and a 200k x 200k pair.

    python benchmarks/large_clouds.py [--threads 2] [--model-dir DIR] [--stem large_clouds]

Cases, each run in a fresh process (so that peak resident memory, ``ru_maxrss``, is the case's
own), with and without point-to-plane ICP on the full clouds:

- ``bunny_40k``: the real Stanford Bunny scans bun000 -> bun045 as they are (about 40k points
  each, metres, their own scanner frames), truth from ``bun.conf``;
- ``merged_200k``: all ten Bunny scans placed in the common frame (about 360k points); the
  source is 200,000 of them and the target another 200,000 (independent uniform draws,
  ``default_rng([SEED, 1])`` / ``[SEED, 2]``), the target moved by a 30 degree turn about a
  skew axis and 0.05 m, then both shifted 1 km from the origin. Timing is the point; the
  error is reported so that a fast wrong answer does not pass for a result.

Quiet machine wanted: nothing else running. Writes benchmarks/results/<stem>.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from common import command_line, machine_info, write_report  # noqa: E402

SEED = 20261130
CASES = ("bunny_40k", "merged_200k")
REFINEMENTS = (None, "point_to_plane")
MERGED_POINTS = 200_000
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
    source = merged[np.random.default_rng([SEED, 1]).choice(len(merged), MERGED_POINTS, replace=False)]
    target = merged[np.random.default_rng([SEED, 2]).choice(len(merged), MERGED_POINTS, replace=False)]
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


def markdown(rows: list[dict], args) -> str:
    stages = ("load", "subsample", "geometry", "descriptors", "matcher", "matching", "pose", "verification",
              "refinement", "evaluation")
    lines = [
        "# Large clouds: end-to-end time and peak memory",
        "",
        f"`{command_line()}`; model `{args.model_dir or 'bundled'}`, {args.threads} onnxruntime threads, "
        "each case in a fresh process. The networks see 1024 points per cloud (farthest-point subsets); "
        "subsampling, verification, ICP and the fitness evaluation read the full clouds.",
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
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--model-dir", default=None)
    parser.add_argument("--stem", default="large_clouds")
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--one", nargs=2, metavar=("CASE", "REFINE"), help=argparse.SUPPRESS)  # worker mode
    args = parser.parse_args(argv)
    if args.one:
        case, refine = args.one
        print(json.dumps(run_case(case, None if refine == "none" else refine, args.threads, args.model_dir)))
        return 0
    rows = []
    for case in args.cases:
        for refine in REFINEMENTS:
            command = [sys.executable, __file__, "--threads", str(args.threads), "--one", case, refine or "none"]
            if args.model_dir:
                command += ["--model-dir", args.model_dir]
            output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
            rows.append(json.loads(output.strip().splitlines()[-1]))
            print(f"{case} {refine}: {rows[-1]['seconds']:.2f} s, {rows[-1]['peak_rss_mib']:.0f} MiB, "
                  f"{rows[-1]['rotation_error_deg']:.2f} deg", flush=True)
    write_report(args.stem, markdown(rows, args), {"command": command_line(), "machine": machine_info(), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
