"""Time and peak memory of one training step on the CPU (forward, loss, backward, Adam).

    python -m training.profile_step --preset small --batch-size 8 --points 1024 [--threads 2] [--protocol partial]

Builds one batch of pairs (``--protocol``, noisy by default; ``--points`` per source cloud) from synthetic
shapes, runs a warm-up step and a measured step, and prints the step time and the process's
peak resident memory (``ru_maxrss``) before and after, in a fresh process per call so peaks
do not mix. ``--json`` prints one JSON line instead.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch
from torch.utils.data import default_collate

from logdesc_rt.geometry import compute_geometry
from logdesc_rt.synthetic import make_pair
from training.config import ModelConfig
from training.data import pair_to_sample
from training.losses import assignment_nll, descriptor_infonce
from training.model import LoGDescMatcher
from training.train import INPUT_NAMES


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def synthetic_shape(rng: np.random.Generator, points: int) -> np.ndarray:
    """A random ellipsoid-like closed surface with bumps, inside the unit sphere."""
    direction = rng.normal(size=(points, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    bumps = 1.0 + 0.15 * np.sin(3 * direction[:, 0] + rng.uniform(0, 6)) * np.cos(2 * direction[:, 1])
    shape = direction * bumps[:, None] * rng.uniform(0.5, 1.0, size=3)
    return shape / np.linalg.norm(shape, axis=1).max()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="small")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--protocol", default="noisy", choices=["clean", "noisy", "partial"],
                        help="pair protocol (partial: 75 %% of --points survive in each cloud)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    config = ModelConfig.preset(args.preset)
    geometry = config.geometry()  # the geometry this network reads
    samples = []
    for _ in range(args.batch_size):
        pair = make_pair(synthetic_shape(rng, 1024), args.protocol, rng, points_per_cloud=args.points)
        samples.append(pair_to_sample(
            pair, compute_geometry(pair.source_network, geometry), compute_geometry(pair.target_network, geometry)
        ))
    batch = default_collate(samples)
    model = LoGDescMatcher(config)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def step() -> float:
        start = time.perf_counter()
        outputs = model(*(batch[name] for name in INPUT_NAMES))
        loss = assignment_nll(outputs["log_assignment"], batch["gt_match_src"], batch["gt_match_tgt"])
        loss = loss + 0.1 * descriptor_infonce(
            outputs["descriptors_src"], outputs["descriptors_tgt"], batch["gt_match_src"]
        )
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return time.perf_counter() - start

    before = peak_rss_mib()
    warm_up = step()
    measured = step()
    report = {
        "preset": args.preset,
        "batch_size": args.batch_size,
        "points_per_cloud": args.points,
        "protocol": args.protocol,
        "threads": torch.get_num_threads(),
        "warm_up_step_s": round(warm_up, 2),
        "step_s": round(measured, 2),
        "peak_rss_before_step_mib": round(before),
        "peak_rss_mib": round(peak_rss_mib()),
        "torch": torch.__version__,
    }
    print(json.dumps(report) if args.json else "\n".join(f"{k}: {v}" for k, v in report.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
