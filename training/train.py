"""Train the LoGDesc matcher on ModelNet pairs (paper protocol), resumable and time-boxed.

Usage (from the repository root; ``python training/train.py ...`` works too)::

    python -m training.train --preset small --out runs/small --batch-size 8 \
        --max-minutes 25 --val-every 500 --protocol-mix clean:0.2,noisy:0.3,partial:0.5
    python -m training.train --out runs/small --resume auto --max-minutes 25   # continue

Data: ModelNet10 train + the ModelNet40 subset (train), 5 % of each held out by shape name as a
fixed validation set (:mod:`training.data`); ModelNet10's test split is never read here.
Loss: the negative log-likelihood of the ground-truth assignment in the Sinkhorn output
(:func:`training.losses.assignment_nll`) plus ``--aux-descriptor-loss-weight`` x an InfoNCE
loss on the pre-transformer descriptors; with ``--distill-from`` a frozen teacher network runs on
every batch and ``--distill-weight`` x the KL divergence from its Sinkhorn assignment to the
student's is added (:func:`training.losses.assignment_distillation`); with
``--soft-correspondence-weight`` W, W x the distance from the plan's mean target point to each
matched source point's true position (:func:`training.losses.soft_correspondence_distance`).
Optimiser: Adam, linear warm-up, then cosine (to
``--min-lr-ratio`` x lr at ``--decay-steps``, default ``--max-steps``; ``--cycle-start`` starts
a warm restart) or constant.

Outputs in ``--out``:

- ``log.jsonl``: one JSON object a line: ``{"type": "train", ...}`` per logged step (loss
  terms, lr, grad norm, timing), ``{"type": "val", ...}`` per validation (val loss, matching
  precision / accuracy / recall of mutual matches, and the rotation error L_R median / mean /
  share under 5 degrees and the success flag of the pose ``register()`` returns, through the
  runtime's own path; per protocol too), plus ``start`` / ``resume`` / ``checkpoint`` / ``stop`` events. Every line has
  ``step``, ``epoch``, ``pairs_seen`` and ``wall_time_s`` (training wall time accumulated over
  all sessions).
- ``last.pt`` every ``--checkpoint-minutes`` and at exit (also on SIGTERM / SIGINT), ``best.pt``
  whenever the ``--best-metric`` improves. Both are written atomically (temporary file, fsync,
  ``os.replace``) and hold the model, optimiser, scheduler, step, pairs seen, wall time, RNG
  states, the model / geometry / normalisation configs, the arguments, the git commit and the
  best metric. ``--resume auto`` continues from ``--out/last.pt`` (fresh start if absent).

The batch sequence is a pure function of ``--seed`` and the step (:class:`TrainBatchSampler`),
so a resumed run sees exactly the pairs an uninterrupted run would have seen.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

if __package__ in (None, ""):  # run as ``python training/train.py``: import from the repo root
    _here = Path(__file__).resolve().parent
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _here]
    sys.path.insert(0, str(_here.parent))

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from logdesc_rt.config import GeometryConfig, MatchingConfig, NormalizationConfig
from logdesc_rt.matching import correspondences_as_array
from logdesc_rt.metrics import SUCCESS_ROTATION_DEG, matching_metrics, rotation_error_deg
from training.checkpoint import is_weights_only
from training.config import PRESETS, ModelConfig
from training.data import (
    DEFAULT_DATA_ROOT,
    DEFAULT_VAL_FRACTION,
    PROTOCOLS,
    SCAN_PROTOCOL,
    SCAN_SHAPE_WEIGHTINGS,
    SOURCE_POINTS,
    SPLITS,
    PairDataset,
    ProtocolSchedule,
    TrainBatchSampler,
    fixed_pair_batches,
    load_dense_shapes,
    load_training_sources,
    parse_protocol_mix,
    run_split,
    validation_keys,
)
from training.evaluate import evaluation_config, register_scored_batch
from training.geometry_torch import invariant_geometry
from training.losses import (
    INFONCE_TEMPERATURE,
    assignment_distillation,
    assignment_nll,
    descriptor_infonce,
    soft_correspondence_distance,
)
from training.model import LoGDescMatcher
from training.run_state import (
    JsonlLog,
    Progress,
    StopFlag,
    atomic_torch_save,
    git_commit,
    restore_rng_states,
    rng_states,
    seed_everything,
    truncate_log,
)
from training.sinkhorn import log_optimal_transport

DEFAULT_LR = {"paper": 1e-4, "small": 1e-3, "tiny": 1e-3}
# metric name -> True when larger is better
BEST_METRICS = {
    "val_loss": False,
    "val_rot_median_deg": False,
    "val_rot_mean_deg": False,
    "val_recall": True,
    "val_precision": True,
    "val_rot_under_5deg": True,
}
INPUT_NAMES = ("src_edges", "src_points", "src_normals", "tgt_edges", "tgt_points", "tgt_normals")


# ----------------------------------------------------------------------------- arguments
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m training.train",
        description="Train the LoGDesc matcher on ModelNet registration pairs.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    run = parser.add_argument_group("run")
    run.add_argument("--preset", default="small", choices=sorted(PRESETS), help="model size")
    run.add_argument("--out", type=Path, required=True, help="output folder (checkpoints, log.jsonl)")
    run.add_argument("--resume", default=None,
                     help="checkpoint to continue from, or 'auto' for --out/last.pt if present")
    run.add_argument("--init-from", type=Path, default=None,
                     help="a fresh run (step 0, new Adam) starting from this checkpoint's weights; edge channels "
                          "the checkpoint lacks (v3 -> v4's chiral layout) get zero weights, so the network's "
                          "function is unchanged at step 0 (ignored when resuming)")
    run.add_argument("--init-skip", action="append", default=[], metavar="PREFIX",
                     help="with --init-from: parameters whose names start with PREFIX keep this network's own "
                          "initialisation (e.g. 'transformer.' when the transformer's shape or role changed); "
                          "may be repeated")
    run.add_argument("--seed", type=int, default=0, help="model init, data and sampler seed")
    run.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                     help="auto = cuda when available")
    run.add_argument("--amp", action="store_true",
                     help="bf16 autocast for the network on CUDA (Sinkhorn and losses stay float32)")
    run.add_argument("--no-tf32", action="store_true", help="keep float32 matmuls exact on CUDA")
    run.add_argument("--workers", type=int, default=None,
                     help="DataLoader workers (default: 2 on CPU, min(12, cores-2) on CUDA)")
    run.add_argument("--threads", type=int, default=None, help="torch.set_num_threads in the main process")
    run.add_argument("--geometry-on-device", action="store_true",
                     help="compute the geometry per batch on the training device (torch port of the NumPy "
                          "reference; invariant networks only) instead of in the data-loader workers")
    run.add_argument("--max-steps", type=int, default=None, help="stop at this global step")
    run.add_argument("--max-minutes", type=float, default=None,
                     help="stop after this many minutes of this invocation (then resume)")
    run.add_argument("--checkpoint-minutes", type=float, default=5.0, help="write last.pt this often")
    run.add_argument("--log-every", type=int, default=1, help="log a train line every N steps")
    run.add_argument("--no-progress", action="store_true", help="no tqdm bar")

    optim = parser.add_argument_group("optimisation")
    optim.add_argument("--batch-size", type=int, default=8)
    optim.add_argument("--lr", type=float, default=None,
                       help="Adam learning rate (default: 1e-4 paper, 1e-3 small/tiny)")
    optim.add_argument("--weight-decay", type=float, default=0.0)
    optim.add_argument("--warmup-steps", type=int, default=200, help="linear warm-up from 1%% of lr")
    optim.add_argument("--schedule", default="cosine", choices=["cosine", "constant"])
    optim.add_argument("--decay-steps", type=int, default=None,
                       help="cosine horizon in steps (default --max-steps; constant if neither)")
    optim.add_argument("--min-lr-ratio", type=float, default=0.05, help="cosine floor, x lr")
    optim.add_argument("--cycle-start", type=int, default=0,
                       help="optimiser step where the schedule starts over (a warm restart of a finished "
                            "run): warm-up and decay count from it, --decay-steps is the cycle's length")
    optim.add_argument("--grad-clip", type=float, default=1.0, help="max grad norm (0 = off)")
    optim.add_argument("--aux-descriptor-loss-weight", type=float, default=0.1,
                       help="weight of InfoNCE on the pre-transformer descriptors")
    optim.add_argument("--infonce-temperature", type=float, default=INFONCE_TEMPERATURE)
    optim.add_argument("--distill-from", type=Path, default=None, metavar="CHECKPOINT",
                       help="a trained network (any checkpoint reading the same geometry) whose Sinkhorn "
                            "assignment the model learns to reproduce beside the task loss")
    optim.add_argument("--distill-weight", type=float, default=1.0,
                       help="weight of the distillation term (with --distill-from)")
    optim.add_argument("--soft-correspondence-weight", type=float, default=0.0,
                       help="weight of the soft correspondence distance (network units): how far the Sinkhorn "
                            "plan's mean target point lies from each matched source point's true position")

    data = parser.add_argument_group("data")
    data.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT)
    data.add_argument("--protocol-mix", default="clean:0.2,noisy:0.3,partial:0.5",
                      help="protocol weights per batch, e.g. 'clean:0.2,noisy:0.3,partial:0.5'; protocols: "
                           "clean, noisy, partial (the paper's), resampled, resampled_partial (each cloud "
                           "its own half of the shape's points: logdesc_rt/synthetic.py) and scan (two simulated "
                           "range scans of a dense shape: logdesc_rt/scan_simulation.py)")
    data.add_argument("--val-protocol-mix", default=None,
                      help="the validation pairs' protocols (default --protocol-mix); keep a resumed run's "
                           "validation set when its training mix changes")
    data.add_argument("--points-per-cloud", type=int, default=SOURCE_POINTS,
                      help="source points per pair (1024 = paper; partial keeps 75%%)")
    data.add_argument("--working-size", type=int, default=None,
                      help="cut every shape pair's clouds to at most this many points with the runtime's working "
                           "subset (labels from geometry); the model's working size at run time")
    data.add_argument("--scan-points-per-cloud", type=int, default=None,
                      help="points per cloud of 'scan' pairs (default --points-per-cloud)")
    data.add_argument("--scan-shape-weighting", default="uniform", choices=SCAN_SHAPE_WEIGHTINGS,
                      help="how training scan pairs draw their dense shape: uniform (the ModelNet40 subset's own "
                           "mix, 61 %% airplanes) or sqrt-class (a class of c shapes weighs sqrt(c)); "
                           "validation pairs stay uniform")
    data.add_argument("--split", default="v3", choices=SPLITS,
                      help="v3: 5 %% of each source held out for validation (seed --seed); three-way (v4): v3's "
                           "validation shapes become the test shapes, never read here, and validation is a fresh "
                           "5 %% of the rest (training.data.split_train_val_test)")
    data.add_argument("--any-orientation", action="store_true",
                      help="turn both clouds of every training and validation pair by a random rotation "
                           "(the paper's pairs keep the source upright; users' scans are not)")
    data.add_argument("--val-fraction", type=float, default=DEFAULT_VAL_FRACTION, help="of each training source")
    data.add_argument("--val-every", type=int, default=500, help="validate every N steps (0 = never)")
    data.add_argument("--val-pairs", type=int, default=128)
    data.add_argument("--best-metric", default="val_loss", choices=sorted(BEST_METRICS))
    return parser


# ----------------------------------------------------------------------------- helpers
def lr_factor(step: int, args) -> float:
    """Multiplier of the base lr at optimiser step ``step`` (warm-up, then the decay), counted
    from the cycle's start (``--cycle-start``; 0 when ``args`` lacks it, as a hand-built Namespace may)."""
    cycle_start = getattr(args, "cycle_start", 0)
    step = max(0, step - cycle_start)
    if args.warmup_steps > 0 and step < args.warmup_steps:
        return 0.01 + 0.99 * step / args.warmup_steps
    horizon = args.decay_steps or (args.max_steps - cycle_start if args.max_steps else None)
    if args.schedule == "constant" or not horizon:
        return 1.0
    progress = min(1.0, (step - args.warmup_steps) / max(1, horizon - args.warmup_steps))
    return args.min_lr_ratio + (1 - args.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device is available")
    return torch.device(name)


def _worker_init(_worker_id: int) -> None:
    # Geometry is NumPy; keep each worker to one torch thread so workers do not oversubscribe.
    torch.set_num_threads(1)


def to_device(batch: dict, device: torch.device, geometry: GeometryConfig | None = None) -> dict:
    """The batch on ``device``; a batch of bare points (``--geometry-on-device``) gets its
    edges and normals computed there (:func:`training.geometry_torch.invariant_geometry`)."""
    batch = {
        name: value.to(device, non_blocking=True) if isinstance(value, torch.Tensor) else value
        for name, value in batch.items()
    }
    if "src_edges" not in batch:
        if geometry is None:
            raise ValueError("a batch without geometry needs the geometry config")
        for prefix in ("src", "tgt"):
            batch[f"{prefix}_edges"], batch[f"{prefix}_normals"] = invariant_geometry(
                batch[f"{prefix}_points"], geometry
            )
    return batch


def forward(model: LoGDescMatcher, batch: dict, amp: bool) -> dict:
    """Model outputs for a device batch; with ``amp`` the network runs in bf16 autocast but
    the Sinkhorn runs on float32 scores (log-sum-exp in bf16 would lose the assignment)."""
    inputs = [batch[name] for name in INPUT_NAMES]
    if not amp:
        return model(*inputs)
    with torch.autocast("cuda", dtype=torch.bfloat16):
        desc_src = model.describe(inputs[0], inputs[1], inputs[2])
        desc_tgt = model.describe(inputs[3], inputs[4], inputs[5])
        scores = model.match_scores(desc_src, desc_tgt, inputs[2], inputs[5], inputs[1], inputs[4])
    scores = scores.float()
    return {
        "scores": scores,
        "log_assignment": log_optimal_transport(scores, model.dustbin_score, model.config.sinkhorn_iterations),
        "descriptors_src": desc_src.float(),
        "descriptors_tgt": desc_tgt.float(),
    }


def loss_terms(outputs: dict, batch: dict, args, teacher_outputs: dict | None = None) -> dict[str, torch.Tensor]:
    """The weighted loss and its terms (all float32 scalars); ``teacher_outputs`` (the
    teacher's outputs on the same batch) add the distillation term."""
    log_assignment = outputs["log_assignment"].float()
    gt_src, gt_tgt = batch["gt_match_src"], batch["gt_match_tgt"]
    terms = {"nll": assignment_nll(log_assignment, gt_src, gt_tgt)}
    loss = terms["nll"]
    if teacher_outputs is not None:
        terms["distill"] = assignment_distillation(log_assignment, teacher_outputs["log_assignment"].float())
        loss = loss + args.distill_weight * terms["distill"]
    if args.soft_correspondence_weight > 0:
        terms["soft_distance"] = soft_correspondence_distance(
            log_assignment, batch["src_points"], batch["tgt_points"], batch["T_gt"], gt_src
        )
        loss = loss + args.soft_correspondence_weight * terms["soft_distance"]
    if args.aux_descriptor_loss_weight > 0:
        terms["infonce"] = descriptor_infonce(
            outputs["descriptors_src"].float(), outputs["descriptors_tgt"].float(), gt_src,
            args.infonce_temperature,
        )
        loss = loss + args.aux_descriptor_loss_weight * terms["infonce"]
    terms["loss"] = loss
    return terms


# ----------------------------------------------------------------------------- validation
def validate(model, loader, device, args, stop: StopFlag, geometry: GeometryConfig | None = None) -> dict | None:
    """Validation loss, mutual-match P/A/R and the rotation error of the pose ``register()``
    would return (the runtime's path: :func:`training.evaluate.register_scored_batch`, no ICP)
    on the fixed pairs.

    Returns None if a stop signal arrived mid-way (the result would be partial).
    """
    model.eval()
    losses, per_pair = [], []
    start = time.perf_counter()
    config = evaluation_config(MatchingConfig(sinkhorn_iterations=int(model.config.sinkhorn_iterations)))
    dustbin = float(model.dustbin_score.detach().cpu())
    with torch.no_grad():
        for batch in loader:
            if stop:
                model.train()
                return None
            batch = to_device(batch, device, geometry)
            outputs = forward(model, batch, args.amp and device.type == "cuda")
            log_assignment = outputs["log_assignment"].float()
            count = log_assignment.shape[0]
            losses.append((assignment_nll(log_assignment, batch["gt_match_src"], batch["gt_match_tgt"]).item(), count))
            gt_src = batch["gt_match_src"].cpu().numpy()
            for row, result, _ in register_scored_batch(
                outputs["scores"].float().cpu().numpy(), batch, dustbin, config
            ):
                predicted = correspondences_as_array(result.correspondences, len(gt_src[row]))
                true_pose = batch["T_gt_user"][row].cpu().numpy()
                per_pair.append({
                    "protocol": batch["protocol"][row],
                    "rot": float(rotation_error_deg(result.transformation[:3, :3], true_pose[:3, :3])),
                    "matches": len(result.correspondences),
                    "failed": result.pose_estimator == "none",
                    "flagged": result.success,
                    **matching_metrics(predicted, gt_src[row]),
                })
    model.train()
    total = sum(count for _, count in losses)

    def aggregate(rows, prefix):
        rot = np.array([r["rot"] for r in rows])
        result = {
            f"{prefix}rot_median_deg": float(np.median(rot)),
            f"{prefix}rot_mean_deg": float(np.mean(rot)),
            f"{prefix}rot_under_5deg": float(np.mean(rot < SUCCESS_ROTATION_DEG)),
            f"{prefix}flagged": float(np.mean([r["flagged"] for r in rows])),
        }
        flagged = np.array([r["flagged"] for r in rows])
        result[f"{prefix}flag_precision"] = (
            float(np.mean(rot[flagged] < SUCCESS_ROTATION_DEG)) if flagged.any() else float("nan")
        )
        for name in ("precision", "accuracy", "recall"):
            values = np.array([r[name] for r in rows], dtype=np.float64)
            result[f"{prefix}{name}"] = float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")
        return result

    record = {"val_loss": sum(loss * count for loss, count in losses) / max(1, total), "val_pairs": total}
    record.update(aggregate(per_pair, "val_"))
    record["val_matches_mean"] = float(np.mean([r["matches"] for r in per_pair]))
    record["val_pose_failures"] = int(sum(r["failed"] for r in per_pair))
    for protocol in PROTOCOLS:
        rows = [r for r in per_pair if r["protocol"] == protocol]
        if rows:
            record.update(aggregate(rows, f"val_{protocol}_"))
    record["val_time_s"] = time.perf_counter() - start
    return record


# ----------------------------------------------------------------------------- main loop
def checkpoint_dict(model, optimizer, scheduler, progress: Progress, args, model_config) -> dict:
    return {
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict(),
        "step": progress.step,
        "pairs_seen": progress.pairs_seen,
        "wall_time_s": progress.wall_time_s,
        "best_metric": progress.best_metric,
        "best_metric_name": args.best_metric,
        "best_step": progress.best_step,
        "rng_states": rng_states(),
        "model_config": model_config.to_dict(),
        "geometry_config": model_config.geometry().to_dict(),
        "normalization_config": NormalizationConfig().to_dict(),
        "matching_config": MatchingConfig().to_dict(),
        "train_args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "git_commit": git_commit(),
        "torch_version": torch.__version__,
    }


def resolve_resume(args) -> Path | None:
    if args.resume is None:
        return None
    if args.resume == "auto":
        candidate = args.out / "last.pt"
        return candidate if candidate.is_file() else None
    path = Path(args.resume)
    if not path.is_file():
        raise SystemExit(f"--resume {path}: no such checkpoint")
    return path


@dataclass
class TrainingRun:
    """One invocation of training: what :func:`train`'s loop works with.

    Built by :func:`start_run` (fresh or resumed); the loop calls :meth:`optimisation_step`,
    :meth:`validate` and :meth:`save`, and asks :meth:`reason_to_stop` when to end.
    """

    args: argparse.Namespace
    device: torch.device
    amp: bool
    model: LoGDescMatcher
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LambdaLR
    progress: Progress
    geometry: GeometryConfig
    train_loader: DataLoader
    val_loader: DataLoader | None
    batches_per_epoch: int
    log: JsonlLog
    resumed_from: Path | None
    teacher: LoGDescMatcher | None = None  # --distill-from, frozen
    session_start: float = field(default_factory=time.monotonic)
    throughput: float | None = None  # pairs/s, exponential moving average

    def wall_time(self) -> float:
        """Training wall time over all sessions, this one included (seconds)."""
        return self.progress.wall_time_s + (time.monotonic() - self.session_start)

    def stamp(self, kind: str, **extra) -> dict:
        """A log record: its type, the progress counters and ``extra``."""
        progress = self.progress
        return {
            "type": kind, "step": progress.step, "epoch": round(progress.step / self.batches_per_epoch, 4),
            "pairs_seen": progress.pairs_seen, "wall_time_s": round(self.wall_time(), 3), **extra,
        }

    def save(self, name: str = "last.pt") -> None:
        """Write a resumable checkpoint (atomically) into ``--out``."""
        progress = self.progress
        snapshot = Progress(
            progress.step, progress.pairs_seen, self.wall_time(), progress.best_metric, progress.best_step
        )
        atomic_torch_save(
            checkpoint_dict(self.model, self.optimizer, self.scheduler, snapshot, self.args, self.model.config),
            self.args.out / name,
        )

    def reason_to_stop(self, stop: StopFlag) -> str | None:
        """Why the loop must end before the next step, or None."""
        if self.args.max_steps is not None and self.progress.step >= self.args.max_steps:
            return "max_steps"
        if self.args.max_minutes is not None and time.monotonic() - self.session_start >= 60 * self.args.max_minutes:
            return "max_minutes"
        if stop:
            return f"signal {stop.signal_name}"
        return None

    def optimisation_step(self, batch: dict, fetch_start: float) -> dict:
        """Forward, loss, backward, clipped Adam step and lr schedule on one host batch.

        A non-finite loss or gradient skips the update but still counts the step, so the
        batch sequence stays aligned with the step. Returns the step's log record.
        """
        compute_start = time.perf_counter()
        batch = to_device(batch, self.device, self.geometry)
        teacher_outputs = None
        if self.teacher is not None:
            with torch.no_grad():
                teacher_outputs = forward(self.teacher, batch, self.amp)
        terms = loss_terms(forward(self.model, batch, self.amp), batch, self.args, teacher_outputs)
        self.optimizer.zero_grad(set_to_none=True)
        grad_norm, skipped = float("nan"), True
        if torch.isfinite(terms["loss"]):
            terms["loss"].backward()
            clip = self.args.grad_clip if self.args.grad_clip > 0 else float("inf")
            grad_norm = float(torch.nn.utils.clip_grad_norm_(self.model.parameters(), clip))
            skipped = not math.isfinite(grad_norm)
            if not skipped:
                self.optimizer.step()
        self.scheduler.step()
        if self.device.type == "cuda":
            torch.cuda.synchronize()
        end = time.perf_counter()

        batch_size = int(batch["src_points"].shape[0])
        self.progress.step += 1
        self.progress.pairs_seen += batch_size
        rate = batch_size / max(1e-9, end - fetch_start)
        self.throughput = rate if self.throughput is None else 0.9 * self.throughput + 0.1 * rate
        return self.stamp(
            "train", **{name: float(value.detach()) for name, value in terms.items()},
            lr=self.optimizer.param_groups[0]["lr"], grad_norm=grad_norm, skipped=skipped,
            protocol=batch["protocol"][0], points=int(batch["src_points"].shape[1]),
            data_s=round(compute_start - fetch_start, 4), compute_s=round(end - compute_start, 4),
            pairs_per_s=round(self.throughput, 3),
        )

    def validate(self, stop: StopFlag, bar) -> None:
        """Validate on the fixed pairs, log the result and keep ``best.pt`` if it improved."""
        if self.val_loader is None:
            return
        result = validate(self.model, self.val_loader, self.device, self.args, stop, self.geometry)
        if result is None:  # a stop signal arrived mid-way
            return
        progress, value = self.progress, result[self.args.best_metric]
        larger_is_better = BEST_METRICS[self.args.best_metric]
        improved = math.isfinite(value) and (
            progress.best_metric is None
            or (value > progress.best_metric if larger_is_better else value < progress.best_metric)
        )
        if improved:
            progress.best_metric, progress.best_step = value, progress.step
        self.log.write(self.stamp("val", **result, best=improved))
        if improved:
            self.save("best.pt")
        bar.write(
            f"[val step {progress.step}] loss {result['val_loss']:.4f}  "
            f"P/A/R {result['val_precision']:.3f}/{result['val_accuracy']:.3f}/{result['val_recall']:.3f}  "
            f"L_R median {result['val_rot_median_deg']:.2f} mean {result['val_rot_mean_deg']:.2f} deg"
            + ("  (best)" if improved else "")
        )


def start_run(args) -> TrainingRun:
    """Everything the loop needs: model and optimiser (fresh, or restored from ``--resume``
    with their schedule, counters and RNG states), the data and the log."""
    args.out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    if device.type == "cuda" and not args.no_tf32:
        torch.set_float32_matmul_precision("high")
    workers = args.workers
    if workers is None:
        workers = min(12, max(0, (os.cpu_count() or 2) - 2)) if device.type == "cuda" else 2

    resume_path = resolve_resume(args)
    checkpoint = torch.load(resume_path, map_location="cpu", weights_only=False) if resume_path else None
    if checkpoint is not None:
        model_config = ModelConfig.from_dict(checkpoint["model_config"])
        saved_preset = checkpoint.get("train_args", {}).get("preset")
        if saved_preset and saved_preset != args.preset:
            print(f"note: resuming a '{saved_preset}' checkpoint; --preset {args.preset} ignored", file=sys.stderr)
            args.preset = saved_preset
    else:
        model_config = ModelConfig.preset(args.preset)
    if args.lr is None:
        args.lr = DEFAULT_LR.get(args.preset, 1e-3)

    seed_everything(args.seed)
    model = LoGDescMatcher(model_config).to(device)
    if checkpoint is None and args.init_from is not None:
        warm_start(
            model, torch.load(args.init_from, map_location="cpu", weights_only=False)["model"],
            skip=tuple(args.init_skip),
        )
    teacher = load_teacher(args.distill_from, model_config, device) if getattr(args, "distill_from", None) else None
    optimizer = torch.optim.Adam(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: lr_factor(step, args))
    progress = Progress() if checkpoint is None else _restore(checkpoint, model, optimizer, scheduler, args)
    del checkpoint

    geometry = model_config.geometry()
    if args.geometry_on_device and geometry.edge_layout not in ("invariant", "chiral"):
        raise SystemExit("--geometry-on-device: only the invariant networks' geometry has a torch port")
    train_loader, val_loader, batches_per_epoch = _loaders(args, geometry, device, workers, progress.step)

    log_path = args.out / "log.jsonl"
    if resume_path is not None:
        truncate_log(log_path, progress.step)
    run = TrainingRun(
        args=args, device=device, amp=bool(args.amp and device.type == "cuda"), model=model,
        optimizer=optimizer, scheduler=scheduler,
        progress=progress, geometry=geometry, train_loader=train_loader, val_loader=val_loader,
        batches_per_epoch=batches_per_epoch, log=JsonlLog(log_path), resumed_from=resume_path, teacher=teacher,
    )
    run.log.write(run.stamp(
        "resume" if resume_path else "start",
        checkpoint=str(resume_path) if resume_path else None, device=str(device), workers=workers,
        amp=run.amp, preset=args.preset, parameters=sum(p.numel() for p in model.parameters()),
        train_shapes=len(train_loader.dataset), val_shapes=len(val_loader.dataset) if val_loader else 0,
        batches_per_epoch=batches_per_epoch, git_commit=git_commit(),
        args={k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
    ))
    return run


def load_teacher(path: Path, model_config: ModelConfig, device: torch.device) -> LoGDescMatcher:
    """The frozen teacher of ``--distill-from``, in eval mode on ``device``.

    Raises:
        SystemExit: the teacher reads other geometry than the model (each batch's edges and
            normals are computed once, for both).
    """
    checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    teacher_config = ModelConfig.from_dict(checkpoint["model_config"])
    if teacher_config.geometry() != model_config.geometry():
        raise SystemExit(
            f"--distill-from {path}: the teacher reads {teacher_config.geometry()}, the model "
            f"{model_config.geometry()}; both must read the same geometry"
        )
    teacher = LoGDescMatcher(teacher_config)
    teacher.load_state_dict(checkpoint["model"])
    teacher.requires_grad_(False)
    return teacher.eval().to(device)


def warm_start(model: LoGDescMatcher, state: dict, skip: tuple[str, ...] = ()) -> None:
    """Load ``state`` into ``model``; a tensor wider than its saved one along the input
    channels (the first edge convolution, when the edge layout gained channels) takes the
    saved weights in its first columns and zeros in the rest, so the function is unchanged.
    Parameters whose names start with a prefix in ``skip`` keep the model's own values; saved
    parameters the model lacks (the transformer's layers, for a descriptor-only model) are unused.

    Raises:
        ValueError: a parameter is missing, or differs in another way than that.
    """
    own = {name: tensor for name, tensor in model.state_dict().items() if not name.startswith(skip)}
    missing = sorted(set(own) - set(state))
    if missing:
        raise ValueError(f"--init-from: the checkpoint lacks {missing[:5]}")
    for name, tensor in own.items():
        saved = state[name]
        if saved.shape == tensor.shape:
            tensor.copy_(saved)
        elif saved.ndim == tensor.ndim and saved.ndim >= 2 and saved.shape[0] == tensor.shape[0] and \
                saved.shape[2:] == tensor.shape[2:] and saved.shape[1] < tensor.shape[1]:
            tensor.zero_()
            tensor[:, : saved.shape[1]].copy_(saved)
        else:
            raise ValueError(f"--init-from: {name} is {tuple(saved.shape)} there, {tuple(tensor.shape)} here")


def _restore(checkpoint: dict, model, optimizer, scheduler, args) -> Progress:
    """Load the model, Adam and schedule states and the RNG states; the counters to continue.

    A weights-only checkpoint (:func:`training.checkpoint.weights_only`) continues the counters
    and the schedule with fresh Adam moments and RNG streams seeded from ``--seed`` and the step:
    repeatable, but not the run that would have continued from the full checkpoint."""
    model.load_state_dict(checkpoint["model"])
    step = int(checkpoint["step"])
    if is_weights_only(checkpoint):
        print("note: weights-only checkpoint: Adam's moments and the RNG streams start afresh", file=sys.stderr)
        scheduler.last_epoch = step
        seed_everything(args.seed + step)
    else:
        optimizer.load_state_dict(checkpoint["optimizer"])
        scheduler.load_state_dict(checkpoint["scheduler"])
        restore_rng_states(checkpoint["rng_states"])
    for group in optimizer.param_groups:  # the CLI's lr wins (e.g. a resumed fine-tune)
        group["initial_lr"] = args.lr
    scheduler.base_lrs = [args.lr for _ in scheduler.base_lrs]
    same_metric = checkpoint.get("best_metric_name", args.best_metric) == args.best_metric
    progress = Progress(
        step=step,
        pairs_seen=int(checkpoint["pairs_seen"]),
        wall_time_s=float(checkpoint["wall_time_s"]),
        best_metric=checkpoint.get("best_metric") if same_metric else None,
        best_step=checkpoint.get("best_step"),
    )
    # The scheduler's lambda closes over args: re-evaluate the lr at the restored step.
    for group in optimizer.param_groups:
        group["lr"] = args.lr * lr_factor(progress.step, args)
    return progress


def _loaders(args, geometry: GeometryConfig, device, workers: int, start_step: int):
    """(train loader, validation loader or None, batches per epoch): ModelNet10 train + the
    ModelNet40 subset, the validation split carved by shape name (:mod:`training.data`)."""
    sources = load_training_sources(args.data_root)
    shapes = run_split(sources, args.split, args.val_fraction, args.seed)
    mix = parse_protocol_mix(args.protocol_mix)
    val_mix = parse_protocol_mix(args.val_protocol_mix) if args.val_protocol_mix else mix
    dense = {"train": None, "val": None}
    if mix.get(SCAN_PROTOCOL, 0.0) > 0 or val_mix.get(SCAN_PROTOCOL, 0.0) > 0:
        all_dense = load_dense_shapes(args.data_root)
        dense = {"train": all_dense.subset(shapes.train_names), "val": all_dense.subset(shapes.val_names)}
    schedule = ProtocolSchedule(
        mix=mix, points_per_cloud=args.points_per_cloud, scan_points_per_cloud=args.scan_points_per_cloud,
    )
    datasets = {
        name: PairDataset(
            split, args.seed, geometry_config=geometry, name=name, any_orientation=args.any_orientation,
            geometry_on_device=bool(args.geometry_on_device), dense=dense[name],
            # getattr: a hand-built Namespace (tests) may predate the flag.
            scan_shape_weighting=getattr(args, "scan_shape_weighting", "uniform") if name == "train" else "uniform",
            working_size=getattr(args, "working_size", None),
        )
        for name, split in (("train", shapes.train), ("val", shapes.val))
    }
    sampler = TrainBatchSampler(len(datasets["train"]), args.batch_size, schedule, args.seed, start_step=start_step)
    options = dict(
        num_workers=workers, pin_memory=device.type == "cuda", worker_init_fn=_worker_init if workers > 0 else None,
    )
    train_loader = DataLoader(
        datasets["train"], batch_sampler=sampler, persistent_workers=workers > 0,
        prefetch_factor=4 if workers > 0 else None, **options,
    )
    val_loader = None
    if args.val_every > 0 and args.val_pairs > 0:
        keys = validation_keys(
            len(datasets["val"]), args.val_pairs, val_mix, args.seed, args.points_per_cloud,
            args.scan_points_per_cloud,
        )
        val_loader = DataLoader(
            datasets["val"], batch_sampler=fixed_pair_batches(keys, args.batch_size), **options,
        )
    return train_loader, val_loader, sampler.batches_per_epoch


def train(args) -> int:
    """Run (or continue) training; returns the process exit code.

    The loop: take the next batch of the fixed sequence, take one optimisation step, log it;
    validate every ``--val-every`` steps (keeping ``best.pt``) and checkpoint every
    ``--checkpoint-minutes``; stop at ``--max-steps``, after ``--max-minutes`` or on a signal,
    always leaving a resumable ``last.pt``.
    """
    run = start_run(args)
    stop = StopFlag()
    stop.install()
    reason, exit_code = "max_steps", 0
    last_checkpoint = time.monotonic()
    last_validated = run.progress.step if run.resumed_from else -1
    bar = tqdm(
        total=args.max_steps, initial=run.progress.step, unit="step", dynamic_ncols=True,
        disable=args.no_progress, desc=f"train {args.preset}",
    )
    run.model.train()
    try:
        batches = iter(run.train_loader)
        while (stopping := run.reason_to_stop(stop)) is None:
            fetch_start = time.perf_counter()
            try:
                batch = next(batches)
            except Exception:
                if stop:  # a worker died of the same Ctrl-C: not an error
                    stopping = f"signal {stop.signal_name}"
                    break
                raise
            record = run.optimisation_step(batch, fetch_start)
            if run.progress.step % max(1, args.log_every) == 0 or record["skipped"]:
                run.log.write(record)
            bar.update(1)
            bar.set_postfix(loss=f"{record['loss']:.3f}", lr=f"{record['lr']:.2e}", pairs_s=f"{run.throughput:.1f}")

            if args.val_every > 0 and run.progress.step % args.val_every == 0:
                run.validate(stop, bar)
                last_validated = run.progress.step
            if time.monotonic() - last_checkpoint >= 60 * args.checkpoint_minutes:
                run.save()
                last_checkpoint = time.monotonic()
                run.log.write(run.stamp("checkpoint", path="last.pt"))
        reason = stopping
        if reason == "max_steps" and run.val_loader is not None and last_validated != run.progress.step:
            run.validate(stop, bar)  # final validation, so best.pt reflects the end of the run
    except KeyboardInterrupt:  # a second Ctrl-C
        reason, exit_code = "keyboard interrupt", 130
    finally:
        bar.close()
        run.save()
        run.log.write(run.stamp("stop", reason=reason))
        run.log.close()
        stop.uninstall()
    print(f"stopped at step {run.progress.step} ({reason}); wall time {run.wall_time():.1f} s; "
          f"checkpoint {args.out / 'last.pt'}")
    return exit_code


def main(argv=None) -> int:
    return train(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
