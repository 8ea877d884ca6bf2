"""Accuracy on the Stanford Bunny: the paper's protocol on its scans, and real pairs.

The model is the bundled one (or ``--model-dir``'s), trained on ModelNet only; the methods are those of
``benchmarks/methods.py`` (as in ``accuracy_modelnet.py``). Two parts:

(a) Paper protocol (the paper follows R-PointHop: the 10 range scans, synthetic
    motion). Each scan is centred on its centroid and divided by its largest point
    distance (unit sphere), farthest-point-sampled to 1024 points (the network's input
    size), and turned into ``--trials`` pairs by :func:`logdesc_rt.synthetic.make_pair`
    under the "noisy" protocol (rotation in [0, 45] deg per Euler axis, translation in
    [-0.5, 0.5] per axis, N(0, 0.01^2) noise clipped to +-0.05), generator
    ``default_rng([seed, scan index, trial])``. The paper does not say how it subsamples
    the scans, so its numbers and ours share the protocol, not necessarily the points.

(b) Real scan pairs. Two different scans, each in its own scanner frame (metres), the
    ground truth from ``bun.conf`` (relative pose ``inv(T_B) @ T_A``). Pairs are chosen
    by measured overlap, not by hand: for every unordered pair (A before B in file-name
    order), the share of a 4000-point farthest-point subset of A that has a point of the
    full scan B within 1 mm once A is mapped into B's frame; pairs with overlap
    >= ``--overlap`` are kept. Each scan of a kept pair is farthest-point-sampled to
    1024 points (every method sees these clouds). No ground-truth correspondences, so
    no P/A/R.

    python benchmarks/bunny.py [--trials 10] [--overlap 0.3] [--threads 2] [--fresh]
                               [--out DIR]
    python benchmarks/bunny.py --flag-only [--threads 1]   # (c) alone

(c) The success flag on the real pairs (``--flag-only`` runs this part alone and writes
    ``<out>/bunny_success_flag.{md,json}``): ``Registrar.register`` as a user calls it
    (estimator "auto": verified hypotheses), without and with point-to-plane ICP, on the
    same 1024-point clouds; per pair the error, whether it is right (the success criterion
    below), and the flag. Precision: right among the pairs flagged success; recall: flagged
    among the right ones. The flag was calibrated on other pairs
    (``benchmarks/calibrate_success.py``), never on these.

Numbers in the report: RMSE(R) / MAE(R), degrees, over the three Euler-angle
differences of every pair (DCP's convention, the paper's Table 5); RMSE(t) / MAE(t)
over the three translation-component differences, in the clouds' units (unit sphere in
(a), metres in (b), millimetres in (b)'s second table); L_R, the isotropic rotation
error in degrees (mean, median); L_t, the norm of the translation error; success, the
share of pairs with L_R < 5 deg and L_t < 5 % of the object's radius (unit sphere:
0.05; scans: about 6 mm); P / A / R, matching precision / accuracy / recall (part (a)
only); ms / pair, the median wall time of a method on a pair on this shared machine;
failed, pairs for which a method returned no pose; overlap, GT angle: see (b).

Per-pair results go to ``<out>/bunny_pairs.jsonl`` as they come (an interrupted run
resumes; ``--fresh`` starts over); the repository keeps them gzipped
(``bunny_pairs.jsonl.gz``, unpacked on the next run). Writes ``<out>/bunny.{md,json}`` and
``<out>/bunny_error_cdf.png``.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import (  # noqa: E402
    DATA_ROOT,
    DEFAULT_SEED,
    PUBLISHED,
    RESULTS,
    SUCCESS_ROTATION_DEG,
    SUCCESS_TRANSLATION_FRACTION,
    BenchmarkPair,
    ResultCache,
    bundled_model_id,
    command_line,
    machine_info,
    markdown_table,
    model_description,
    pair_record,
    project_relative,
    summarize,
    write_report,
)
from methods import (  # noqa: E402
    ALL_METHODS,
    REFINEMENT_ID,
    SCAN_TUNING_FILE,
    TUNING_FILE,
    FpfhParameters,
    MethodRunner,
    parameters_dict,
    runnable_methods,
)
from plots import error_cdf  # noqa: E402
from pykdtree.kdtree import KDTree  # noqa: E402
from tqdm import tqdm  # noqa: E402

from logdesc_rt.io import read_point_cloud, read_stanford_conf  # noqa: E402
from logdesc_rt.metrics import rotation_error_deg  # noqa: E402
from logdesc_rt.normalization import PairNormalization  # noqa: E402
from logdesc_rt.sampling import farthest_point_sampling  # noqa: E402
from logdesc_rt.synthetic import SOURCE_POINTS, make_pair  # noqa: E402

BUNNY_DIR = DATA_ROOT / "stanford_bunny" / "data"
STEM = "bunny"
PAPER_PROTOCOL = "paper_protocol"
REAL_PAIRS = "real_pairs"
PART_TITLES = {
    PAPER_PROTOCOL: "(a) paper protocol: 10 scans, synthetic noisy motion",
    REAL_PAIRS: "(b) real scan pairs, ground truth from bun.conf",
}
CDF_TITLES = {PAPER_PROTOCOL: "(a) paper protocol", REAL_PAIRS: "(b) real scan pairs"}
CLOUD_POINTS = SOURCE_POINTS  # 1024, the network's input size (and the paper's)
OVERLAP_SUBSET_POINTS = 4000  # FPS subset of A for the overlap (all of B is searched)
OVERLAP_DISTANCE_M = 0.001  # 1 mm: about twice the scans' median point spacing
DEFAULT_MIN_OVERLAP = 0.3
# Cache index of the paper-protocol pair (scan s, trial k) is s * TRIAL_STRIDE + k, of
# the real pair (scan i, scan j) i * SCAN_STRIDE + j: stable whatever --trials and
# --overlap are, so runs with other settings never read each other's records.
TRIAL_STRIDE = 1000
SCAN_STRIDE = 100
# The other rows of the paper's Table 5 (RMSE(R), MAE(R), RMSE(t), MAE(t)); the LoGDesc
# row is common.PUBLISHED["bunny"]. FGR is the one peer we also run (fpfh_fgr).
PUBLISHED_PEERS = {
    "FGR": (1.99, 1.49, 0.1993, 0.1658),
    "DCP": (6.44, 4.78, 0.0406, 0.0374),
    "R-PointHop": (1.49, 1.09, 0.0361, 0.0269),
    "RoCNet": (0.99, 0.83, 0.0338, 0.0288),
    "RoCNet++": (0.91, 0.50, 0.0316, 0.0301),
}
PUBLISHED_KEYS = ("rmse_r", "mae_r", "rmse_t", "mae_t")


# ------------------------------------------------------------------ the scans
@dataclass(frozen=True)
class BunnyScan:
    """One range scan of the bunny.

    Attributes:
        name: file name, e.g. "bun045.ply".
        points: (N, 3) float64 points in the scanner's frame, metres (N = 30k-40k).
        pose: (4, 4) float64 scanner frame -> common (world) frame, from ``bun.conf``.
    """

    name: str
    points: np.ndarray
    pose: np.ndarray

    @property
    def stem(self) -> str:
        return Path(self.name).stem


def load_scans(data_dir: Path = BUNNY_DIR) -> list[BunnyScan]:
    """The 10 scans with their poses, in file-name order (which numbers them 0-9)."""
    poses = read_stanford_conf(Path(data_dir) / "bun.conf")
    paths = sorted(Path(data_dir).glob("*.ply"))
    missing = [path.name for path in paths if path.name not in poses]
    if missing or not paths:
        raise FileNotFoundError(f"{data_dir}: no scans, or no pose for {missing}")
    return [BunnyScan(p.name, read_point_cloud(p), poses[p.name]) for p in paths]


def relative_pose(source: BunnyScan, target: BunnyScan) -> np.ndarray:
    """(4, 4) pose mapping source-scan coordinates onto target-scan coordinates."""
    return np.linalg.inv(target.pose) @ source.pose


def transform(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N, 3) points moved by a (4, 4) pose."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def fps_subset(points: np.ndarray, count: int) -> np.ndarray:
    """(count, 3) farthest-point subset of (N, 3) points (deterministic; all if <=)."""
    if len(points) <= count:
        return points
    return points[farthest_point_sampling(points, count)]


# ------------------------------------------------------------------ pair selection
@dataclass(frozen=True)
class ScanPair:
    """Two scans and how much they overlap.

    Attributes:
        source, target: indices into the :func:`load_scans` list (source < target).
        overlap: share of the source's overlap subset that lies within the overlap
            distance of the target scan once mapped by the ground truth, in [0, 1].
        reverse_overlap: the same measured from the target's side (for information).
        angle_deg: rotation angle of the ground-truth relative pose, degrees.
    """

    source: int
    target: int
    overlap: float
    reverse_overlap: float
    angle_deg: float


def measure_overlaps(
    scans: list[BunnyScan],
    subset_points: int = OVERLAP_SUBSET_POINTS,
    distance: float = OVERLAP_DISTANCE_M,
) -> list[ScanPair]:
    """Overlap of every unordered pair of scans (45 for 10 scans), in index order.

    Args:
        scans: from :func:`load_scans`.
        subset_points: size of the farthest-point subset of the *measured* scan (for
            speed); the other scan is searched in full, so the subset's sparsity does
            not lower the overlap.
        distance: a point overlaps when the other scan has a point this close, metres.
    """
    subsets = [fps_subset(scan.points, subset_points) for scan in scans]
    trees = [KDTree(scan.points) for scan in scans]

    def share_near(measured: int, other: int) -> float:
        pose = relative_pose(scans[measured], scans[other])
        moved = transform(subsets[measured], pose)
        nearest, _ = trees[other].query(moved, k=1)
        return float(np.mean(nearest < distance))

    pairs = []
    for source, target in itertools.combinations(range(len(scans)), 2):
        rotation = relative_pose(scans[source], scans[target])[:3, :3]
        angle = float(rotation_error_deg(rotation, np.eye(3)))
        overlap, reverse = share_near(source, target), share_near(target, source)
        pairs.append(ScanPair(source, target, overlap, reverse, angle))
    return pairs


def select_scan_pairs(
    scans: list[BunnyScan],
    min_overlap: float = DEFAULT_MIN_OVERLAP,
    overlaps: list[ScanPair] | None = None,
) -> list[ScanPair]:
    """The scan pairs whose measured overlap is at least ``min_overlap`` (module doc).

    ``overlaps`` (from :func:`measure_overlaps`) saves measuring them again.
    """
    overlaps = measure_overlaps(scans) if overlaps is None else overlaps
    return [pair for pair in overlaps if pair.overlap >= min_overlap]


def pair_name(scans: list[BunnyScan], pair: ScanPair) -> str:
    return f"{scans[pair.source].stem} -> {scans[pair.target].stem}"


# ------------------------------------------------------------------ benchmark pairs
def unit_sphere(points: np.ndarray) -> np.ndarray:
    """(N, 3) points centred on their centroid and divided by the largest distance."""
    centred = points - points.mean(axis=0)
    return centred / np.linalg.norm(centred, axis=1).max()


def paper_protocol_pairs(
    scans: list[BunnyScan], trials: int, seed: int = DEFAULT_SEED
) -> Iterator[BenchmarkPair]:
    """``trials`` noisy synthetic pairs per scan (unit sphere, FPS to 1024 points)."""
    for scan_index, scan in enumerate(scans):
        # Normalise the whole scan first, so that the 1024 points lie in the unit ball.
        shape = fps_subset(unit_sphere(scan.points), CLOUD_POINTS)
        for trial in range(trials):
            rng = np.random.default_rng([seed, scan_index, trial])
            pair = make_pair(shape, "noisy", rng)
            yield BenchmarkPair(
                PAPER_PROTOCOL,
                scan_index * TRIAL_STRIDE + trial,
                f"{scan.stem} trial {trial}",
                pair.source,
                pair.target,
                pair.T_gt,
                pair.gt_match_src,
                pair.normalization.scale,
            )


def real_scan_pairs(
    scans: list[BunnyScan], selection: list[ScanPair]
) -> list[BenchmarkPair]:
    """The selected pairs as benchmark pairs: 1024 FPS points, scanner frames (m)."""
    clouds: dict[int, np.ndarray] = {}
    pairs = []
    for chosen in selection:
        for index in (chosen.source, chosen.target):
            if index not in clouds:
                clouds[index] = fps_subset(scans[index].points, CLOUD_POINTS)
        source, target = clouds[chosen.source], clouds[chosen.target]
        pairs.append(
            BenchmarkPair(
                REAL_PAIRS,
                chosen.source * SCAN_STRIDE + chosen.target,
                pair_name(scans, chosen),
                source,
                target,
                relative_pose(scans[chosen.source], scans[chosen.target]),
                None,
                PairNormalization.fit(source, target).scale,  # larger radius, metres
            )
        )
    return pairs


def is_cached(cache: ResultCache, pair: BenchmarkPair, methods: list[str]) -> bool:
    """True when every method has a record of this pair *with this ground truth*; a
    record left by a run with another seed (or other data) is recomputed, not reused."""
    if not cache.has(pair.protocol, pair.index, methods):
        return False
    cached = [cache.records[(pair.protocol, pair.index, m)]["T_gt"] for m in methods]
    return all(np.allclose(T_gt, pair.T_gt, atol=1e-12) for T_gt in cached)


# ------------------------------------------------------------------ report
def published_rows() -> dict[str, dict]:
    """The paper's Table 5 rows, labelled as published (unit sphere, own sampling)."""
    rows = {f"*{PUBLISHED['bunny']['label']}*": PUBLISHED["bunny"]}
    for method, values in PUBLISHED_PEERS.items():
        label = f"*published {method} (paper Table 5)*"
        rows[label] = dict(zip(PUBLISHED_KEYS, values, strict=True))
    return rows


def millimetre_table(records: dict[str, list[dict]]) -> str:
    """Translation errors of the real pairs in millimetres, rotation errors beside."""
    lines = [
        "| method | RMSE(t) mm | MAE(t) mm | L_t mean mm | L_t median mm | L_R mean | "
        "L_R median | success % |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, method_records in records.items():
        if not method_records:
            continue
        metrics = summarize(method_records)
        errors_mm = 1e3 * np.array([r["translation_error"] for r in method_records])
        cells = [
            f"{1e3 * metrics['rmse_t']:.2f}",
            f"{1e3 * metrics['mae_t']:.2f}",
            f"{errors_mm.mean():.2f}",
            f"{np.median(errors_mm):.2f}",
            f"{metrics['l_r']:.2f}",
            f"{metrics['l_r_median']:.3f}",
            f"{100 * metrics['success']:.1f}",
        ]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def per_pair_table(
    scans: list[BunnyScan], selection: list[ScanPair], records: dict[str, list[dict]]
) -> str:
    """One row per real pair: overlap, true rotation angle, each method's L_R (deg)."""
    methods = list(records)
    by_index = {method: {r["index"]: r for r in records[method]} for method in methods}
    lines = [
        "| pair | overlap % | GT angle (deg) | " + " | ".join(methods) + " |",
        "| --- | ---: | ---: | " + " | ".join("---:" for _ in methods) + " |",
    ]
    for chosen in selection:
        index = chosen.source * SCAN_STRIDE + chosen.target
        cells = [f"{100 * chosen.overlap:.1f}", f"{chosen.angle_deg:.1f}"]
        for method in methods:
            record = by_index[method].get(index)
            error = None if record is None else record["rotation_error_deg"]
            cells.append("" if error is None else f"{error:.2f}")
        lines.append(f"| {pair_name(scans, chosen)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def report(args, scans, overlaps, selection, real_pairs, records, summary, runners,
           cache_name: str, wall_seconds: float) -> tuple[str, dict]:
    """The markdown report and the JSON payload (``runners``: part -> its MethodRunner)."""
    runner = runners[PAPER_PROTOCOL]
    kept = ", ".join(
        f"{pair_name(scans, p)} ({100 * p.overlap:.1f} %)" for p in selection
    )
    radius_mm = [1e3 * pair.scale for pair in real_pairs]
    if radius_mm:
        radius_text = (
            f"{min(radius_mm):.0f}-{max(radius_mm):.0f} mm, so success means L_R < "
            f"{SUCCESS_ROTATION_DEG:g} deg and a translation error under about "
            f"{SUCCESS_TRANSLATION_FRACTION * np.mean(radius_mm):.1f} mm."
        )
    else:
        radius_text = "undefined (no pair kept)."
    paper_count = len(records[PAPER_PROTOCOL][runner.methods[0]])
    lines = [
        "# Stanford Bunny: registration accuracy",
        "",
        f"The model is {model_description(args.model_dir)}, trained on ModelNet10 train + part of "
        "ModelNet40 train; the baselines are those of "
        "`benchmarks/methods.py`, on the 10 range scans of the Stanford Bunny "
        "(`../shared/data/stanford_bunny`). Angles in degrees: RMSE(R) / MAE(R) over "
        "the three Euler-angle differences of every pair (DCP's convention, the "
        "paper's Table 5), L_R the isotropic rotation error (mean, median). RMSE(t) / "
        "MAE(t) over the translation components, in the clouds' units. Success: L_R < "
        f"{SUCCESS_ROTATION_DEG:g} deg and translation error < "
        f"{100 * SUCCESS_TRANSLATION_FRACTION:g} % of the object's radius. ms / pair: "
        "median wall time of a method on a pair during this run, on a shared 2-core "
        "machine (another benchmark may have been running); `latency.md` has "
        "controlled timings.",
        "",
        f"Command: `{command_line()}`",
        f"Machine: {machine_info()}",
        f"Wall time of this run: {wall_seconds:.0f} s (cached pairs are not re-run).",
        "Open3D parameters (network units, object radius = 1), chosen by `tune_open3d.py` on validation pairs "
        "of each part's kind: for (a) on ModelNet pairs "
        f"(`{project_relative(args.open3d_tuning)}`): {parameters_dict(runner.parameters)}; for (b) on "
        f"simulated range scans (`{project_relative(args.real_open3d_tuning)}`): "
        f"{parameters_dict(runners[REAL_PAIRS].parameters)}.",
        "",
        f"## {PART_TITLES[PAPER_PROTOCOL]}",
        "",
        "Each scan centred and scaled into the unit sphere (divided by its largest "
        f"point distance), then farthest-point-sampled to {CLOUD_POINTS} points; "
        f"{args.trials} pairs per scan ({paper_count} in all) from "
        '`logdesc_rt.synthetic.make_pair(points, "noisy", default_rng([seed, scan, '
        f"trial]))` (seed {args.seed}): rotation up to 45 deg per Euler axis, "
        "translation up to 0.5 per axis, N(0, 0.01^2) noise clipped to +-0.05. Units: "
        "unit sphere. P/A/R: matching precision / accuracy / recall against the true "
        "correspondences (for descriptor-only and FPFH rows, mutual nearest neighbours "
        "in descriptor space).",
        "",
        "**The paper does not publish how it subsamples the scans** (it follows "
        "R-PointHop: the 10 scans, a model trained on ModelNet40). Ours is "
        "farthest-point sampling to 1024 points after scaling to the unit sphere, so "
        "the published rows (in italics, copied from the paper's Table 5; models "
        "trained on ModelNet40, ours on ModelNet10 + a ModelNet40 subset) share the "
        "protocol, not "
        "necessarily the points. The published LoGDesc row has MAE(t) > RMSE(t), which "
        "cannot happen for one set of errors; it is copied as printed.",
        "",
        markdown_table({**summary[PAPER_PROTOCOL], **published_rows()}),
        "",
        f"## {PART_TITLES[REAL_PAIRS]}",
        "",
        "Two different scans, each in its own scanner frame (metres); ground truth "
        "`inv(T_B) @ T_A` from `bun.conf` (quaternion with qw's sign flipped, see "
        "`../shared/data/README.md`). Pairs chosen by measured overlap, not by hand: "
        f"for each of the {len(overlaps)} unordered pairs (A before B in file-name "
        f"order), the share of a {OVERLAP_SUBSET_POINTS}-point farthest-point subset "
        f"of A that has a point of the full scan B within {1e3 * OVERLAP_DISTANCE_M:g} "
        "mm "
        "after mapping A into B's frame (the scans' point spacing is about 0.5 mm). "
        f"Kept: overlap >= {100 * args.overlap:g} %, {len(selection)} pairs: "
        f"{kept or 'none'}. Each scan is then farthest-point-sampled to {CLOUD_POINTS} "
        "points (all methods get the same clouds). Most pairs are far outside the "
        "training range of rotations (up to 45 deg per Euler axis): see the GT angle "
        "column.",
        "",
        "The bunny is about 0.15 m across; the pairs' radius (the larger cloud's "
        "largest distance from its centroid, the reference for success) is "
        f"{radius_text} Translations in metres in the first table, in millimetres in "
        "the second. No ground-truth correspondences, so no P/A/R. Euler-angle "
        "RMSE/MAE mean little for rotations near 180 deg (several pairs): read L_R.",
        "",
        markdown_table(summary[REAL_PAIRS]),
        "",
        millimetre_table(records[REAL_PAIRS]),
        "",
        "Per pair: measured overlap, the true rotation between the two scans (GT "
        "angle), and each method's L_R (deg).",
        "",
        per_pair_table(scans, selection, records[REAL_PAIRS]),
        "",
        f"Error CDF: `{STEM}_error_cdf.png`. Per-pair records: `{cache_name}`.",
    ]
    all_overlaps = [
        {
            "pair": pair_name(scans, p),
            "overlap": p.overlap,
            "reverse_overlap": p.reverse_overlap,
            "angle_deg": p.angle_deg,
            "kept": p.overlap >= args.overlap,
        }
        for p in overlaps
    ]
    payload = {
        "command": command_line(),
        "machine": machine_info(),
        "wall_seconds": wall_seconds,
        "seed": args.seed,
        "methods": list(runner.methods),
        "scans": [scan.name for scan in scans],
        PAPER_PROTOCOL: {
            "trials_per_scan": args.trials,
            "pairs": paper_count,
            "points": CLOUD_POINTS,
            "subsampling": "unit sphere (centroid, largest distance), then FPS",
        },
        REAL_PAIRS: {
            "min_overlap": args.overlap,
            "overlap_subset_points": OVERLAP_SUBSET_POINTS,
            "overlap_distance_m": OVERLAP_DISTANCE_M,
            "points": CLOUD_POINTS,
            "radius_m": {pair.name: pair.scale for pair in real_pairs},
            "all_overlaps": all_overlaps,
        },
        "open3d_tuning": {PAPER_PROTOCOL: str(project_relative(args.open3d_tuning)),
                          REAL_PAIRS: str(project_relative(args.real_open3d_tuning))},
        "open3d_parameters": {part: parameters_dict(part_runner.parameters) for part, part_runner in runners.items()},
        "summary": summary,
        "published": {
            "logdesc": PUBLISHED["bunny"],
            "peers": {name: dict(zip(PUBLISHED_KEYS, values, strict=True))
                      for name, values in PUBLISHED_PEERS.items()},
        },
        "per_pair_file": cache_name,
    }
    return "\n".join(lines), payload


# ------------------------------------------------------------------ (c) the success flag
FLAG_STEM = "bunny_success_flag"


def success_flag_rows(
    real_pairs: list[BenchmarkPair], threads: int | None, model_dir: Path | None = None
) -> list[dict]:
    """``Registrar.register`` on each real pair, without and with ICP: error, right, flag."""
    from logdesc_rt import Registrar

    registrar = Registrar(model_dir, threads=threads)
    rows = []
    for pair in real_pairs:
        for refine in (None, "point_to_plane"):
            result = registrar.register(pair.source, pair.target, refine=refine)
            rotation_error = float(rotation_error_deg(result.rotation, pair.T_gt[:3, :3]))
            translation_error = float(np.linalg.norm(result.translation - pair.T_gt[:3, 3]))
            rows.append({
                "pair": pair.name,
                "refine": refine or "none",
                "rotation_error_deg": rotation_error,
                "translation_error": translation_error,
                "right": bool(rotation_error < SUCCESS_ROTATION_DEG
                              and translation_error < SUCCESS_TRANSLATION_FRACTION * pair.scale),
                "success": bool(result.success),
                "confidence": float(result.confidence),
                "pose_estimator": result.pose_estimator,
                "seconds": float(result.timings["total"]),
            })
    return rows


def success_flag_report(rows: list[dict]) -> tuple[str, dict]:
    """Markdown and JSON: per mode, right / claimed / precision / recall; then per pair."""
    summary = {}
    for refine in ("none", "point_to_plane"):
        chosen = [row for row in rows if row["refine"] == refine]
        right = sum(row["right"] for row in chosen)
        claimed = sum(row["success"] for row in chosen)
        both = sum(row["right"] and row["success"] for row in chosen)
        summary[refine] = {
            "pairs": len(chosen), "right": right, "claimed": claimed, "right_and_claimed": both,
            "precision": both / claimed if claimed else None, "recall": both / right if right else None,
        }
    lines = [
        "# Stanford Bunny real pairs: the success flag",
        "",
        f"Command: `{command_line()}`",
        f"Machine: {machine_info()}",
        "",
        "`Registrar.register` (estimator auto: verified hypotheses) on the real scan pairs of part (b)",
        "(1024 farthest-point samples per scan). Right: L_R < 5 deg and translation < 5 % of the radius.",
        "Precision = right among the flagged successes; recall = flagged among the right poses. The flag",
        "was calibrated on other pairs (`benchmarks/results/success_calibration.md`), never these.",
        "",
        "| ICP | pairs | right | flagged success | right and flagged | precision | recall |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for refine, q in summary.items():
        precision = "-" if q["precision"] is None else f"{q['precision']:.1%}"
        recall = "-" if q["recall"] is None else f"{q['recall']:.1%}"
        lines.append(f"| {refine} | {q['pairs']} | {q['right']} | {q['claimed']} | {q['right_and_claimed']} | "
                     f"{precision} | {recall} |")
    lines += ["", "| pair | ICP | L_R (deg) | right | success | confidence | pose from |",
              "| --- | --- | ---: | --- | --- | ---: | --- |"]
    for row in rows:
        lines.append(f"| {row['pair']} | {row['refine']} | {row['rotation_error_deg']:.1f} | {row['right']} | "
                     f"{row['success']} | {row['confidence']:.3f} | {row['pose_estimator']} |")
    payload = {"command": command_line(), "machine": machine_info(), "summary": summary, "pairs": rows}
    return "\n".join(lines) + "\n", payload


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=10,
                        help="paper-protocol pairs per scan")
    parser.add_argument("--overlap", type=float, default=DEFAULT_MIN_OVERLAP,
                        help="least overlap of a real pair (share within 1 mm)")
    parser.add_argument("--methods", nargs="+", default=list(ALL_METHODS),
                        choices=ALL_METHODS)
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--threads", type=int, default=None,
                        help="onnxruntime threads (default: all cores)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--model-dir", type=Path, default=None,
                        help="an exported model folder (export/to_onnx.py) instead of the bundled one; "
                             "use another --out: the per-pair cache is per model")
    parser.add_argument("--fresh", action="store_true",
                        help="ignore cached per-pair results")
    parser.add_argument("--open3d-tuning", type=Path, default=TUNING_FILE,
                        help="Open3D's parameters for (a), a tune_open3d.py open3d_tuning.json (default: the "
                             "sweep on ModelNet validation pairs, whose kind (a) is)")
    parser.add_argument("--real-open3d-tuning", type=Path, default=SCAN_TUNING_FILE,
                        help="Open3D's parameters for (b)'s real scan pairs (default: the sweep on simulated "
                             "scans of validation shapes, methods.SCAN_TUNING_FILE)")
    parser.add_argument("--flag-only", action="store_true",
                        help="run part (c) alone: the success flag's precision / recall on the real pairs")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if not 1 <= args.trials <= TRIAL_STRIDE:
        raise SystemExit(f"--trials must be in [1, {TRIAL_STRIDE}]")
    started = time.perf_counter()
    if args.flag_only:
        scans = load_scans()
        real_pairs = real_scan_pairs(scans, select_scan_pairs(scans, args.overlap))
        markdown, payload = success_flag_report(success_flag_rows(real_pairs, args.threads, args.model_dir))
        write_report(FLAG_STEM, markdown, payload, args.out)
        print(markdown)
        return 0
    methods = runnable_methods(args.methods)
    cache_path = args.out / f"{STEM}_pairs.jsonl"
    # Each part gives Open3D the parameters tuned on validation pairs of its own kind; the
    # learned methods share one registrar.
    runner = MethodRunner(methods, FpfhParameters.tuned(args.open3d_tuning), threads=args.threads,
                          model_dir=args.model_dir)
    runners = {
        PAPER_PROTOCOL: runner,
        REAL_PAIRS: runner.with_parameters(FpfhParameters.tuned(args.real_open3d_tuning)),
    }
    cache = ResultCache(cache_path, fresh=args.fresh, model_id=bundled_model_id(args.model_dir),
                        baseline_id={
                            part: part_runner.parameters.fingerprint() for part, part_runner in runners.items()
                        },
                        refinement_id=REFINEMENT_ID)

    scans = load_scans()
    print(f"measuring the overlaps of {len(scans)} scans ...", file=sys.stderr)
    overlaps = measure_overlaps(scans)
    selection = select_scan_pairs(scans, args.overlap, overlaps)
    real_pairs = real_scan_pairs(scans, selection)

    indices: dict[str, list[int]] = {PAPER_PROTOCOL: [], REAL_PAIRS: []}
    synthetic = paper_protocol_pairs(scans, args.trials, args.seed)
    pairs = itertools.chain(synthetic, real_pairs)
    total = len(scans) * args.trials + len(real_pairs)
    with tqdm(total=total, desc="Bunny pairs", unit="pair", dynamic_ncols=True) as bar:
        for pair in pairs:
            # Only what the cache lacks: after a model change, the learned methods alone.
            to_run = [m for m in methods if not is_cached(cache, pair, [m])]
            if to_run:
                results = runners[pair.protocol].run(pair.source, pair.target, seed=pair.index, methods=to_run)
                cache.add(pair_record(pair, m, result) for m, result in results.items())
            indices[pair.protocol].append(pair.index)
            bar.update(1)

    records = {
        part: {m: cache.select(part, m, part_indices) for m in methods}
        for part, part_indices in indices.items()
    }
    summary = {
        part: {m: summarize(part_records[m]) for m in methods if part_records[m]}
        for part, part_records in records.items()
    }
    wall_seconds = time.perf_counter() - started
    markdown, payload = report(args, scans, overlaps, selection, real_pairs, records,
                               summary, runners, cache_path.name + ".gz", wall_seconds)
    write_report(STEM, markdown, payload, args.out)
    cache.pack()  # the gzipped per-pair records kept in the repository
    error_cdf(
        {
            f"{CDF_TITLES[part]} ({len(indices[part])} pairs)": records[part]
            for part in indices
        },
        args.out / f"{STEM}_error_cdf.png",
        title="Stanford Bunny: rotation error per pair",
        max_deg=180.0,
    )
    print(markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
