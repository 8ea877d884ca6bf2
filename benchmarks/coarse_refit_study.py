"""Which pose should ``register()`` return without ICP? The estimator's own, or the matches
its verified pose explains, re-fitted (``VerificationConfig.refit_spacings``)?

    python benchmarks/coarse_refit_study.py [--pairs 150] [--spacings 0 1 1.5 2 3]

On validation pairs only (``scan_pairs.py``'s pairs of the validation shapes): each pair is
matched and verified once, with ``register()``'s seed for it (the pair's index), and its chosen
hypothesis then gives one returned pose per setting through the runtime's own
:func:`logdesc_rt.pose_selection.coarse_pose` (0: the estimator's own pose). A pose is right
when its rotation error is < 5 degrees and its translation error < 5 % of the radius; the
verified pose (after verification's short ICP) is counted beside them for reference.

Writes ``benchmarks/results/coarse_refit/coarse_refit_study.{md,json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from common import (  # noqa: E402
    RESULTS,
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_FRACTION,
    command_line,
    machine_info,
    write_report,
)
from scan_pairs import protocol_pairs  # noqa: E402

from logdesc_rt import Registrar  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402
from logdesc_rt.pose_selection import coarse_pose  # noqa: E402


def is_right(pose: np.ndarray, pair) -> bool:
    rotation = rotation_error_deg(pose[:3, :3], pair.T_gt[:3, :3])
    translation = np.linalg.norm(pose[:3, 3] - pair.T_gt[:3, 3]) / pair.scale
    return bool(rotation < SUCCESS_ROTATION_DEG and translation < SUCCESS_TRANSLATION_FRACTION)


def study_pair(registrar: Registrar, pair, spacings: list[float]) -> dict:
    """Whether each setting's returned pose, and the verified pose, is right."""
    matched = registrar.match(pair.source, pair.target)
    result = registrar.register_matches(matched, seed=pair.index)
    if result.verification is None:  # too few matches: register() returns the identity
        return {"index": pair.index, "verified": False, "returned": {str(s): False for s in spacings}}
    chosen = result.verification.best
    correspondences = matched.correspondences
    returned = {
        str(spacing): is_right(coarse_pose(
            chosen, matched.source_points[correspondences[:, 0]], matched.target_points[correspondences[:, 1]],
            matched.matches.confidence, matched.target_points[matched.target_index],
            dataclasses.replace(registrar.config.verification, refit_spacings=spacing),
        ), pair)
        for spacing in spacings
    }
    return {"index": pair.index, "verified": is_right(chosen.verified_transformation, pair), "returned": returned}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=150)
    parser.add_argument("--protocols", nargs="+", default=["scan", "partial", "resampled_partial"])
    parser.add_argument("--spacings", nargs="+", type=float, default=[0.0, 1.0, 1.5, 2.0, 3.0])
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", type=Path, default=RESULTS / "coarse_refit")
    args = parser.parse_args(argv)
    registrar = Registrar(threads=args.threads)
    results = {}
    for protocol in args.protocols:
        rows = [study_pair(registrar, pair, args.spacings) for pair in protocol_pairs("val", protocol, args.pairs)]
        summary = {
            "pairs": len(rows),
            "verified_right": sum(row["verified"] for row in rows),
            "returned_right": {str(s): sum(row["returned"][str(s)] for row in rows) for s in args.spacings},
        }
        results[protocol] = {"summary": summary, "rows": rows}
        print(protocol, summary, flush=True)
    totals = {str(s): sum(r["summary"]["returned_right"][str(s)] for r in results.values()) for s in args.spacings}
    header = [f"{s:g} spacings" if s else "estimator's own (0)" for s in args.spacings]
    table = [
        [protocol, str(r["summary"]["pairs"]), *[str(r["summary"]["returned_right"][str(s)]) for s in args.spacings],
         str(r["summary"]["verified_right"])]
        for protocol, r in results.items()
    ]
    table.append(["all", str(sum(r["summary"]["pairs"] for r in results.values())),
                  *[str(totals[str(s)]) for s in args.spacings],
                  str(sum(r["summary"]["verified_right"] for r in results.values()))])
    markdown = "\n".join([
        "# The pose register() returns without ICP: the estimator's own or its matches re-fitted",
        "",
        f"Command: `{command_line()}`. Machine: {machine_info()}. Validation pairs of "
        "`benchmarks/scan_pairs.py` (validation shapes; never the test split nor the Bunny), "
        "the bundled model, `register()`'s seed per pair. Each column counts the pairs whose returned "
        "pose is right (rotation error < 5 degrees, translation error < 5 % of the radius) when "
        "`coarse_pose` re-fits the matches the chosen hypothesis' verified pose explains within that "
        "many target spacings; the last column is the verified pose itself (after the short ICP), "
        "for reference (`benchmarks/coarse_refit_study.py` docstring).",
        "",
        "| " + " | ".join(["protocol", "pairs", *header, "verified pose"]) + " |",
        "| --- | " + " | ".join("---:" for _ in range(2 + len(header))) + " |",
        *("| " + " | ".join(row) + " |" for row in table),
    ])
    write_report("coarse_refit_study", markdown, results, out=args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
