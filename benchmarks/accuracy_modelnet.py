"""Accuracy on the ModelNet10 test split: logdesc-rt against its own variants and Open3D.

All 908 test shapes (fixed seed, the pairs of ``training/evaluate.py``), protocols clean,
noisy and noisy + partial (and, on request, the resampled ones, whose two clouds share no
sample, like real scan pairs), methods of ``benchmarks/methods.py``: logdesc-rt with FSR / SVD /
RANSAC on its matches, its descriptors alone with Open3D RANSAC / FGR, Open3D FPFH + RANSAC /
FGR (parameters tuned on validation pairs by ``tune_open3d.py``), and point-to-plane ICP from
the identity. The paper's published ModelNet40 figures are shown beside ours, labelled.

    python benchmarks/accuracy_modelnet.py [--pairs 908] [--methods ...] [--threads 2]
        [--model-dir DIR --out OTHER_DIR]   # a candidate model instead of the bundled one

Per-pair results go to ``benchmarks/results/modelnet10_accuracy_pairs.jsonl`` as they come,
so an interrupted run resumes; ``--fresh`` starts over. The repository keeps them gzipped
(``.jsonl.gz``, unpacked on the next run), so the report can be rebuilt without recomputing. Writes
``benchmarks/results/modelnet10_accuracy.{md,json}`` and ``modelnet10_error_cdf.png``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import (  # noqa: E402
    ANY_RELATIVE_SUFFIX,
    DEFAULT_SEED,
    PUBLISHED,
    RESULTS,
    ROTATED_SUFFIX,
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_FRACTION,
    ResultCache,
    bundled_model_id,
    command_line,
    is_success,
    machine_info,
    markdown_table,
    model_description,
    modelnet10_test_pairs,
    pair_record,
    project_relative,
    summarize,
    write_report,
)
from methods import (  # noqa: E402
    ALL_METHODS,
    REFINED_FROM,
    REFINEMENT_ID,
    TUNING_FILE,
    FpfhParameters,
    MethodResult,
    MethodRunner,
    parameters_dict,
    refine_pose,
    runnable_methods,
)
from plots import error_cdf  # noqa: E402
from tqdm import tqdm  # noqa: E402

from logdesc_rt.synthetic import PAPER_PROTOCOLS, RESAMPLED_PROTOCOLS  # noqa: E402

PROTOCOLS = PAPER_PROTOCOLS  # the default run
# Beyond the paper: each cloud its own half of the shape's samples, so no point has a twin in the
# other cloud, as in real scan pairs (logdesc_rt.synthetic; correspondences by geometry).
RESAMPLED = RESAMPLED_PROTOCOLS
ROTATED = tuple(f"{protocol}{ROTATED_SUFFIX}" for protocol in PROTOCOLS + RESAMPLED)
ANY_RELATIVE = tuple(f"{protocol}{ANY_RELATIVE_SUFFIX}" for protocol in PROTOCOLS + RESAMPLED)
PROTOCOL_TITLES = {
    "clean": "clean",
    "noisy": "noisy (full overlap)",
    "partial": "noisy + partial (768 of 1024)",
    "resampled": "noisy, each cloud its own 512 of the shape's 1024 samples (beyond the paper: no shared points)",
    "resampled_partial": "noisy + partial, each cloud its own 512 samples, cropped to 384 "
                         "(beyond the paper: no shared points, as real scans)",
}
PROTOCOL_TITLES.update({f"{p}{ROTATED_SUFFIX}": f"{PROTOCOL_TITLES[p]}; both clouds turned by a random rotation "
                        "(beyond the paper)" for p in PROTOCOLS + RESAMPLED})
PROTOCOL_TITLES.update({f"{p}{ANY_RELATIVE_SUFFIX}": f"{PROTOCOL_TITLES[p]}; turned, then the target turned alone: "
                        "relative rotations of any size (beyond the paper)" for p in PROTOCOLS + RESAMPLED})
STEM = "modelnet10_accuracy"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=908, help="test shapes per protocol (all: 908)")
    parser.add_argument("--protocols", nargs="+", default=list(PROTOCOLS),
                        choices=PROTOCOLS + RESAMPLED + ROTATED + ANY_RELATIVE,
                        help="the paper's protocols, or the resampled ones (no point shared by the two clouds); "
                             "'<protocol>_rotated' turns both clouds by a random rotation, "
                             "'<protocol>_any_relative' then the target alone (relative rotations of any size)")
    parser.add_argument("--methods", nargs="+", default=list(ALL_METHODS), choices=ALL_METHODS)
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: all cores)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--model-dir", type=Path, default=None,
                        help="an exported model folder (export/to_onnx.py) instead of the bundled one; "
                             "the per-pair cache keeps one model's records (another's are re-run): "
                             "use another --out to keep both")
    parser.add_argument("--open3d-tuning", type=Path, default=TUNING_FILE,
                        help="the tune_open3d.py sweep whose chosen Open3D parameters the baselines use; "
                             "baseline records of other parameters are re-run: use another --out to keep both")
    parser.add_argument("--fresh", action="store_true", help="ignore cached per-pair results")
    return parser


def refined_record(pair, method: str, coarse: dict) -> dict:
    """The record of ``method`` (ICP from the coarse method's pose) on ``pair``."""
    pose, seconds = refine_pose(pair.source, pair.target, np.array(coarse["T_pred"]), pair.scale)
    result = MethodResult(pose, coarse["seconds"] + seconds, coarse["failed"])
    record = pair_record(pair, method, result)
    for key in ("precision", "accuracy", "recall", "match_count"):  # the coarse method's matches
        if key in coarse:
            record[key] = coarse[key]
    return record


def class_breakdown(cache: ResultCache, methods: list[str], args) -> list[str]:
    """Markdown lines: success rate per ModelNet10 class, and how logdesc's failures look.

    The class is the shape name's prefix (``chair_0890`` -> chair). A failure is a pair
    outside the success bounds; its rotation error tells a symmetric flip (near 90 or 180
    degrees) from a plain miss.
    """
    protocol = "partial" if "partial" in args.protocols else args.protocols[0]
    by_method = {m: cache.select(protocol, m, range(args.pairs)) for m in methods}
    classes = sorted({r["name"].rsplit("_", 1)[0] for records in by_method.values() for r in records})
    lines = [f"Protocol {protocol}; success = L_R < {SUCCESS_ROTATION_DEG:g} deg and translation < "
             f"{100 * SUCCESS_TRANSLATION_FRACTION:g} % of the radius.", "",
             "| class | pairs | " + " | ".join(methods) + " |",
             "| --- | ---: | " + " | ".join("---:" for _ in methods) + " |"]
    for name in classes:
        cells = []
        count = 0
        for method in methods:
            records = [r for r in by_method[method] if r["name"].rsplit("_", 1)[0] == name]
            count = len(records)
            cells.append(f"{100 * summarize(records)['success']:.0f}" if records else "")
        lines.append(f"| {name} | {count} | " + " | ".join(cells) + " |")
    if "logdesc_fsr" in by_method:
        misses = [r for r in by_method["logdesc_fsr"] if not is_success(r)]
        errors = np.array([r["rotation_error_deg"] for r in misses])
        flips = int(np.sum(errors > 150)) if len(errors) else 0
        quarter = int(np.sum((errors > 60) & (errors < 120))) if len(errors) else 0
        lines += ["", f"logdesc_fsr misses on {protocol}: {len(misses)} of {len(by_method['logdesc_fsr'])} pairs; "
                  f"rotation error > 150 deg (a half-turn flip, symmetric shapes) in {flips}, 60-120 deg in "
                  f"{quarter}, below 60 deg in {len(misses) - flips - quarter}."]
    return lines


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    methods = runnable_methods(args.methods)
    cache_path = args.out / f"{STEM}_pairs.jsonl"
    # Refined methods start from a coarse method's cached pose: ICP alone, no second network pass.
    refined = [m for m in methods if m in REFINED_FROM]
    coarse = list(dict.fromkeys([m for m in methods if m not in REFINED_FROM] + [REFINED_FROM[m] for m in refined]))
    runner = MethodRunner(coarse, FpfhParameters.tuned(args.open3d_tuning), threads=args.threads,
                          model_dir=args.model_dir)
    cache = ResultCache(cache_path, fresh=args.fresh, model_id=bundled_model_id(args.model_dir),
                        baseline_id=runner.parameters.fingerprint(), refinement_id=REFINEMENT_ID)

    total = args.pairs * len(args.protocols)
    pairs = modelnet10_test_pairs(args.protocols, args.pairs, args.seed)
    with tqdm(total=total, desc="ModelNet10 pairs", unit="pair", dynamic_ncols=True) as bar:
        for pair in pairs:
            # Only what the cache lacks: after a model change, the learned methods alone.
            to_run = [m for m in coarse if not cache.has(pair.protocol, pair.index, [m])]
            if to_run:
                results = runner.run(pair.source, pair.target, seed=pair.index, methods=to_run)
                cache.add(pair_record(pair, method, result) for method, result in results.items())
            missing = [m for m in refined if not cache.has(pair.protocol, pair.index, [m])]
            cache.add(refined_record(pair, m, cache.records[(pair.protocol, pair.index, REFINED_FROM[m])])
                      for m in missing)
            bar.update(1)

    summary = {
        protocol: {method: summarize(cache.select(protocol, method, range(args.pairs))) for method in methods}
        for protocol in args.protocols
    }
    lines = [
        "# ModelNet10 test: registration accuracy",
        "",
        f"All methods on the same pairs: the first {args.pairs} ModelNet10 test shapes, seed {args.seed} "
        f"(the pairs of `training/evaluate.py`). The model is {model_description(args.model_dir)}.",
        "Angles in degrees (RMSE/MAE over Euler angles, DCP's convention; L_R isotropic), translations in "
        "dataset units (unit sphere). Success: L_R < 5 deg and translation error < 5 % of the object's "
        "radius. P/A/R: matching precision / accuracy / recall against the true correspondences, for "
        "logdesc's Sinkhorn matches and, for descriptor-only and FPFH rows, the mutual nearest neighbours "
        "in descriptor space (the paper does not say how it matched FPFH for its Table 1, probably "
        "through its learned matcher, so its FPFH row and ours measure different things). ms / pair: "
        "median wall time of the method on a pair (network included), "
        "measured during this run on a shared 2-core machine; `latency.md` has the controlled timings.",
        "",
        f"Command: `{command_line()}`",
        f"Machine: {machine_info()}",
        f"Open3D parameters (network units, object radius = 1; chosen on validation pairs by "
        f"`tune_open3d.py`, `{project_relative(args.open3d_tuning)}`): {parameters_dict(runner.parameters)}",
    ]
    for protocol in args.protocols:
        rows = dict(summary[protocol])
        published = PUBLISHED.get(protocol)
        if published:
            rows[f"*{published['label']}*"] = published
        if protocol == "partial":
            fpfh = PUBLISHED["fpfh_matching_partial"]
            rows[f"*{fpfh['label']}*"] = fpfh
        lines += ["", f"## {PROTOCOL_TITLES[protocol]}", "", markdown_table(rows)]
    lines += ["", "## Success rate by class (noisy + partial unless absent)", "",
              *class_breakdown(cache, methods, args), ""]
    lines += [f"Error CDF: `{STEM.replace('accuracy', 'error_cdf')}.png`."]
    markdown = "\n".join(lines)

    payload = {
        "command": command_line(),
        "machine": machine_info(),
        "pairs_per_protocol": args.pairs,
        "seed": args.seed,
        "open3d_parameters": parameters_dict(runner.parameters),
        "open3d_tuning": str(project_relative(args.open3d_tuning)),
        "summary": summary,
        "published": PUBLISHED,
        "per_pair_file": cache_path.name + ".gz",
    }
    write_report(STEM, markdown, payload, args.out)
    cache.pack()  # the gzipped per-pair records kept in the repository
    error_cdf(
        {protocol: {method: cache.select(protocol, method, range(args.pairs)) for method in methods}
         for protocol in args.protocols},
        args.out / "modelnet10_error_cdf.png",
        title=f"ModelNet10 test, {args.pairs} pairs per protocol",
    )
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
