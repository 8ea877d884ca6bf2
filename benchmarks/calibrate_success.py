"""Calibrate the success flag (``logdesc_rt/verification.py``) on validation pairs only.

Never the test split: the pairs are built from the training run's held-out *validation*
shapes (``training.data.split_training_shapes``: 5 % of ModelNet10's train split and of the
ModelNet40 train subset, seed 0), and optionally from the Bunny scan pairs that
``benchmarks/bunny.py`` does *not* benchmark (measured overlap below its 0.3 threshold).

Two steps, both resumable:

    python benchmarks/calibrate_success.py collect [--count 120] [--threads 1] [--model-dir DIR --cache DIR]
        runs the network once per pair and caches the matches (runs/success_calibration/)
    python benchmarks/calibrate_success.py fit [--cache DIR --report STEM] [--manifest MODEL_DIR] [--folds 5]
        computes the verification features of every candidate pose, fits the logistic model
        and the threshold, writes benchmarks/results/success_calibration.{md,json} with the
        flag on the calibration pairs (in-sample) and held out by shape folds; with
        --manifest, also writes the calibration into that model's manifest ("runtime" ->
        "verification"), where the runtime reads it (a calibration belongs to one model)

Pair groups (the synthetic ones from validation shapes, noise sigma 0.01, independent crops,
both clouds turned by one random rotation so that no canonical pose helps):

- ``val_in_range``: the training motion (Euler angles in [0, 45] deg per axis, translation
  in [-0.5, 0.5]); the model mostly succeeds;
- ``val_any_rotation``: the same pairs with the target turned further about its centroid by a
  uniformly random rotation: relative rotations of any size, where the model mostly fails;
- ``val_small_overlap``: the training motion with harder crops (512 of 1024 points kept);
- ``val_resampled_partial``: the training motion, "resampled_partial" protocol: each cloud
  its own half of the shape's samples (no point has an exact twin, as in real scan pairs);
- ``bunny_unbenchmarked``: real scan pairs with overlap < 0.3 (full scans, metres). Left out
  for v4 on: ``align_bunny.py`` registers every Bunny pair, so these are test pairs too;
- ``val_scan``: two simulated range scans of a validation shape (``logdesc_rt.scan_simulation``,
  raw views with stray points and outliers, any relative pose), as real scan pairs come;
- ``bunny_init_near_truth`` (fit only): those pairs with an initial guess near the truth
  among the candidates (3 deg, 1 % of the radius off), for right poses on real scans.

Every random choice comes from ``default_rng([SEED, group number, pair index])``.

``--split three-way`` (v4) draws the validation shapes of ``training.data.split_train_val_test``;
the default ``v3`` those of ``split_training_shapes`` (seed 0), which are v4's test shapes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from logdesc_rt import Registrar  # noqa: E402
from logdesc_rt.config import CANDIDATE_ESTIMATORS  # noqa: E402
from logdesc_rt.config import VERIFICATION_FEATURES as FEATURES  # noqa: E402
from logdesc_rt.synthetic import make_pair  # noqa: E402

SEED = 20261130
CACHE = ROOT / "runs" / "success_calibration"
# Appended, never reordered: a group's number seeds its pairs.
GROUPS = (
    "val_in_range", "val_any_rotation", "val_small_overlap", "bunny_unbenchmarked", "val_resampled_partial", "val_scan",
)
SPLITS = ("v3", "three-way")
SYNTHETIC_PROTOCOL = {"val_resampled_partial": "resampled_partial"}  # the others: "partial"
MODEL_RECORD = "model.json"  # in the cache: which model the cached matches are from
# Built from the cached bunny_unbenchmarked matches at fit time (no network run): the same
# pairs with one more candidate, an initial guess 3 deg / 1 % of the radius from the truth.
# The network fails on every unbenchmarked pair, so without it the calibration would see no
# right pose on a real scan.
INIT_GROUP = "bunny_init_near_truth"
INIT_GROUP_NUMBER = 4  # seeds its candidates; the number of groups when it was added, kept fixed
INIT_ROTATION_DEG = 3.0
INIT_TRANSLATION_FRACTION = 0.01


def synthetic_pairs(group: str, count: int, split: str = "v3"):
    """Yield (name, source, target, truth) for the validation-shape groups."""
    from training.data import load_dense_shapes, load_training_sources, split_train_val_test, split_training_shapes

    sources = load_training_sources()
    shapes = split_train_val_test(sources).shapes if split == "three-way" else split_training_shapes(sources)
    number = GROUPS.index(group)
    if group == "val_scan":
        from logdesc_rt.scan_simulation import make_scan_pair

        dense = load_dense_shapes().subset(shapes.val_names)
        for index in range(count):
            shape = index % len(dense.points)
            pair = make_scan_pair(dense.points[shape], dense.normals[shape],
                                  np.random.default_rng([SEED, number, index]),
                                  points_per_cloud=None)
            yield f"{group}/{index:04d}", pair.source, pair.target, pair.T_gt
        return
    for index in range(min(count, len(shapes.val))):
        rng = np.random.default_rng([SEED, number, index])
        partial = 512 if group == "val_small_overlap" else None
        protocol = SYNTHETIC_PROTOCOL.get(group, "partial")
        pair = make_pair(shapes.val[index], protocol, rng, partial_points=partial, any_orientation=True,
                         any_relative_rotation=group == "val_any_rotation")
        yield f"{group}/{index:04d}", pair.source, pair.target, pair.T_gt


def bunny_pairs():
    """Yield (name, source, target, truth) for the Bunny pairs bunny.py does not benchmark."""
    from bunny import DEFAULT_MIN_OVERLAP, load_scans, measure_overlaps, relative_pose

    scans = load_scans()
    for pair in measure_overlaps(scans):
        if pair.overlap >= DEFAULT_MIN_OVERLAP:
            continue  # benchmarked: never calibrate on it
        source, target = scans[pair.source], scans[pair.target]
        yield (f"bunny_unbenchmarked/{source.stem}-{target.stem}", source.points, target.points,
               relative_pose(source, target))


def model_record(model_dir: Path | None) -> dict[str, str]:
    """The model a cache's matches come from: its description and the fingerprint of what
    makes its matches (calibration left out, so ``fit --manifest`` keeps the cache usable)."""
    from common import bundled_model_id, model_description

    return {"id": bundled_model_id(model_dir, without_calibration=True), "description": model_description(model_dir)}


def collect(
    groups: list[str], count: int, threads: int, model_dir: Path | None = None, cache: Path = CACHE, split: str = "v3"
) -> None:
    registrar = Registrar(model_dir, threads=threads)
    record = model_record(model_dir)
    record_path = cache / MODEL_RECORD
    if record_path.exists() and json.loads(record_path.read_text())["id"] != record["id"]:
        raise SystemExit(f"{cache} holds another model's matches ({record_path}); use another --cache")
    if record_path.exists() and json.loads(record_path.read_text()).get("split", split) != split:
        raise SystemExit(f"{cache} holds pairs of the {json.loads(record_path.read_text())['split']!r} split; "
                         "use another --cache")
    cache.mkdir(parents=True, exist_ok=True)
    record_path.write_text(json.dumps({**record, "split": split}, indent=1) + "\n")
    for group in groups:
        (cache / group).mkdir(parents=True, exist_ok=True)
        pairs = bunny_pairs() if group == "bunny_unbenchmarked" else synthetic_pairs(group, count, split)
        started = time.perf_counter()
        done = 0
        for name, source, target, truth in pairs:
            path = cache / f"{name}.npz"
            if path.exists():
                continue
            matched = registrar.match(source, target)
            np.savez_compressed(
                path,
                source=source,
                target=target,
                truth=truth,
                source_network=matched.source_network,
                target_network=matched.target_network,
                source_index=matched.source_index,
                target_index=matched.target_index,
                match_source=matched.matches.source_index,
                match_target=matched.matches.target_index,
                confidence=matched.matches.confidence,
                descriptor_match_source=matched.descriptor_matches.source_index,
                descriptor_match_target=matched.descriptor_matches.target_index,
                descriptor_confidence=matched.descriptor_matches.confidence,
                source_centre=matched.normalization.source_centre,
                target_centre=matched.normalization.target_centre,
                scale=matched.normalization.scale,
            )
            done += 1
        print(f"{group}: {done} new pairs in {time.perf_counter() - started:.0f} s", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    collecting = commands.add_parser("collect", help="run the network on the calibration pairs, cache the matches")
    collecting.add_argument("--groups", nargs="+", choices=GROUPS, default=list(GROUPS))
    collecting.add_argument("--count", type=int, default=120, help="pairs per synthetic group")
    collecting.add_argument("--threads", type=int, default=1)
    collecting.add_argument("--model-dir", type=Path, default=None, help="exported model (default: the bundled one)")
    collecting.add_argument("--split", choices=SPLITS, default="v3",
                            help="whose validation shapes: v3's (split_training_shapes) or v4's (three-way)")
    fitting = commands.add_parser("fit", help="features, logistic fit, threshold; writes the report")
    fitting.add_argument("--groups", nargs="+", choices=(*GROUPS, INIT_GROUP), default=[*GROUPS, INIT_GROUP])
    fitting.add_argument("--report", type=Path, default=REPORT, help="report path without suffix")
    fitting.add_argument("--candidates", nargs="+", default=None, choices=CANDIDATE_ESTIMATORS,
                         help="the candidate estimators the calibration is fitted with (stored with it in the "
                              "manifest; default: VerificationConfig's)")
    fitting.add_argument("--descriptor-consensus", nargs="*", default=None, choices=CANDIDATE_ESTIMATORS,
                         help="the estimators run on the descriptors' own mutual nearest neighbours (none: "
                              "give the flag alone; default: VerificationConfig's)")
    fitting.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                         help="VerificationConfig settings over its defaults, VALUE as JSON (e.g. "
                              "refit_plane_steps=3 turn_over_spin=true); stored with the calibration")
    fitting.add_argument("--folds", type=int, default=5,
                         help="held-out estimate of the flag by shape folds (0 or 1: none)")
    fitting.add_argument("--split", choices=SPLITS, default="v3",
                         help="whose validation shapes the cache holds, for the folds (a cache that records its "
                              "own split uses that one)")
    fitting.add_argument("--manifest", type=Path, default=None, metavar="MODEL_DIR",
                         help="write the calibration into this model's manifest.json (the model collected with)")
    counting = commands.add_parser(
        "count", help="per group, the pairs whose chosen hypothesis is right (verified, without ICP) and the claims"
    )
    counting.add_argument("--report", type=Path, default=None,
                          help="a fit's report (.json) whose calibration chooses and flags (default: --model-dir's)")
    counting.add_argument("--model-dir", type=Path, default=None, help="a model whose manifest's calibration is used "
                                                                       "(default: the bundled one)")
    counting.add_argument("--by-class", action="store_true",
                          help="also count the scan pairs by their shape's class (three-way split caches)")
    for command in (collecting, fitting, counting):
        command.add_argument("--cache", type=Path, default=CACHE, help="the matches' cache (one per model)")
    args = parser.parse_args(argv)
    if args.command == "collect":
        collect(args.groups, args.count, args.threads, args.model_dir, args.cache, args.split)
    elif args.command == "count":
        if not (args.cache / "hypotheses.json").exists():
            parser.error(f"{args.cache}: no hypotheses.json; run fit on this cache first")
        print_counts(args.cache, args.report, args.model_dir, args.by_class)
    else:
        from logdesc_rt.config import VerificationConfig

        settings = {}
        for item in args.set:
            key, equals, value = item.partition("=")
            if not equals or key not in VerificationConfig.__dataclass_fields__:
                parser.error(f"--set {item!r}: expected KEY=VALUE with KEY a VerificationConfig field")
            try:
                settings[key] = json.loads(value)
            except json.JSONDecodeError:
                parser.error(f"--set {item!r}: VALUE must be JSON (true, 3, 0.1, [\"ransac\"])")
        fit(args.groups, args.cache, args.report, args.manifest, args.candidates, args.descriptor_consensus,
            args.folds, args.split, settings)
    return 0


# ----------------------------------------------------------------------------- fitting
# A pose is right below this rotation error and this translation error (a fraction of the
# pair's scale): the success criterion of every benchmark (logdesc_rt.metrics).
from logdesc_rt.metrics import SUCCESS_ROTATION_DEG as ROTATION_LIMIT_DEG  # noqa: E402
from logdesc_rt.metrics import SUCCESS_TRANSLATION_FRACTION as TRANSLATION_LIMIT  # noqa: E402

TARGET_PRECISION = 0.97  # aim above the 95 % goal, for the margin between calibration and use
# The fast exit skips the rest of verification: its claims must be right more often still.
EXIT_TARGET_PRECISION = 0.99
L2_PENALTY = 1e-2
REPORT = ROOT / "benchmarks" / "results" / "success_calibration"


def is_right(pose: np.ndarray, truth: np.ndarray, scale: float) -> bool:
    """The benchmarks' success criterion: rotation < 5 deg, translation < 5 % of the scale."""
    from logdesc_rt.metrics import rotation_error_deg

    return bool(
        rotation_error_deg(pose[:3, :3], truth[:3, :3]) < ROTATION_LIMIT_DEG
        and np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < TRANSLATION_LIMIT * scale
    )


def _near_truth(truth: np.ndarray, scale: float, rng: np.random.Generator) -> np.ndarray:
    """``truth`` moved by INIT_ROTATION_DEG about a random axis and a random translation."""
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    moved = np.eye(4)
    moved[:3, :3] = Rotation.from_rotvec(np.deg2rad(INIT_ROTATION_DEG) * axis / np.linalg.norm(axis)).as_matrix()
    moved[:3, 3] = INIT_TRANSLATION_FRACTION * scale * direction / np.linalg.norm(direction)
    return moved @ truth


def pair_hypotheses(path: Path, config, with_init: bool = False) -> list[dict]:
    """Every distinct hypothesis of one cached pair: features and whether it is right."""
    from logdesc_rt.config import RuntimeConfig
    from logdesc_rt.matching import Matches
    from logdesc_rt.metrics import rotation_error_deg
    from logdesc_rt.normalization import PairNormalization
    from logdesc_rt.pose.candidates import candidate_poses, descriptor_candidate_poses
    from logdesc_rt.pose_selection import coarse_pose, pose_without_icp, verify_candidates
    from logdesc_rt.verification import PoseVerifier

    data = np.load(path)
    if len(data["confidence"]) < 3:
        return []
    normalization = PairNormalization(data["source_centre"], data["target_centre"], float(data["scale"]))
    source_matched = data["source_network"][data["match_source"]]
    target_matched = data["target_network"][data["match_target"]]
    candidates = [
        (name, normalization.pose_to_user_frame(pose))
        for name, pose in candidate_poses(source_matched, target_matched, data["confidence"],
                                          top_k_fraction=config.top_k_fraction, estimators=config.candidates)
    ]
    if config.descriptor_consensus:
        if "descriptor_match_source" not in data:
            raise SystemExit(f"{path} was collected without the descriptors' matches: collect into a new --cache")
        descriptor_matches = Matches(
            data["descriptor_match_source"], data["descriptor_match_target"], data["descriptor_confidence"]
        )
        candidates += [
            (name, normalization.pose_to_user_frame(pose))
            for name, pose in descriptor_candidate_poses(
                data["source_network"], data["target_network"], descriptor_matches,
                top_k_fraction=config.top_k_fraction, estimators=config.descriptor_consensus,
            )
        ]
    if with_init:
        rng = np.random.default_rng([SEED, INIT_GROUP_NUMBER, int.from_bytes(path.stem.encode(), "little") % 2**32])
        candidates.append(("init", _near_truth(data["truth"], float(data["scale"]), rng)))
    source_index, target_index = data["source_index"], data["target_index"]
    source_user, target_user = (
        data["source"][source_index[data["match_source"]]],
        data["target"][target_index[data["match_target"]]],
    )
    verifier = PoseVerifier(
        data["source"], data["target"], source_user, target_user, data["confidence"], float(data["scale"]), config
    )
    verified = verify_candidates(
        verifier, candidates, normalization, source_matched, target_matched, data["confidence"],
        RuntimeConfig(verification=config),
    )
    truth, scale = data["truth"], float(data["scale"])
    rows = []
    for hypothesis in verified.hypotheses:
        # What register() returns without ICP were this hypothesis chosen.
        refit = coarse_pose(
            hypothesis, source_user, target_user, data["confidence"], data["target"][target_index], config
        )
        unrefined, claimable = pose_without_icp(
            hypothesis, refit, verifier.pose_within_verified(refit, hypothesis), config
        )
        rows.append({
            "pair": f"{INIT_GROUP if with_init else path.parent.name}/{path.stem}",
            "group": INIT_GROUP if with_init else path.parent.name,
            "estimators": list(hypothesis.estimators),
            "refined": hypothesis.refined,
            "features": [hypothesis.features[name] for name in FEATURES],
            "verified_right": is_right(hypothesis.verified_transformation, truth, scale),
            "verified_error_deg": float(rotation_error_deg(hypothesis.verified_transformation[:3, :3], truth[:3, :3])),
            "unrefined_right": is_right(unrefined, truth, scale),
            "unrefined_claimable": claimable,
        })
    return rows


def fit_logistic(features: np.ndarray, labels: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, float]:
    """L2-regularised weighted logistic regression (scipy L-BFGS); returns (coefficients, bias)."""
    from scipy.optimize import minimize

    mean, spread = features.mean(axis=0), features.std(axis=0) + 1e-9
    scaled = (features - mean) / spread
    targets = labels.astype(np.float64)

    def loss(parameters: np.ndarray) -> tuple[float, np.ndarray]:
        z = scaled @ parameters[:-1] + parameters[-1]
        probability = 1.0 / (1.0 + np.exp(-z))
        log_likelihood = weights * (np.logaddexp(0.0, z) - targets * z)
        gradient_z = weights * (probability - targets)
        value = log_likelihood.sum() / weights.sum() + L2_PENALTY * np.sum(parameters[:-1] ** 2)
        gradient = np.append(scaled.T @ gradient_z, gradient_z.sum()) / weights.sum()
        gradient[:-1] += 2 * L2_PENALTY * parameters[:-1]
        return value, gradient

    solution = minimize(loss, np.zeros(features.shape[1] + 1), jac=True, method="L-BFGS-B").x
    coefficients = solution[:-1] / spread  # back to raw feature units
    bias = float(solution[-1] - np.sum(solution[:-1] * mean / spread))
    return coefficients, bias


def choose_threshold(confidence: np.ndarray, right: np.ndarray) -> float:
    """The lowest threshold whose precision, on these pairs, reaches TARGET_PRECISION (``fit``
    then raises it above every wrong real-scan pose)."""
    for threshold in np.unique(np.round(confidence, 4)):
        claimed = confidence >= threshold
        if claimed.any() and np.mean(right[claimed]) >= TARGET_PRECISION:
            return float(threshold)
    return 1.0


def flag_quality(claimed: np.ndarray, right: np.ndarray) -> dict[str, float]:
    """Precision (right among claimed), recall (claimed among right), counts."""
    return {
        "pairs": int(len(right)),
        "right": int(right.sum()),
        "claimed": int(claimed.sum()),
        "precision": float(np.mean(right[claimed])) if claimed.any() else float("nan"),
        "recall": float(np.mean(claimed[right])) if right.any() else float("nan"),
    }


def _markdown(payload: dict, pairs_per_group: dict[str, int]) -> str:
    """The report: what the flag was calibrated on, the fitted values, the flag on those pairs."""
    config = payload["verification_config"]
    with_bunny = any(group.startswith("bunny") for group in pairs_per_group)
    lines = [
        "# Success-flag calibration (validation pairs only)",
        "",
        f"Fitted by `{payload['command']}` on the matches `python benchmarks/calibrate_success.py collect` cached",
        "(the same --cache, the model below; `--split` and the groups as given).",
        "",
        f"Model: {payload['model']['description']}. Pairs: the training run's held-out *validation* shapes",
        "(5 % of ModelNet10 train and of the ModelNet40 train subset; never ModelNet10's test split),",
        "\"partial\" protocol (\"resampled_partial\" for val_resampled_partial), both clouds turned by one",
        "random rotation; val_scan: two simulated range scans of a dense validation shape, each in its own pose"
        + ("; and the Stanford Bunny scan pairs that `benchmarks/bunny.py` does **not** benchmark (overlap < 0.3)."
           if with_bunny else "; no real scan (the Bunny is a test set)."),
        "Groups",
        "(`benchmarks/calibrate_success.py` docstring): "
        + ", ".join(f"{g} ({n} pairs)" for g, n in pairs_per_group.items()) + ".",
        "",
        "Right = rotation error < 5 deg and translation error < 5 % of the larger radius.",
        "Logistic regression (L2, every group the same total weight) on every hypothesis; the",
        f"threshold is the lowest with precision >= {payload['target_precision']:.0%} on the chosen hypotheses"
        + (", raised above every wrong real-scan pose." if with_bunny else "."),
        "",
        "| feature | weight |",
        "| --- | ---: |",
        *[f"| {name} | {weight:.4f} |" for name, weight in zip(payload["features"], config["weights"], strict=True)],
        f"| (bias) | {config['bias']:.4f} |",
        "",
        f"Success threshold on the confidence: **{config['success_threshold']:.4f}**.",
        "",
        *(_exit_lines(config)),
        "The flag on the calibration pairs (in-sample: an optimistic estimate). `refined`: the",
        "verified (ICP-refined) pose, what `refine=...` returns; `unrefined`: what `register()`",
        "returns without ICP (`pose_selection.pose_without_icp`: the matches its verified pose explains,",
        "re-fitted, claimed within `same_pose_deg` of its verified pose; where they stray, the verified",
        "pose if the clouds coincide there closely enough, else the re-fit, unclaimed).",
        "",
        "| mode | group | pairs | right | claimed | precision | recall | fast exits | right among them |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += _flag_rows(payload["flag_on_calibration_pairs"])
    if payload.get("flag_held_out"):
        lines += [
            "",
            f"The flag held out ({payload['held_out_folds']}-fold by shape: each pair flagged by a calibration",
            "fitted, weights and threshold, on the pairs of the other folds' shapes alone; an estimate",
            "of what the flag does on shapes it was not fitted on):",
            "",
            "| mode | group | pairs | right | claimed | precision | recall | fast exits | right among them |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
            *_flag_rows(payload["flag_held_out"]),
        ]
    return "\n".join(lines) + "\n"


def _exit_lines(config: dict) -> list[str]:
    """The fast exit's model in the report (none when the calibration found no threshold)."""
    from logdesc_rt.config import EXIT_FEATURES

    if not config.get("exit_weights"):
        return ["No fast exit: no threshold gave exits right at least "
                f"{EXIT_TARGET_PRECISION:.0%} of the time.", ""]
    return [
        f"Fast exit: the `{config['exit_estimator']}` hypothesis alone, refined and scored; a second logistic model",
        "(every group the same total weight) over its own features; the pair exits at the lowest threshold",
        f"whose exits are right >= {EXIT_TARGET_PRECISION:.0%} of the time, verified and as returned without ICP.",
        "",
        "| exit feature | weight |",
        "| --- | ---: |",
        *[f"| {name} | {weight:.4f} |" for name, weight in zip(EXIT_FEATURES, config["exit_weights"], strict=True)],
        f"| (bias) | {config['exit_bias']:.4f} |",
        "",
        f"Exit threshold: **{config['exit_threshold']:.4f}**.",
        "",
    ]


def _flag_rows(summary: dict) -> list[str]:
    """Markdown rows of a :func:`flag_summary`."""
    lines = []
    for mode, groups in summary.items():
        for group, q in groups.items():
            precision = "-" if q["precision"] != q["precision"] else f"{q['precision']:.3f}"
            recall = "-" if q["recall"] != q["recall"] else f"{q['recall']:.3f}"
            lines.append(
                f"| {mode} | {group} | {q['pairs']} | {q['right']} | {q['claimed']} | {precision} | {recall} "
                f"| {q.get('fast_exits', 0)} | {q.get('fast_exits_right', 0)} |"
            )
    return lines


def fit(
    groups: list[str], cache: Path = CACHE, report: Path = REPORT, manifest_dir: Path | None = None,
    candidates: tuple[str, ...] | None = None, descriptor_consensus: tuple[str, ...] | None = None,
    folds: int = 0, split: str = "v3", settings: dict | None = None,
) -> None:
    """Features of every cached hypothesis, the calibration, its report (and manifest).

    ``folds`` > 1 adds a held-out estimate of the flag: the pairs' shapes are dealt into that
    many folds, and each fold's pairs are flagged by a calibration fitted on the other folds
    alone (``split``: the validation shapes the cache was collected from, where its model
    record does not say). ``settings``: other VerificationConfig values over its defaults
    (e.g. ``refit_plane_steps``, ``turn_over_spin``).
    """
    import dataclasses

    from common import command_line

    from logdesc_rt.config import VerificationConfig

    base = VerificationConfig() if candidates is None else VerificationConfig(candidates=tuple(candidates))
    if descriptor_consensus is not None:
        base = dataclasses.replace(base, descriptor_consensus=tuple(descriptor_consensus))
    base = dataclasses.replace(base, **(settings or {}))
    features_cache = cache / "hypotheses.json"
    cached = json.loads(features_cache.read_text()) if features_cache.exists() else {}
    if cached.get("config") != {
        k: v for k, v in base.to_dict().items() if k not in ("weights", "bias", "success_threshold")
    }:
        cached = {"config": {k: v for k, v in base.to_dict().items()
                             if k not in ("weights", "bias", "success_threshold")},
                  "rows": {}}
    started = time.perf_counter()
    for group in groups:
        folder = cache / ("bunny_unbenchmarked" if group == INIT_GROUP else group)
        for path in sorted(folder.glob("*.npz")):
            key = f"{group}/{path.stem}"
            if key not in cached["rows"]:
                cached["rows"][key] = pair_hypotheses(path, base, with_init=group == INIT_GROUP)
    features_cache.write_text(json.dumps(cached))
    print(f"features in {time.perf_counter() - started:.0f} s", flush=True)

    rows = [row for group in groups for key, pair in cached["rows"].items() if key.startswith(group + "/")
            for row in pair]
    fitted = calibrate(rows, base)
    outcomes = flag_outcomes(rows, fitted)
    pairs_per_group: dict[str, int] = {}
    for pair in outcomes:
        pairs_per_group[pair.split("/")[0]] = pairs_per_group.get(pair.split("/")[0], 0) + 1
    summary = flag_summary(outcomes, groups)
    held_out = None
    if folds > 1:
        # The split the pairs were collected from (where the cache records it), else the caller's.
        recorded = json.loads((cache / MODEL_RECORD).read_text()) if (cache / MODEL_RECORD).exists() else {}
        shapes = pair_shapes(sorted(outcomes), recorded.get("split", split))
        held_out = flag_summary(cross_validated_outcomes(rows, base, shapes, folds), groups)
    payload = {
        "what": "success-flag calibration on validation pairs (benchmarks/calibrate_success.py)",
        "command": command_line(),
        "model": (json.loads((cache / MODEL_RECORD).read_text()) if (cache / MODEL_RECORD).exists()
                  else {"id": None, "description": "not recorded (a cache collected before model.json)"}),
        "groups": groups,
        "features": list(FEATURES),
        "verification_config": fitted.to_dict(),
        "target_precision": TARGET_PRECISION,
        "flag_on_calibration_pairs": summary,
        "flag_held_out": held_out,
        "held_out_folds": folds if held_out else None,
    }
    report.with_suffix(".json").write_text(json.dumps(payload, indent=1))
    report.with_suffix(".md").write_text(_markdown(payload, pairs_per_group))
    if manifest_dir is not None:
        write_calibration(manifest_dir, fitted, settings)
    print(json.dumps({"weights": fitted.weights, "bias": fitted.bias, "threshold": fitted.success_threshold,
                      "exit_weights": fitted.exit_weights, "exit_bias": fitted.exit_bias,
                      "exit_threshold": fitted.exit_threshold}, indent=1))
    for label, table in (("in-sample", summary), ("held-out", held_out)):
        for mode in ("refined", "unrefined") if table else ():
            for group, quality in table[mode].items():
                print(f"{label:9s} {mode:10s} {group:22s} " + " ".join(f"{k} {v:.3g}" for k, v in quality.items()))


def calibrate(rows: list[dict], base):
    """The logistic weights and the success threshold fitted on ``rows`` (hypotheses of
    :func:`pair_hypotheses`), and the fast exit's model (:func:`calibrate_exit`): ``base`` (a
    VerificationConfig) with them filled in."""
    import dataclasses

    features = np.array([row["features"] for row in rows])
    labels = np.array([row["verified_right"] for row in rows])
    # Each pair weighs one in total (pairs with many hypotheses do not dominate), and each group
    # the same in total (the 23 real scan pairs count as much as 120 synthetic ones).
    per_pair, pairs_per_group = {}, {}
    for row in rows:
        per_pair[row["pair"]] = per_pair.get(row["pair"], 0) + 1
    for pair in per_pair:
        group = pair.split("/")[0]
        pairs_per_group[group] = pairs_per_group.get(group, 0) + 1
    weights = np.array([1.0 / per_pair[row["pair"]] / pairs_per_group[row["group"]] for row in rows])
    coefficients, bias = fit_logistic(features, labels, weights)
    fitted = dataclasses.replace(base, weights=tuple(coefficients.tolist()), bias=bias)
    outcomes = flag_outcomes(rows, fitted)
    pairs = sorted(outcomes)
    confidence = np.array([outcomes[p]["confidence"] for p in pairs])
    threshold = choose_threshold(confidence, np.array([outcomes[p]["refined_right"] for p in pairs]))
    # Real scans: no wrong pose of an (unbenchmarked) real pair may be claimed.
    real_wrong = [outcomes[p]["confidence"] for p in pairs
                  if p.startswith("bunny") and not outcomes[p]["refined_right"]]
    if real_wrong:
        threshold = max(threshold, float(np.ceil((max(real_wrong) + 1e-4) * 1e4) / 1e4))
    return calibrate_exit(rows, dataclasses.replace(fitted, success_threshold=threshold))


def exit_rows(rows: list[dict], estimator: str) -> list[dict]:
    """Per pair, the hypothesis the fast exit scores: the one ``estimator`` leads (it is
    refined and its features, but for agreement and margin, are those of the fast exit)."""
    return [row for row in rows if row.get("estimators", [None])[0] == estimator and row.get("refined", False)]


def exit_features(row: dict) -> np.ndarray:
    """The EXIT_FEATURES of a hypothesis row."""
    from logdesc_rt.config import EXIT_FEATURES

    return np.array([row["features"][FEATURES.index(name)] for name in EXIT_FEATURES])


def calibrate_exit(rows: list[dict], base):
    """``base`` with the fast exit's model fitted on ``rows``: a logistic over the exit
    estimator's hypothesis' own features, and the lowest threshold whose exits, on these pairs,
    are right at least EXIT_TARGET_PRECISION of the time both verified and as ``register()``
    returns them without ICP (an exit claims the unrefined pose only where
    ``pose_selection.pose_without_icp`` allows),
    and claim no wrong real-scan pose. No exit when no threshold qualifies."""
    import dataclasses

    candidates = exit_rows(rows, base.exit_estimator)
    if not candidates or len({row["verified_right"] for row in candidates}) < 2:
        return dataclasses.replace(base, exit_weights=(), exit_bias=0.0, exit_threshold=1.0)
    per_group: dict[str, int] = {}
    for row in candidates:
        per_group[row["group"]] = per_group.get(row["group"], 0) + 1
    features = np.array([exit_features(row) for row in candidates])
    labels = np.array([row["verified_right"] for row in candidates])
    sample_weights = np.array([1.0 / per_group[row["group"]] for row in candidates])
    coefficients, bias = fit_logistic(features, labels, sample_weights)
    z = bias + features @ coefficients
    confidence = 1.0 / (1.0 + np.exp(-z))
    verified_right = labels
    unrefined_right = np.array([row["unrefined_right"] for row in candidates])
    claimable = np.array([row["unrefined_claimable"] for row in candidates])
    real = np.array([row["group"].startswith("bunny") for row in candidates])
    threshold = 1.0
    for value in np.unique(np.round(confidence, 4)):
        claimed = confidence >= value
        claimed_unrefined = claimed & claimable
        if not claimed.any() or not claimed_unrefined.any():
            continue
        if (np.mean(verified_right[claimed]) >= EXIT_TARGET_PRECISION
                and np.mean(unrefined_right[claimed_unrefined]) >= EXIT_TARGET_PRECISION
                and not np.any(claimed & real & ~verified_right)):
            threshold = float(value)
            break
    if threshold >= 1.0:
        return dataclasses.replace(base, exit_weights=(), exit_bias=0.0, exit_threshold=1.0)
    return dataclasses.replace(
        base, exit_weights=tuple(coefficients.tolist()), exit_bias=float(bias), exit_threshold=threshold
    )


def flag_outcomes(rows: list[dict], fitted) -> dict[str, dict]:
    """Per pair, what the runtime does with the calibration ``fitted``: its chosen hypothesis
    (highest confidence), whether the flag claims it, refined and unrefined, and whether it is right."""
    from logdesc_rt.verification import logistic_confidence

    chosen: dict[str, tuple[float, dict]] = {}
    for row in rows:
        confidence = logistic_confidence(np.array(row["features"]), fitted)
        if row["pair"] not in chosen or confidence > chosen[row["pair"]][0]:
            chosen[row["pair"]] = (confidence, row)
    exits: dict[str, float] = {}
    if fitted.fast_exit:
        for row in exit_rows(rows, fitted.exit_estimator):
            z = fitted.exit_bias + float(np.dot(fitted.exit_weights, exit_features(row)))
            confidence = 1.0 / (1.0 + np.exp(-z))
            if confidence >= fitted.exit_threshold:
                exits[row["pair"]] = confidence
                chosen[row["pair"]] = (confidence, row)
    outcomes = {}
    for pair, (confidence, row) in chosen.items():
        claimed = bool(pair in exits or confidence >= fitted.success_threshold)
        outcomes[pair] = {
            "fast_exit": pair in exits,
            "confidence": float(confidence),
            "refined_claimed": claimed,
            "refined_right": bool(row["verified_right"]),
            # register() without ICP claims only the poses pose_selection.pose_without_icp allows.
            "unrefined_claimed": claimed and bool(row["unrefined_claimable"]),
            "unrefined_right": bool(row["unrefined_right"]),
        }
    return outcomes


def flag_summary(outcomes: dict[str, dict], groups: list[str]) -> dict[str, dict]:
    """:func:`flag_quality` of ``outcomes`` per mode (refined / unrefined) and group ("all" first)."""
    pairs = sorted(outcomes)
    summary: dict[str, dict] = {"refined": {}, "unrefined": {}}
    for group in ["all", *groups]:
        member = [p for p in pairs if group == "all" or p.startswith(group + "/")]
        if not member:
            continue
        for mode in summary:
            claimed = np.array([outcomes[p][f"{mode}_claimed"] for p in member])
            right = np.array([outcomes[p][f"{mode}_right"] for p in member])
            summary[mode][group] = flag_quality(claimed, right)
            exited = np.array([outcomes[p].get("fast_exit", False) for p in member])
            summary[mode][group]["fast_exits"] = int(exited.sum())
            summary[mode][group]["fast_exits_right"] = int((exited & right).sum())
    return summary


def group_counts(rows: dict[str, list[dict]], fitted, classes: dict[str, str] | None = None) -> dict[str, dict]:
    """Per group (and, given ``classes`` {pair: class}, per scan class as ``val_scan:<class>``):
    pairs; whose chosen hypothesis (``fitted``'s calibration) is right verified and without
    ICP; the claims without ICP and the right ones among them; and the pairs with any right
    verified hypothesis (what a perfect choice would reach)."""
    outcomes = flag_outcomes([row for pair in rows.values() for row in pair], fitted)
    counts: dict[str, dict] = {}
    for pair, hypotheses in rows.items():
        if pair not in outcomes:
            continue  # fewer than three matches: no hypothesis
        outcome = outcomes[pair]
        keys = [pair.split("/")[0]] + ([f"val_scan:{classes[pair]}"] if classes and pair in classes else [])
        for key in keys:
            count = counts.setdefault(key, dict.fromkeys(
                ("pairs", "verified_right", "unrefined_right", "claimed", "right_among_claimed", "any_right"), 0))
            count["pairs"] += 1
            count["verified_right"] += outcome["refined_right"]
            count["unrefined_right"] += outcome["unrefined_right"]
            count["claimed"] += outcome["unrefined_claimed"]
            count["right_among_claimed"] += outcome["unrefined_claimed"] and outcome["unrefined_right"]
            count["any_right"] += any(h["verified_right"] for h in hypotheses)
    return counts


def print_counts(cache: Path, report: Path | None, model_dir: Path | None, by_class: bool) -> None:
    """:func:`group_counts` of a fitted cache, printed a line per group."""
    from logdesc_rt.config import VerificationConfig
    from logdesc_rt.network import bundled_model_dir, read_manifest

    if report is not None:
        fitted = VerificationConfig.from_dict(json.loads(report.read_text())["verification_config"])
    else:
        fitted = read_manifest(model_dir or bundled_model_dir()).runtime_config().verification
    rows = json.loads((cache / "hypotheses.json").read_text())["rows"]
    classes = None
    if by_class:
        scans = sorted(pair for pair in rows if pair.startswith("val_scan/"))
        classes = {pair: name.rsplit("_", 1)[0] for pair, name in pair_shapes(scans, "three-way").items()}
    for key, count in sorted(group_counts(rows, fitted, classes).items()):
        print(f"{key:28s} " + " ".join(f"{name} {value}" for name, value in count.items()))


def pair_shapes(pairs: list[str], split: str) -> dict[str, str]:
    """The shape each calibration pair (``"<group>/<index>"``) was cut from, as
    :func:`synthetic_pairs` and :func:`bunny_pairs` choose it: the unit a held-out fold keeps
    whole, so that no shape is both fitted and judged (the scan group reuses its shapes)."""
    from training.data import load_dense_shapes, load_training_sources, split_train_val_test, split_training_shapes

    sources = load_training_sources()
    shapes = split_train_val_test(sources).shapes if split == "three-way" else split_training_shapes(sources)
    dense_names = None
    names = {}
    for pair in pairs:
        group, index = pair.split("/", 1)
        if group in ("bunny_unbenchmarked", INIT_GROUP):
            names[pair] = "bunny/" + index  # a real pair of two scans: its own unit
        elif group == "val_scan":
            if dense_names is None:
                dense_names = load_dense_shapes().subset(shapes.val_names).names
            names[pair] = dense_names[int(index) % len(dense_names)]
        else:
            names[pair] = shapes.val_ids[int(index)].split("/", 1)[1]
    return names


def cross_validated_outcomes(rows: list[dict], base, shapes: dict[str, str], folds: int) -> dict[str, dict]:
    """:func:`flag_outcomes` of every pair under a calibration fitted without its shape: the
    shapes are dealt into ``folds`` folds (seeded), each fold judged by a fit on the others."""
    unique = sorted(set(shapes.values()))
    order = np.random.default_rng([SEED, folds]).permutation(len(unique))
    fold_of = {unique[i]: rank % folds for rank, i in enumerate(order)}
    outcomes: dict[str, dict] = {}
    for fold in range(folds):
        training = [row for row in rows if fold_of[shapes[row["pair"]]] != fold]
        judged = [row for row in rows if fold_of[shapes[row["pair"]]] == fold]
        if judged:
            outcomes.update(flag_outcomes(judged, calibrate(training, base)))
    return outcomes


def write_calibration(model_dir: Path, fitted, settings: dict | None = None) -> None:
    """Store the fitted weights, bias and threshold as the model's verification defaults, with
    the second look's settings and every ``--set`` setting (``settings``' keys, e.g. the
    verification caps) they were fitted with."""
    path = Path(model_dir) / "manifest.json"
    manifest = json.loads(path.read_text())
    runtime = manifest.setdefault("runtime", {})
    runtime["verification"] = {
        **runtime.get("verification", {}),
        "weights": list(fitted.weights),
        "bias": fitted.bias,
        "success_threshold": fitted.success_threshold,
        "candidates": list(fitted.candidates),
        "turn_over_axes": fitted.turn_over_axes,
        "turn_over_spin": fitted.turn_over_spin,
        "second_consensus": list(fitted.second_consensus),
        "descriptor_consensus": list(fitted.descriptor_consensus),
        "refit_spacings": fitted.refit_spacings,
        "refit_plane_steps": fitted.refit_plane_steps,
        "refit_point_weight": fitted.refit_point_weight,
        "verified_fallback_rmse": fitted.verified_fallback_rmse,
        "exit_estimator": fitted.exit_estimator,
        "exit_weights": list(fitted.exit_weights),
        "exit_bias": fitted.exit_bias,
        "exit_threshold": fitted.exit_threshold,
    }
    for key in settings or {}:
        value = getattr(fitted, key)
        runtime["verification"][key] = list(value) if isinstance(value, tuple) else value
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"calibration written to {path}")


if __name__ == "__main__":
    sys.exit(main())
