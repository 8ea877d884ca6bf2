"""Does the matcher earn its cost? The learned descriptors alone against descriptors + matcher.

    python benchmarks/matcher_study.py [--pairs 60] [--protocols scan partial] [--threads 2]

Issue 23 asks whether the normal-encoder transformer (the matcher network, about half of the
networks' time) pays on scan-like pairs; the paper's own MVP-RG table has its descriptor with
RANSAC ahead of the full matcher. On the same validation pairs (``--split val`` of
``benchmarks/scan_pairs.py``: v4's validation shapes, never the Bunny), each pair runs the
shipped model's descriptors once, then two ways of reading matches from them:

- ``matcher``: what ``register()`` does (matcher network, Sinkhorn with the learned dustbin,
  mutual test);
- ``descriptors``: mutual nearest neighbours of the descriptors (cosine similarity), the
  similarity as each match's confidence, no matcher network.

Both go through the same candidate poses and verification (``register_matched``, no ICP, the
model's calibrated flag). The flag was calibrated on matcher confidences, so only the pose
success is compared (rotation < 5 deg and translation < 5 % of the object's radius), with the
mutual match counts and the share of matches within 5 % of the radius of their true partner.
The descriptor-only reading leaves out the matcher's time (the matcher column of
``latency_v4.md``); it is not retrained for it, so this bounds what a descriptor-only model
would start from, not what it could reach.

Writes ``benchmarks/results/matcher_study.{md,json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from common import command_line, machine_info, write_report  # noqa: E402
from methods import mutual_nearest_descriptors  # noqa: E402
from scan_pairs import protocol_pairs  # noqa: E402

from logdesc_rt import Registrar  # noqa: E402
from logdesc_rt.matching import Matches  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402
from logdesc_rt.pose_selection import register_matched  # noqa: E402

SUCCESS_DEG, SUCCESS_FRACTION = 5.0, 0.05


def descriptor_matches(source_descriptors: np.ndarray, target_descriptors: np.ndarray) -> Matches:
    """Mutual nearest neighbours of (N, d) / (M, d) unit descriptors (the benchmarks' one
    reading, ``methods.mutual_nearest_descriptors``: nearest in distance is most similar for
    unit vectors); confidence = their cosine."""
    assignment = mutual_nearest_descriptors(source_descriptors, target_descriptors)
    source_index = np.flatnonzero(assignment >= 0)
    target_index = assignment[source_index]
    cosine = np.sum(source_descriptors[source_index] * target_descriptors[target_index], axis=1)
    confidence = np.clip(cosine.astype(np.float64), 1e-6, 1.0)
    return Matches(source_index=source_index.astype(np.int64), target_index=target_index.astype(np.int64),
                   confidence=confidence)


def judged(pair, result) -> dict:
    rotation = float(rotation_error_deg(result.transformation[:3, :3], pair.T_gt[:3, :3]))
    translation = float(np.linalg.norm(result.transformation[:3, 3] - pair.T_gt[:3, 3]))
    return {"rotation_error_deg": rotation, "right": rotation < SUCCESS_DEG and translation < SUCCESS_FRACTION * pair.scale,
            "matches": len(result.correspondences)}


def match_precision(pair, matched, correspondences: np.ndarray) -> float:
    """Share of matches whose source point, moved by the truth, lies within 5 % of the radius
    of its matched target point (NaN without matches)."""
    if len(correspondences) == 0:
        return float("nan")
    source = matched.prepared.source_points[correspondences[:, 0]]
    target = matched.prepared.target_points[correspondences[:, 1]]
    moved = source @ pair.T_gt[:3, :3].T + pair.T_gt[:3, 3]
    return float(np.mean(np.linalg.norm(moved - target, axis=1) < SUCCESS_FRACTION * pair.scale))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=60)
    parser.add_argument("--protocols", nargs="+", default=["scan", "partial"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--stem", default="matcher_study")
    args = parser.parse_args(argv)
    registrar = Registrar(threads=args.threads)
    rows = []
    for protocol in args.protocols:
        for pair in protocol_pairs("val", protocol, args.pairs):
            matched = registrar.match(pair.source, pair.target)
            config = registrar.call_config()
            for reading in ("matcher", "descriptors"):
                if reading == "descriptors":
                    matches = descriptor_matches(matched.source_descriptors, matched.target_descriptors)
                    candidate = dataclasses.replace(matched, matches=matches)
                else:
                    candidate = matched
                result = register_matched(candidate, config)
                rows.append({"protocol": protocol, "pair": pair.index, "reading": reading, **judged(pair, result),
                             "match_precision": match_precision(pair, candidate, result.correspondences)})
        print(protocol, "done", flush=True)

    lines = [
        "# The matcher network against the descriptors alone (validation pairs)",
        "",
        f"`{command_line()}`; the bundled model; {args.pairs} validation pairs per protocol (v4's validation "
        "shapes, `scan_pairs.py --split val`'s pairs); no ICP. Right: rotation < 5 deg and translation < 5 % of "
        "the radius. Match precision: median share of mutual matches within 5 % of the radius of their true partner.",
        "",
        "| protocol | matches read by | right | median mutual matches | median match precision |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    summary = {}
    for protocol in args.protocols:
        for reading in ("matcher", "descriptors"):
            chosen = [r for r in rows if r["protocol"] == protocol and r["reading"] == reading]
            right = float(np.mean([r["right"] for r in chosen]))
            matches = float(np.median([r["matches"] for r in chosen]))
            precision = float(np.nanmedian([r["match_precision"] for r in chosen]))
            summary[f"{protocol}/{reading}"] = {"right": right, "median_matches": matches, "median_match_precision": precision}
            lines.append(f"| {protocol} | {reading} | {100 * right:.1f} % | {matches:.0f} | {100 * precision:.1f} % |")
    write_report(args.stem, "\n".join(lines), {"command": command_line(), "machine": machine_info(),
                                               "summary": summary, "rows": rows})
    print("\n".join(lines[-2 - 2 * len(args.protocols):]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
