"""Simulated range-scan pairs of shapes no model trained on: logdesc-rt against Open3D.

Each pair is two simulated scans of one dense ModelNet40 shape (``logdesc_rt.scan_simulation``:
separate samples, sensors 15-90 degrees apart, hidden-point removal, density falling with
incidence and range, noise along the ray, stray points and box outliers, any relative pose), as
the scanner would deliver them: raw views of a few hundred to a few thousand points, which every
method takes as they are (logdesc-rt sets stray points aside and subsamples itself; FPFH runs on
the whole view).

Shapes: ``--split test`` (default) holds the shapes v3 validated on, which neither v3 nor v4
trained on (``training.data.split_train_val_test``); ``--split val`` is v4's validation split,
for model selection. Pair i uses dense shape ``i % S`` and ``default_rng([seed, 11, i])``.

    python benchmarks/scan_pairs.py [--pairs 60] [--split test] [--model-dir DIR --out DIR]
        [--protocol partial]   # the same split's 1024-point shapes under a shape protocol instead

``--protocol`` other than ``scan`` builds the split's pairs of ``logdesc_rt.synthetic`` instead
(e.g. ``partial``, ``resampled_partial``; both clouds turned, relative rotation of any size), so
that model selection can check ModelNet-style pairs on the same held-out shapes.

Methods: ``register()`` as a user calls it (verified candidates, the success flag), without and
with point-to-plane ICP; Open3D FPFH + RANSAC and FPFH + FGR, each without and with the same ICP,
with parameters tuned on validation pairs of the same kind (``tune_open3d.py``): on simulated
scans of validation shapes for ``--protocol scan`` (``methods.SCAN_TUNING_FILE``), on ModelNet
validation pairs for the shape protocols; ``--open3d-tuning`` names another sweep. Success: rotation
error < 5 deg and translation error < 5 % of the object's radius, overall and by the pairs' overlap
(``common.overlap_ratio``). Writes
``benchmarks/results/scan_pairs_<split>.{md,json}`` and the per-pair records
(``..._pairs.jsonl.gz``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from common import (  # noqa: E402
    DATA_ROOT,
    OVERLAP_SPACINGS,
    RESULTS,
    BenchmarkPair,
    ResultCache,
    bundled_model_id,
    command_line,
    is_success,
    machine_info,
    markdown_table,
    model_description,
    overlap_markdown_table,
    overlap_ratio,
    pair_record,
    project_relative,
    success_by_overlap,
    summarize,
    write_report,
)
from methods import (  # noqa: E402
    REFINEMENT_ID,
    SCAN_TUNING_FILE,
    TUNING_FILE,
    FpfhParameters,
    MethodRunner,
    parameters_dict,
    runnable_methods,
)
from tqdm import tqdm  # noqa: E402

from logdesc_rt.metrics import twin_distance  # noqa: E402
from logdesc_rt.scan_simulation import make_scan_pair  # noqa: E402
from logdesc_rt.synthetic import PROTOCOLS as SHAPE_PROTOCOLS  # noqa: E402

METHODS = ("logdesc_auto", "logdesc_auto_icp", "fpfh_ransac", "fpfh_ransac_icp", "fpfh_fgr", "fpfh_fgr_icp")
PAIR_STREAM = 11  # the second seed word of the pairs' generators
# A miss whose twin distance is below this is a symmetry twin of the truth: fixed before any
# figure (benchmarks/results/symmetry_twins/README.md), about the dense shapes' point spacing.
TWIN_DISTANCE = 0.02


def scan_shapes(split: str, data_root: Path = DATA_ROOT):
    """The dense shapes of a split of ``training.data.split_train_val_test`` (by shape name)."""
    from training.data import load_dense_shapes, load_training_sources, split_train_val_test

    three_way = split_train_val_test(load_training_sources(data_root))
    names = three_way.test_names if split == "test" else three_way.shapes.val_names
    return load_dense_shapes(data_root).subset(set(names))


def shape_pairs(split: str, protocol: str, count: int, seed: int = 0, data_root: Path = DATA_ROOT):
    """``count`` pairs of a :mod:`logdesc_rt.synthetic` protocol from the split's 1024-point shapes,
    both clouds turned and the relative rotation of any size."""
    from logdesc_rt.synthetic import make_pair
    from training.data import load_training_sources, split_train_val_test

    three_way = split_train_val_test(load_training_sources(data_root))
    if split == "test":
        from training.data import split_training_shapes

        held_out = split_training_shapes(load_training_sources(data_root))  # its validation = the test names
        points, names = held_out.val, held_out.val_ids
    else:
        points, names = three_way.shapes.val, three_way.shapes.val_ids
    for index in range(count):
        shape = index % len(points)
        pair = make_pair(points[shape], protocol, np.random.default_rng([seed, PAIR_STREAM, index]),
                         any_orientation=True, any_relative_rotation=True)
        yield BenchmarkPair(protocol, index, names[shape], pair.source, pair.target, pair.T_gt, pair.gt_match_src,
                            pair.normalization.scale)


def scan_pairs(split: str, count: int, seed: int = 0, data_root: Path = DATA_ROOT, complete_shapes: dict | None = None):
    """``count`` raw simulated scan pairs (:class:`BenchmarkPair`) of the split's dense shapes.

    ``complete_shapes``, if given, receives {pair index: (P, 3) the complete dense shape in the
    pair's source frame}, for :func:`symmetry_twins`."""
    shapes = scan_shapes(split, data_root)
    for index in range(count):
        shape = index % len(shapes.points)
        pair = make_scan_pair(
            shapes.points[shape], shapes.normals[shape], np.random.default_rng([seed, PAIR_STREAM, index]),
            points_per_cloud=None,
        )
        if complete_shapes is not None:
            placement = pair.shape_to_source
            complete_shapes[index] = shapes.points[shape] @ placement[:3, :3].T + placement[:3, 3]
        yield BenchmarkPair("scan", index, shapes.names[shape], pair.source, pair.target, pair.T_gt,
                            pair.gt_match_src, pair.normalization.scale)


def symmetry_twins(records: dict[str, list[dict]], complete_shapes: dict[int, np.ndarray]) -> dict[str, dict]:
    """Per method: its misses, how many of them are symmetry twins (twin distance below
    ``TWIN_DISTANCE``: the whole object lands where the truth puts it, up to the shape's own
    symmetry), and the twin distance of every pair (``benchmarks/results/symmetry_twins``)."""
    table = {}
    for method, method_records in records.items():
        distances = {
            record["index"]: twin_distance(complete_shapes[record["index"]], record["T_pred"], record["T_gt"])
            for record in method_records
        }
        misses = [record["index"] for record in method_records if not is_success(record)]
        twins = [index for index in misses if distances[index] < TWIN_DISTANCE]
        claimed = [record for record in method_records if record.get("flagged_success")]
        table[method] = {
            "claimed": len(claimed),
            "claimed_right_up_to_symmetry": sum(is_success(r) or r["index"] in twins for r in claimed),
            "pairs": len(method_records),
            "successes": len(method_records) - len(misses),
            "misses": len(misses),
            "twins": len(twins),
            "twin_pairs": twins,
            "twin_distance": {str(index): distance for index, distance in distances.items()},
        }
    return table


def symmetry_twins_table(table: dict[str, dict]) -> str:
    """Markdown: per method, strict success, misses, twins among them, right up to symmetry,
    and the success flag's claims that are right up to symmetry (strict successes or twins)."""
    rows = [
        "| method | pairs | strict success % | misses | symmetry twins among them | right up to symmetry % "
        "| flag claims right up to symmetry |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, row in table.items():
        pairs = max(row["pairs"], 1)
        claims = f"{row['claimed_right_up_to_symmetry']} of {row['claimed']}" if row["claimed"] else ""
        rows.append(
            f"| {method} | {row['pairs']} | {100 * row['successes'] / pairs:.1f} | {row['misses']} | {row['twins']} | "
            f"{100 * (row['successes'] + row['twins']) / pairs:.1f} | {claims} |"
        )
    return "\n".join(rows)


def protocol_pairs(
    split: str,
    protocol: str,
    count: int,
    seed: int = 0,
    data_root: Path = DATA_ROOT,
    complete_shapes: dict | None = None,
):
    """``count`` pairs of a split: raw scan pairs for ``protocol == "scan"``, else the shape
    protocol's (:func:`scan_pairs`, :func:`shape_pairs`)."""
    if protocol == "scan":
        return scan_pairs(split, count, seed, data_root, complete_shapes)
    return shape_pairs(split, protocol, count, seed, data_root)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=60)
    parser.add_argument("--split", choices=["test", "val"], default="test")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--methods", nargs="+", default=list(METHODS),
                        choices=(*METHODS, "logdesc_thorough", "logdesc_second_draw", "logdesc_refit_only"))
    parser.add_argument("--protocol", default="scan", choices=["scan", *SHAPE_PROTOCOLS])
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime threads (default: all cores)")
    parser.add_argument("--model-dir", type=Path, default=None, help="an exported model instead of the bundled one")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--fresh", action="store_true", help="ignore cached per-pair results")
    parser.add_argument("--open3d-tuning", type=Path, default=None,
                        help="Open3D's parameters (a tune_open3d.py open3d_tuning.json; default: the sweep on "
                             "validation scans for --protocol scan, on ModelNet validation pairs otherwise)")
    return parser


def open3d_tuning_file(protocol: str, chosen: Path | None = None) -> Path:
    """The Open3D sweep a protocol's baselines use: ``chosen``, else the one on its own kind of
    validation pairs (scans for ``"scan"``)."""
    if chosen is not None:
        return chosen
    return SCAN_TUNING_FILE if protocol == "scan" else TUNING_FILE


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    methods = runnable_methods(args.methods)
    stem = f"scan_pairs_{args.split}" if args.protocol == "scan" else f"heldout_{args.protocol}_{args.split}"
    tuning = open3d_tuning_file(args.protocol, args.open3d_tuning)
    runner = MethodRunner(methods, FpfhParameters.tuned(tuning), threads=args.threads, model_dir=args.model_dir)
    cache = ResultCache(args.out / f"{stem}_pairs.jsonl", fresh=args.fresh, model_id=bundled_model_id(args.model_dir),
                        baseline_id=runner.parameters.fingerprint(), refinement_id=REFINEMENT_ID)
    sizes, overlaps = [], {}
    complete_shapes: dict[int, np.ndarray] = {}
    pairs = protocol_pairs(args.split, args.protocol, args.pairs, args.seed, complete_shapes=complete_shapes)
    for pair in tqdm(pairs, total=args.pairs, desc=f"{args.protocol} pairs", unit="pair"):
        sizes.append((len(pair.source), len(pair.target)))
        overlaps[pair.index] = overlap_ratio(pair.source, pair.target, pair.T_gt)
        to_run = [m for m in methods if not cache.has(pair.protocol, pair.index, [m])]
        if to_run:
            results = runner.run(pair.source, pair.target, seed=pair.index, methods=to_run)
            cache.add(pair_record(pair, method, result) for method, result in results.items())

    records = {method: cache.select(args.protocol, method, range(args.pairs)) for method in methods}
    summary = {method: summarize(method_records) for method, method_records in records.items()}
    by_overlap = success_by_overlap(records, overlaps)
    overlap_values = np.array(list(overlaps.values()))
    sizes = np.array(sizes)
    size_text = f"{int(sizes.min())}-{int(sizes.max())} points (median {int(np.median(sizes))})"
    if args.protocol == "scan":
        description = (
            f"{args.pairs} pairs of two simulated scans each (`logdesc_rt/scan_simulation.py`: separate samples, "
            "sensors 15-90 deg apart, hidden-point removal, density falling with incidence and range, noise along "
            f"the ray, stray points and box outliers, any relative pose), raw views of {size_text}, of the "
            f"{args.split} split's dense ModelNet40 shapes (`training.data.split_train_val_test`)."
        )
    else:
        description = (
            f"{args.pairs} `{args.protocol}` pairs (`logdesc_rt/synthetic.py`; both clouds turned, relative "
            f"rotation of any size; {size_text}) of the {args.split} split's 1024-point shapes "
            "(`training.data.split_train_val_test`)."
        )
    lines = [
        f"# {'Simulated range-scan' if args.protocol == 'scan' else args.protocol} pairs, {args.split} shapes",
        "",
        f"{description} The model is {model_description(args.model_dir)}.",
        "Success: rotation error < 5 deg and translation error < 5 % of the object's radius. flag P / R: "
        "the runtime's success flag (right among the flagged / flagged among the right). ICP: the package's "
        "point-to-plane ICP from each coarse pose. ms / pair: median wall time on a shared 2-core machine.",
        "",
        f"Command: `{command_line()}`",
        f"Machine: {machine_info()}",
        f"Open3D parameters (network units, object radius = 1; `{project_relative(tuning)}`, chosen by "
        f"`tune_open3d.py` on validation pairs): {parameters_dict(runner.parameters)}",
        "",
        markdown_table(summary),
        "",
        "## Success by overlap",
        "",
        "Overlap: the smaller of the two clouds' shares of points that have a point of the other cloud, in the "
        f"true pose, within {OVERLAP_SPACINGS:g} median point spacings (`benchmarks/common.py: overlap_ratio`); "
        f"these pairs' overlaps span {overlap_values.min():.2f}-{overlap_values.max():.2f} "
        f"(median {np.median(overlap_values):.2f}). Successes / pairs in each bin:",
        "",
        overlap_markdown_table(by_overlap),
        "",
    ]
    twins = None
    if complete_shapes:
        twins = symmetry_twins(records, complete_shapes)
        lines += [
            "## Misses that are the shape's own symmetry",
            "",
            "Twin distance: the mean two-sided closest-point distance between the complete dense shape (10,000 "
            "points) moved by the estimate and by the truth, over the shape's radius (`logdesc_rt.metrics."
            f"twin_distance`). A miss with a twin distance below {TWIN_DISTANCE:g} puts the whole object where the "
            "truth puts it, up to a symmetry of the shape (a bottle turned about its axis, a bathtub by a half-turn): "
            "geometry alone cannot tell it from the truth. Reported beside the strict success rate, never instead "
            "of it; the rule was written before its figures (`benchmarks/results/symmetry_twins/README.md`).",
            "",
            symmetry_twins_table(twins),
            "",
        ]
    markdown = "\n".join(lines)
    write_report(stem, markdown, {"command": command_line(), "machine": machine_info(), "split": args.split,
                                  "pairs": args.pairs, "seed": args.seed, "summary": summary,
                                  "success_by_overlap": by_overlap, "overlaps": overlaps,
                                  "open3d_tuning": str(project_relative(tuning)),
                                  "open3d_parameters": parameters_dict(runner.parameters),
                                  "symmetry_twins": twins, "per_pair_file": f"{stem}_pairs.jsonl.gz"}, args.out)
    cache.pack()
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
