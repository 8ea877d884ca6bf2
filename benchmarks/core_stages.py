"""Per-stage CPU timings of the torch-free core on 1024-point clouds.

Measures, for real ModelNet10 test shapes (or a synthetic sphere when the shared data is
absent): the kNN query, PCA features, umbrella normals, edge features, the whole
``compute_geometry``, log-Sinkhorn on a 1024 x 1024 score matrix, and FSR on 1024 matches.
Reports the median and the 90th percentile over repeats, in milliseconds.

    python benchmarks/core_stages.py [--shapes 20] [--repeats 10]

Writes benchmarks/results/core_stages.md and .json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from logdesc_rt import compute_geometry  # noqa: E402
from logdesc_rt.config import PAPER_GEOMETRY  # noqa: E402
from logdesc_rt.geometry import drop_self, edge_features, nearest_neighbours, pca_features, umbrella_normals  # noqa: E402
from logdesc_rt.matching import sinkhorn_matches  # noqa: E402
from logdesc_rt.pose import FsrConfig, fsr  # noqa: E402

SHARED_DATA = ROOT.parent / "shared" / "data"


def load_clouds(count: int) -> tuple[list[np.ndarray], str]:
    """Up to ``count`` ModelNet10 test shapes of 1024 points, or a sphere if data is missing."""
    path = SHARED_DATA / "modelnet10_hdf5_1024" / "ply_data_test0.h5"
    try:
        import h5py

        with h5py.File(path, "r") as handle:
            shapes = handle["data"][:count].astype(np.float64)
        return list(shapes), f"ModelNet10 test shapes 0..{count - 1} ({path.name})"
    except (ImportError, OSError):
        index = np.arange(1024) + 0.5
        polar, azimuth = np.arccos(1 - 2 * index / 1024), np.pi * (1 + 5**0.5) * index
        sphere = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], 1)
        return [sphere], "synthetic unit sphere (shared data not found)"


def time_ms(function, repeats: int) -> list[float]:
    function()  # warm-up
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args()

    config = PAPER_GEOMETRY  # the stages below are the paper geometry's (umbrella normals, its edges)
    clouds, source = load_clouds(args.shapes)
    stages: dict[str, list[float]] = {}

    def record(name, function):
        stages.setdefault(name, []).extend(time_ms(function, args.repeats))

    rng = np.random.default_rng(0)
    for points in clouds:
        neighbours = nearest_neighbours(points, config.pca_max_neighbours)
        pca = pca_features(points, config.pca_radius, config.pca_max_neighbours, config.pca_min_neighbours, neighbours)
        index = drop_self(neighbours[1], config.umbrella_neighbours)
        normals = umbrella_normals(points, index, pca.lrf, config.umbrella_area_temperature)
        shape = np.stack([pca.anisotropy, pca.planarity, pca.omnivariance], axis=1)
        record("kNN (128, pykdtree)", lambda: nearest_neighbours(points, config.pca_max_neighbours))
        record("PCA features + LRF", lambda: pca_features(points, config.pca_radius, config.pca_max_neighbours, config.pca_min_neighbours, neighbours))
        record("umbrella normals", lambda: umbrella_normals(points, index, pca.lrf, config.umbrella_area_temperature))
        record("edge features", lambda: edge_features(points, shape, pca.lrf, normals, index))
        record("compute_geometry (all of the above)", lambda: compute_geometry(points, config))

        # Matching and pose on a synthetic but realistic input: a noisy permutation score matrix.
        permutation = rng.permutation(len(points))
        scores = rng.normal(scale=1.0, size=(len(points), len(points)))
        scores[np.arange(len(points)), permutation] += 6.0
        # What the runtime runs: the float32 scaling reader, matches included.
        record("Sinkhorn 1024x1024, 50 it., mutual matches", lambda: sinkhorn_matches(scores, 1.0, 50))
        # FSR on 1024 putative matches, 30 % of them wrong.
        matched_target = points @ np.diag([1.0, -1.0, -1.0]) + 0.1 + rng.normal(scale=0.01, size=points.shape)
        wrong = rng.random(len(points)) < 0.3
        matched_target[wrong] = rng.uniform(-1.0, 1.0, size=(wrong.sum(), 3))
        record("FSR on 1024 matches (30 % wrong)", lambda: fsr(points, matched_target, None, FsrConfig()))

    rows = []
    for name, samples in stages.items():
        rows.append(
            {
                "stage": name,
                "median_ms": statistics.median(samples),
                "p90_ms": float(np.percentile(samples, 90)),
                "samples": len(samples),
            }
        )
    machine = {
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
    report = {"data": source, "points_per_cloud": int(len(clouds[0])), "machine": machine, "stages": rows,
              "command": "python benchmarks/core_stages.py " + " ".join(sys.argv[1:])}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "core_stages.json").write_text(json.dumps(report, indent=2))
    lines = [
        "# Core stage timings (CPU, one 1024-point cloud)",
        "",
        f"Data: {source}. Machine: {machine}. Command: `{report['command']}`.",
        "",
        "| stage | median ms | p90 ms | samples |",
        "| --- | ---: | ---: | ---: |",
    ]
    lines += [f"| {r['stage']} | {r['median_ms']:.2f} | {r['p90_ms']:.2f} | {r['samples']} |" for r in rows]
    (args.out / "core_stages.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
