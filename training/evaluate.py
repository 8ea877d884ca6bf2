"""Evaluate a training checkpoint on ModelNet10's test split with the paper's protocol.

``--split val`` evaluates on the checkpoint's own held-out validation shapes instead (the
split ``training.train`` carved with its ``--val-fraction`` and ``--seed``): that is the set
to choose between checkpoints on; the test split only reports the chosen one.

Usage (from the repository root)::

    python -m training.evaluate runs/small/best.pt --protocols clean noisy partial \
        --pairs 908 --seed 1234 --out results/small_eval.md

For every protocol, test pair i is built from test shape i with
``np.random.default_rng([seed, 0, i])`` (:class:`training.data.PairDataset`, epoch 0), so
the same shape gets the same rigid motion under every protocol and every checkpoint sees the
same pairs. Each pair is registered through the runtime's own path, as users get it:

    torch network (scores) -> logdesc_rt.pair.pair_from_scores (the runtime's Sinkhorn and
    mutual test) -> logdesc_rt.pose_selection.register_matched (candidate poses, verification,
    the success flag; ``--estimator auto`` by default, ``fsr`` for the paper's estimator alone)
    -> paper metrics in the user (dataset) frame.

Reported per protocol: RMSE(R), MAE(R) (Euler 'zyx' degrees), RMSE(t), MAE(t), L_R (deg), L_t,
L_RMSE (logdesc_rt.metrics.registration_metrics) and the matching precision / accuracy / recall
of the mutual matches (logdesc_rt.metrics.matching_metrics, averaged over pairs), plus the
median L_R, the share of pairs with L_R < 5 degrees, why the others missed
(:attr:`PairResult.failure`: no pose, near miss, a symmetric alternative that fits as well as
the truth, or wrong), and the success flag's precision and recall.

The functions (:func:`register_scored_batch`, :func:`evaluate_model`, :func:`summarize`,
:func:`format_markdown`) are reusable by training and benchmarks.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

if __package__ in (None, ""):  # run as ``python training/evaluate.py``: import from the repo root
    _here = Path(__file__).resolve().parent
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _here]
    sys.path.insert(0, str(_here.parent))

import numpy as np
from pykdtree.kdtree import KDTree

from logdesc_rt.config import (
    POSE_ESTIMATORS,
    GeometryConfig,
    MatchingConfig,
    NormalizationConfig,
    RuntimeConfig,
    VerificationConfig,
)
from logdesc_rt.matching import correspondences_as_array
from logdesc_rt.metrics import SUCCESS_ROTATION_DEG, matching_metrics, registration_metrics, rotation_error_deg
from logdesc_rt.normalization import PairNormalization
from logdesc_rt.pair import pair_from_scores
from logdesc_rt.pose_selection import register_matched
from logdesc_rt.results import RegistrationResult
from training.checkpoint import configs_from_checkpoint, load_checkpoint, model_from_checkpoint
from training.data import (
    DEFAULT_DATA_ROOT,
    DEFAULT_VAL_FRACTION,
    MODELNET10_FOLDER,
    PAPER_PROTOCOLS,
    PROTOCOLS,
    SOURCE_POINTS,
    PairDataset,
    PairKey,
    fixed_pair_batches,
    load_modelnet,
    load_training_sources,
    run_split,
)

__all__ = [
    "DEFAULT_EVAL_SEED",
    "PairResult",
    "evaluate_checkpoint",
    "evaluate_model",
    "evaluation_keys",
    "format_markdown",
    "load_checkpoint",
    "model_from_checkpoint",
    "modelnet10_test_dataset",
    "evaluation_config",
    "register_scored_batch",
    "summarize",
    "validation_dataset",
]

DEFAULT_EVAL_SEED = 1234
NEAR_MISS_DEG = 30.0
SYMMETRIC_FIT_RATIO = 0.9
FAILURE_KINDS = ("no pose", "near miss", "symmetric", "wrong")
SPLITS = ("test", "val")
TEST_SHAPES = 908


@dataclass
class PairResult:
    """Outcome of one test pair (user frame unless noted).

    Attributes:
        protocol, index: which pair.
        T_pred: (4, 4) predicted pose source -> target, user frame.
        T_gt: (4, 4) true pose, user frame.
        source: (N, 3) user-frame source (for L_RMSE).
        target: (M, 3) user-frame target (for the fit of a wrong pose).
        scale: the pair's scale (the larger cloud's radius, user units).
        pred_match: (N,) int64 predicted target index per source point, -1 unmatched.
        gt_match: (N,) int64 true counterpart, -1 none, -2 ignored (resampled pairs).
        match_count: number of mutual matches.
        pose_failed: True when no pose could be estimated (fewer than 3 matches, or degenerate
            ones); the identity was used.
        seconds: wall time of Sinkhorn, matching, the candidates and verification for this
            pair (network excluded).
        flagged: the runtime's success flag (``RegistrationResult.success``).
        confidence: its calibrated confidence.
        estimator: the estimator whose pose was kept ("none" without a pose).
    """

    protocol: str
    index: int
    T_pred: np.ndarray
    T_gt: np.ndarray
    source: np.ndarray
    target: np.ndarray
    scale: float
    pred_match: np.ndarray
    gt_match: np.ndarray
    match_count: int
    pose_failed: bool
    seconds: float
    flagged: bool = False
    confidence: float = 0.0
    estimator: str = "fsr"

    @property
    def rotation_error_deg(self) -> float:
        return float(rotation_error_deg(self.T_pred[:3, :3], self.T_gt[:3, :3]))

    @functools.cached_property
    def _target_tree(self) -> KDTree:  # built once: a failure's fit is read for two poses
        return KDTree(self.target)

    def fitness(self, pose: np.ndarray) -> float:
        """Share of the source points within the runtime's inlier distance of the target after
        ``pose`` (the verification's ``fitness``: ``distance_fraction`` x scale)."""
        distance, _ = self._target_tree.query(self.source @ pose[:3, :3].T + pose[:3, 3], k=1)
        return float(np.mean(distance < VerificationConfig().distance_fraction * self.scale))

    @property
    def failure(self) -> str | None:
        """Why the rotation is 5 degrees or more off (None when it is not).

        ``"no pose"``: fewer than 3 matches or degenerate ones; ``"near miss"``: under 30
        degrees, the right alignment found roughly; ``"symmetric"``: a different alignment
        that fits the target at least 90 % as well as the truth (a shape that looks the same
        turned: geometry alone cannot tell, an orientation prior can); ``"wrong"``: the rest.
        """
        error = self.rotation_error_deg
        if error < SUCCESS_ROTATION_DEG:
            return None
        if self.pose_failed:
            return "no pose"
        if error < NEAR_MISS_DEG:
            return "near miss"
        if self.fitness(self.T_pred) >= SYMMETRIC_FIT_RATIO * self.fitness(self.T_gt):
            return "symmetric"
        return "wrong"


# ----------------------------------------------------------------------------- per pair
def evaluation_config(
    matching: MatchingConfig = MatchingConfig(),
    estimator: str = "auto",
    verification: VerificationConfig = VerificationConfig(),
) -> RuntimeConfig:
    """The runtime configuration pairs are evaluated with: ``register()``'s defaults (no ICP),
    the checkpoint's matching and ``estimator``. ``verification`` defaults to the bundled
    model's calibration (a checkpoint has none of its own until ``calibrate_success.py`` fits
    one), so the flag's figures of an uncalibrated checkpoint are indicative only."""
    if estimator not in POSE_ESTIMATORS:
        raise ValueError(f"estimator {estimator!r}: expected one of {POSE_ESTIMATORS}")
    return RuntimeConfig(estimator=estimator, matching=matching, verification=verification)


def register_scored_batch(scores: np.ndarray, batch: dict, dustbin_score: float, config: RuntimeConfig):
    """Register every pair of a collated batch from its network scores, through the runtime's
    path (:func:`logdesc_rt.pair.pair_from_scores`, then
    :func:`logdesc_rt.pose_selection.register_matched`).

    Args:
        scores: (B, N, M) matching scores of the batch's pairs.
        batch: the collated samples (:class:`training.data.PairDataset`): their user-frame
            clouds and normalisation.
        dustbin_score: the model's learned dustbin score.
        config: :func:`evaluation_config`.

    Yields:
        (row, :class:`~logdesc_rt.results.RegistrationResult`, seconds) per pair, in batch order.
    """
    for row in range(scores.shape[0]):
        start = time.perf_counter()
        normalization = PairNormalization(
            source_centre=_as_numpy(batch["source_centre"][row]),
            target_centre=_as_numpy(batch["target_centre"][row]),
            scale=float(batch["scale"][row]),
        )
        pair = pair_from_scores(
            _as_numpy(batch["source_user"][row]), _as_numpy(batch["target_user"][row]), normalization,
            _as_numpy(scores[row]), dustbin_score, config,
        )
        result: RegistrationResult = register_matched(pair, config)
        yield row, result, time.perf_counter() - start


def _as_numpy(value) -> np.ndarray:
    """float64 NumPy copy of an array or a (CPU or CUDA) torch tensor."""
    if hasattr(value, "detach"):
        value = value.detach().float().cpu().numpy()
    return np.asarray(value, dtype=np.float64)


# ----------------------------------------------------------------------------- test pairs
def modelnet10_test_dataset(
    data_root=DEFAULT_DATA_ROOT,
    seed: int = DEFAULT_EVAL_SEED,
    geometry_config: GeometryConfig = GeometryConfig(),
    normalization_config: NormalizationConfig = NormalizationConfig(),
    any_orientation: bool = False,
    any_relative_rotation: bool = False,
) -> PairDataset:
    """ModelNet10's test shapes as a :class:`PairDataset` (the only reader of the test split).

    ``any_orientation`` turns both clouds of every pair by a random rotation (the same pairs
    otherwise; ``benchmarks/`` calls these protocols ``<protocol>_rotated``);
    ``any_relative_rotation`` then turns the target alone (relative rotations of any size).
    """
    split = load_modelnet(Path(data_root) / MODELNET10_FOLDER, "test")
    return PairDataset(
        split.points[:, :SOURCE_POINTS], seed, geometry_config, normalization_config, name="test",
        any_orientation=any_orientation, any_relative_rotation=any_relative_rotation,
    )


def validation_dataset(
    checkpoint: dict,
    data_root=DEFAULT_DATA_ROOT,
    seed: int = DEFAULT_EVAL_SEED,
    geometry_config: GeometryConfig = GeometryConfig(),
    normalization_config: NormalizationConfig = NormalizationConfig(),
    any_orientation: bool = False,
    any_relative_rotation: bool = False,
) -> PairDataset:
    """The checkpoint's held-out validation shapes as a :class:`PairDataset`.

    The split is re-carved from the training sources with the checkpoint's own ``--split``,
    ``--val-fraction`` and ``--seed`` (:func:`training.data.run_split`), so it is the set the
    run validated on; the pairs are drawn with ``seed`` like the test pairs.
    """
    train_args = checkpoint.get("train_args") or {}
    shapes = run_split(
        load_training_sources(data_root),
        str(train_args.get("split", "v3")),
        float(train_args.get("val_fraction", DEFAULT_VAL_FRACTION)),
        int(train_args.get("seed", 0)),
    )
    return PairDataset(
        shapes.val, seed, geometry_config, normalization_config, name="val", any_orientation=any_orientation,
        any_relative_rotation=any_relative_rotation,
    )


def evaluation_keys(num_shapes: int, protocols=PAPER_PROTOCOLS, pairs: int | None = None) -> list[PairKey]:
    """Pair i of each protocol is shape i with epoch 0: the first ``pairs`` shapes (all: None)."""
    count = num_shapes if pairs is None else min(int(pairs), num_shapes)
    return [PairKey(0, index, protocol, SOURCE_POINTS) for protocol in protocols for index in range(count)]


def evaluate_model(
    model,
    dataset: PairDataset,
    keys,
    *,
    device="cpu",
    batch_size: int = 8,
    workers: int = 0,
    config: RuntimeConfig | None = None,
    amp: bool = False,
    progress: bool = True,
) -> list[PairResult]:
    """Run the network on the pairs of ``keys`` and register each through the runtime's path.

    The network gives the (B, N, M) scores (descriptor + transformer, no torch Sinkhorn); the
    matches, the candidate poses, the verified pose and the flag are the runtime's
    (:func:`register_scored_batch`), with ``config`` (default: :func:`evaluation_config` of
    the model's Sinkhorn iterations).
    """
    import torch
    from torch.utils.data import DataLoader
    from tqdm import tqdm

    device = torch.device(device)
    if config is None:
        config = evaluation_config(MatchingConfig(sinkhorn_iterations=int(model.config.sinkhorn_iterations)))
    dustbin = float(model.dustbin_score.detach().cpu())
    loader = DataLoader(
        dataset,
        batch_sampler=fixed_pair_batches(list(keys), batch_size),
        num_workers=workers,
        pin_memory=device.type == "cuda",
    )
    results: list[PairResult] = []
    model.eval()
    with tqdm(total=len(keys), desc="evaluate", unit="pair", disable=not progress, dynamic_ncols=True) as bar:
        for batch in loader:
            scores = network_scores(model, batch, device, amp)
            for row, result, seconds in register_scored_batch(scores, batch, dustbin, config):
                source = batch["source_user"][row].numpy()
                results.append(
                    PairResult(
                        protocol=batch["protocol"][row],
                        index=int(batch["index"][row]),
                        T_pred=result.transformation,
                        T_gt=batch["T_gt_user"][row].numpy(),
                        source=source,
                        target=batch["target_user"][row].numpy(),
                        scale=float(batch["scale"][row]),
                        pred_match=correspondences_as_array(result.correspondences, len(source)),
                        gt_match=batch["gt_match_src"][row].numpy(),
                        match_count=len(result.correspondences),
                        pose_failed=result.pose_estimator == "none",
                        seconds=seconds,
                        flagged=result.success,
                        confidence=result.confidence,
                        estimator=result.pose_estimator,
                    )
                )
                bar.update(1)
            if results:
                recent = results[-scores.shape[0] :]
                bar.set_postfix(L_R=f"{np.median([r.rotation_error_deg for r in recent]):.2f}")
    return results


def network_scores(model, batch: dict, device, amp: bool = False) -> np.ndarray:
    """(B, N, M) float64 matching scores of a collated batch (no gradient)."""
    import torch

    device = torch.device(device)
    names = ("src_edges", "src_points", "src_normals", "tgt_edges", "tgt_points", "tgt_normals")
    inputs = {name: batch[name].to(device, non_blocking=True) for name in names}
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp and device.type == "cuda")
    with torch.no_grad(), autocast:
        desc_src = model.describe(inputs["src_edges"], inputs["src_points"], inputs["src_normals"])
        desc_tgt = model.describe(inputs["tgt_edges"], inputs["tgt_points"], inputs["tgt_normals"])
        scores = model.match_scores(
            desc_src, desc_tgt, inputs["src_normals"], inputs["tgt_normals"], inputs["src_points"], inputs["tgt_points"]
        )
    return scores.float().cpu().numpy().astype(np.float64)


# ----------------------------------------------------------------------------- reporting
def summarize(results: list[PairResult]) -> dict[str, dict[str, float]]:
    """Paper metrics per protocol (and ``"all"`` when several), from per-pair results.

    Registration metrics follow :func:`logdesc_rt.metrics.registration_metrics` (user frame);
    matching P/A/R are averaged over pairs with ``nanmean`` (a pair without predicted matches
    has no precision). Extra keys: ``l_r_median``, ``pose_failures``, ``matches_mean``,
    ``pairs``, ``seconds_per_pair`` (NumPy part only), ``rotation_under_5deg``, one
    ``failed_<kind>`` count per :data:`FAILURE_KINDS` (spaces as underscores), and the success
    flag's ``flagged`` share, ``flag_precision`` (flagged pairs with L_R < 5 degrees; NaN when
    none is flagged) and ``flag_recall``.
    """
    protocols = list(dict.fromkeys(result.protocol for result in results))
    groups = {protocol: [r for r in results if r.protocol == protocol] for protocol in protocols}
    summary = {}
    for protocol, group in groups.items():
        metrics = registration_metrics(
            np.stack([r.T_pred for r in group]),
            np.stack([r.T_gt for r in group]),
            sources=[r.source for r in group],
        )
        matching = [matching_metrics(r.pred_match, r.gt_match) for r in group]
        for name in ("precision", "accuracy", "recall"):
            values = np.array([m[name] for m in matching], dtype=np.float64)
            metrics[name] = float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")
        metrics["l_r_median"] = float(np.median([r.rotation_error_deg for r in group]))
        metrics["pose_failures"] = int(sum(r.pose_failed for r in group))
        failures = [r.failure for r in group]
        metrics["rotation_under_5deg"] = float(np.mean([kind is None for kind in failures]))
        for kind in FAILURE_KINDS:
            metrics[f"failed_{kind.replace(' ', '_')}"] = int(sum(f == kind for f in failures))
        metrics["matches_mean"] = float(np.mean([r.match_count for r in group]))
        metrics["seconds_per_pair"] = float(np.mean([r.seconds for r in group]))
        right = np.array([kind is None for kind in failures])
        flagged = np.array([r.flagged for r in group])
        metrics["flagged"] = float(np.mean(flagged))
        metrics["flag_precision"] = float(np.mean(right[flagged])) if flagged.any() else float("nan")
        metrics["flag_recall"] = float(np.mean(flagged[right])) if right.any() else float("nan")
        metrics["pairs"] = len(group)
        summary[protocol] = metrics
    return summary


_COLUMNS = [
    ("RMSE(R)", "rmse_r", "{:.3f}"),
    ("MAE(R)", "mae_r", "{:.3f}"),
    ("RMSE(t)", "rmse_t", "{:.4f}"),
    ("MAE(t)", "mae_t", "{:.4f}"),
    ("L_R", "l_r", "{:.3f}"),
    ("L_R median", "l_r_median", "{:.3f}"),
    ("L_t", "l_t", "{:.4f}"),
    ("L_RMSE", "l_rmse", "{:.4f}"),
    ("P %", "precision", "{:.1f}"),
    ("A %", "accuracy", "{:.1f}"),
    ("R %", "recall", "{:.1f}"),
    ("matches", "matches_mean", "{:.0f}"),
    ("L_R < 5° %", "rotation_under_5deg", "{:.1f}"),
    ("no pose", "failed_no_pose", "{:d}"),
    ("near miss", "failed_near_miss", "{:d}"),
    ("symmetric", "failed_symmetric", "{:d}"),
    ("wrong", "failed_wrong", "{:d}"),
    ("flagged %", "flagged", "{:.1f}"),
    ("flag P %", "flag_precision", "{:.1f}"),
    ("flag R %", "flag_recall", "{:.1f}"),
    ("pairs", "pairs", "{:d}"),
]


def format_markdown(summary: dict, meta: dict | None = None) -> str:
    """A markdown table, one row per protocol (angles in degrees, P/A/R in percent)."""
    lines = []
    if meta:
        lines.append("Evaluation: " + ", ".join(f"{k} = `{v}`" for k, v in meta.items()))
        lines.append("")
    lines.append("| protocol | " + " | ".join(title for title, _, _ in _COLUMNS) + " |")
    lines.append("| --- | " + " | ".join("---:" for _ in _COLUMNS) + " |")
    for protocol, metrics in summary.items():
        cells = []
        for _, key, fmt in _COLUMNS:
            value = metrics.get(key, float("nan"))
            if key in ("precision", "accuracy", "recall", "rotation_under_5deg", "flagged", "flag_precision",
                       "flag_recall"):
                value = 100.0 * value
            if isinstance(value, float) and not math.isfinite(value):
                cells.append("n/a")
            else:
                cells.append(fmt.format(value))
        lines.append(f"| {protocol} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def evaluate_checkpoint(
    checkpoint_path,
    *,
    data_root=DEFAULT_DATA_ROOT,
    protocols=PAPER_PROTOCOLS,
    pairs: int | None = None,
    seed: int = DEFAULT_EVAL_SEED,
    device="cpu",
    batch_size: int = 8,
    workers: int = 0,
    amp: bool = False,
    sinkhorn_iterations: int | None = None,
    match_threshold: float = MatchingConfig().match_threshold,
    estimator: str = "auto",
    progress: bool = True,
    any_orientation: bool = False,
    split: str = "test",
    any_relative_rotation: bool = False,
) -> tuple[dict, list[PairResult], dict]:
    """Load a checkpoint, evaluate it on ModelNet10 test pairs (or, with ``split="val"``, on its
    validation shapes); returns (summary, results, meta)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    checkpoint = load_checkpoint(checkpoint_path)
    model = model_from_checkpoint(checkpoint, device)
    geometry_config, normalization_config = configs_from_checkpoint(checkpoint)
    if split == "val":
        dataset = validation_dataset(
            checkpoint, data_root, seed, geometry_config, normalization_config, any_orientation,
            any_relative_rotation=any_relative_rotation,
        )
    else:
        dataset = modelnet10_test_dataset(data_root, seed, geometry_config, normalization_config, any_orientation,
                                          any_relative_rotation=any_relative_rotation)
    keys = evaluation_keys(len(dataset), protocols, pairs)
    matching = MatchingConfig(
        sinkhorn_iterations=int(sinkhorn_iterations or model.config.sinkhorn_iterations),
        match_threshold=match_threshold,
    )
    config = evaluation_config(matching, estimator)
    start = time.perf_counter()
    results = evaluate_model(
        model, dataset, keys, device=device, batch_size=batch_size, workers=workers, config=config, amp=amp,
        progress=progress,
    )
    meta = {
        "checkpoint": str(checkpoint_path),
        "split": split,
        "step": checkpoint.get("step"),
        "git_commit": checkpoint.get("git_commit", "unknown"),
        "seed": seed,
        "any_orientation": any_orientation,
        "any_relative_rotation": any_relative_rotation,
        "pairs_per_protocol": len(keys) // max(1, len(protocols)),
        "matching": matching.to_dict(),
        "estimator": estimator,
        "wall_time_s": round(time.perf_counter() - start, 1),
    }
    return summarize(results), results, meta


# ----------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m training.evaluate",
        description="Evaluate a LoGDesc checkpoint on ModelNet10 test pairs (paper protocol and metrics).",
    )
    parser.add_argument("checkpoint", type=Path, help="checkpoint .pt written by training.train")
    parser.add_argument("--split", default="test", choices=SPLITS,
                        help="test: ModelNet10 test shapes; val: the checkpoint's held-out validation "
                             "shapes (choose checkpoints on this)")
    parser.add_argument("--protocols", nargs="+", default=list(PAPER_PROTOCOLS), choices=PROTOCOLS,
                        help="the paper's protocols by default; resampled and resampled_partial give each "
                             "cloud its own samples of the shape, as real scans have")
    parser.add_argument("--pairs", type=int, default=None,
                        help=f"pairs per protocol: the first N shapes (default all; {TEST_SHAPES} test shapes)")
    parser.add_argument("--seed", type=int, default=DEFAULT_EVAL_SEED, help="pair seed (default 1234)")
    parser.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    parser.add_argument("--out", type=Path, default=None,
                        help="write <out>.md and <out>.json (suffix .md/.json optional)")
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--workers", type=int, default=None, help="DataLoader workers (default 2 CPU / 12 CUDA)")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    parser.add_argument("--amp", action="store_true", help="bf16 autocast on CUDA (scores only)")
    parser.add_argument("--sinkhorn-iterations", type=int, default=None,
                        help="default: the model config's value")
    parser.add_argument("--match-threshold", type=float, default=MatchingConfig().match_threshold)
    parser.add_argument("--estimator", default="auto", choices=POSE_ESTIMATORS,
                        help="the pose register() returns (auto: every candidate verified, the best kept; "
                             "fsr: the paper's estimator's pose)")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--any-orientation", action="store_true",
                        help="turn both clouds of every pair by a random rotation (same pairs otherwise)")
    parser.add_argument("--any-relative-rotation", action="store_true",
                        help="then turn the target alone by a random rotation: relative rotations of any "
                             "size, as between scans taken from anywhere (the paper's are <= 45 deg per axis)")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import os

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    device = "cuda" if args.device == "auto" and torch.cuda.is_available() else args.device
    device = "cpu" if device == "auto" else device
    workers = args.workers
    if workers is None:
        workers = min(12, max(0, (os.cpu_count() or 2) - 2)) if device == "cuda" else 2
    summary, _, meta = evaluate_checkpoint(
        args.checkpoint, data_root=args.data_root, protocols=args.protocols, pairs=args.pairs,
        seed=args.seed, device=device, batch_size=args.batch_size, workers=workers, amp=args.amp,
        sinkhorn_iterations=args.sinkhorn_iterations, match_threshold=args.match_threshold, estimator=args.estimator,
        progress=not args.no_progress, any_orientation=args.any_orientation, split=args.split,
        any_relative_rotation=args.any_relative_rotation,
    )
    markdown = format_markdown(summary, meta)
    print(markdown)
    if args.out is not None:
        stem = args.out.with_suffix("") if args.out.suffix in (".md", ".json") else args.out
        stem.parent.mkdir(parents=True, exist_ok=True)
        Path(f"{stem}.md").write_text(markdown)
        Path(f"{stem}.json").write_text(json.dumps({"meta": meta, "metrics": summary}, indent=2))
        print(f"wrote {stem}.md and {stem}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
