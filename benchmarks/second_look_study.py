"""Would the second look find the right pose where the first look's candidates are all wrong?

    python benchmarks/second_look_study.py [--pairs 60] [--protocols scan partial resampled_partial]

On validation pairs only (``scan_pairs.py``'s pairs of the validation shapes): each pair is
matched once, verified without the second look (``turn_over_axes=0``, no second consensus), and
its leading refined pose (the highest fitness + match agreement) then gets every alternative at
full cost: the six turn-overs each refined by the verifier's short ICP (no screening), and all
five candidate estimators on the matches it leaves unexplained, each refined. A pair counts for
a kind of alternative when the leading pose is wrong and one of its alternatives is right
(rotation error < 5 degrees after the short ICP). This asks whether a right hypothesis exists,
not whether the calibrated flag would choose it (``calibrate_success.py fit`` and
``scan_pairs.py`` measure that); the runtime screens the turn-overs and runs RANSAC alone on
the unexplained matches, at a fraction of this cost.

Writes ``benchmarks/results/second_look/second_look_study.{md,json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from common import RESULTS, command_line, machine_info, write_report  # noqa: E402
from scan_pairs import protocol_pairs  # noqa: E402

from logdesc_rt import Registrar  # noqa: E402
from logdesc_rt.config import CANDIDATE_ESTIMATORS  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402
from logdesc_rt.pose.candidates import unexplained_candidate_poses  # noqa: E402
from logdesc_rt.verification import PoseVerifier  # noqa: E402

RIGHT_DEG = 5.0


def study_pair(registrar: Registrar, pair) -> dict:
    """The leading pose's error and the best error among each kind of alternative (degrees)."""
    matched = registrar.match(pair.source, pair.target)
    config = matched.config
    first_look = dataclasses.replace(config.verification, turn_over_axes=0, second_consensus=())
    correspondences = matched.correspondences
    verifier = PoseVerifier(
        matched.source_points, matched.target_points,
        matched.source_points[correspondences[:, 0]], matched.target_points[correspondences[:, 1]],
        matched.matches.confidence, matched.normalization.scale, first_look,
    )
    verification = verifier.verify(matched.candidates(config))
    refined = [h.verified_transformation for h in verification.hypotheses if h.refined]
    leading = max(refined, key=verifier.quick_score)

    def error(pose: np.ndarray) -> float:
        return float(rotation_error_deg(pose[:3, :3], pair.T_gt[:3, :3]))

    # Every turn-over of the runtime's set (six axes in the source's principal plane), each refined.
    turn_overs = PoseVerifier(
        matched.source_points, matched.target_points, verifier.source_matched, verifier.target_matched,
        verifier.confidences, matched.normalization.scale, config.verification,
    ).turn_overs
    turned = [error(verifier.refine(leading @ turn)) for turn in turn_overs]
    normalization = matched.normalization
    unexplained = {
        name: error(verifier.refine(normalization.pose_to_user_frame(pose)))
        for name, pose in unexplained_candidate_poses(
            *matched.matched_network_points(), normalization.pose_to_network_frame(leading),
            config.verification.match_tolerance, config.fsr, config.ransac, config.verification.top_k_fraction,
            CANDIDATE_ESTIMATORS,
        )
    }
    return {
        "name": pair.name, "index": pair.index, "leading_deg": error(leading),
        "turned_over_deg": min(turned, default=float("inf")),
        "unexplained_deg": {name: value for name, value in unexplained.items()},
    }


def summarize(rows: list[dict]) -> dict:
    wrong = [row for row in rows if row["leading_deg"] >= RIGHT_DEG]

    def rescued(row, kinds) -> bool:
        errors = [row["turned_over_deg"]] if "turned_over" in kinds else []
        errors += [row["unexplained_deg"].get(name, float("inf")) for name in kinds if name != "turned_over"]
        return min(errors, default=float("inf")) < RIGHT_DEG

    kinds = {
        "turn-overs (6, each refined)": ("turned_over",),
        "RANSAC on the unexplained matches": ("ransac",),
        "all five estimators on them": CANDIDATE_ESTIMATORS,
        "both kinds, all of them": ("turned_over", *CANDIDATE_ESTIMATORS),
    }
    return {
        "pairs": len(rows),
        "leading_right": len(rows) - len(wrong),
        "rescued": {label: sum(rescued(row, chosen) for row in wrong) for label, chosen in kinds.items()},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=60)
    parser.add_argument("--protocols", nargs="+", default=["scan", "partial", "resampled_partial"])
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--out", type=Path, default=RESULTS / "second_look")
    args = parser.parse_args(argv)
    registrar = Registrar(threads=args.threads)
    results = {}
    for protocol in args.protocols:
        rows = [study_pair(registrar, pair) for pair in protocol_pairs("val", protocol, args.pairs)]
        results[protocol] = {"summary": summarize(rows), "rows": rows}
        print(protocol, results[protocol]["summary"], flush=True)
    labels = list(next(iter(results.values()))["summary"]["rescued"])
    table = [
        [protocol, str(r["summary"]["pairs"]), str(r["summary"]["leading_right"]),
         *[str(r["summary"]["rescued"][label]) for label in labels]]
        for protocol, r in results.items()
    ]
    markdown = "\n".join([
        "# The second look: does a right alternative exist where the leading pose is wrong?",
        "",
        f"Command: `{command_line()}`. Machine: {machine_info()}. Validation pairs of "
        "`benchmarks/scan_pairs.py` (validation shapes; never the test split nor the Bunny). "
        "Leading pose: the first look's best refined candidate by fitness + match agreement. "
        f"Right: rotation error < {RIGHT_DEG:g} degrees after the verifier's short ICP. "
        "The columns count the pairs with a wrong leading pose and a right alternative of that kind "
        "(`benchmarks/second_look_study.py` docstring).",
        "",
        "| " + " | ".join(["protocol", "pairs", "leading pose right", *labels]) + " |",
        "| --- | " + " | ".join("---:" for _ in range(2 + len(labels))) + " |",
        *("| " + " | ".join(row) + " |" for row in table),
    ])
    write_report("second_look_study", markdown, results, out=args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
