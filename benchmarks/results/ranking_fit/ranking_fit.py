"""Held-out comparison of the flag's fit with and without a per-pair ranking term (README.md).

    python benchmarks/results/ranking_fit/ranking_fit.py CACHE

CACHE: a ``benchmarks/calibrate_success.py`` cache of the five validation groups (three-way
split) whose ``fit`` has written ``hypotheses.json`` with the shipped runtime settings.
Run from the project root.
"""
import collections
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, "benchmarks")
import calibrate_success as cs  # noqa: E402

from logdesc_rt.config import VerificationConfig  # noqa: E402

RANKING_WEIGHT = 1.0  # fixed before any fit (README.md)


def fit_with_ranking(rows: list[dict], base):
    """calibrate(rows, base) with the conditional-logit term added to the logistic loss."""
    features = np.array([row["features"] for row in rows])
    labels = np.array([row["verified_right"] for row in rows], dtype=np.float64)
    per_pair, per_group = collections.Counter(r["pair"] for r in rows), collections.Counter()
    for pair in per_pair:
        per_group[pair.split("/")[0]] += 1
    weights = np.array([1.0 / per_pair[r["pair"]] / per_group[r["group"]] for r in rows])
    pair_weight = {p: 1.0 / per_group[p.split("/")[0]] for p in per_pair}
    pairs = sorted(per_pair)
    pair_index = np.array([pairs.index(r["pair"]) for r in rows])
    has_right = np.zeros(len(pairs), dtype=bool)
    np.logical_or.at(has_right, pair_index, labels > 0)
    pw = np.array([pair_weight[p] for p in pairs])

    mean, spread = features.mean(axis=0), features.std(axis=0) + 1e-9
    scaled = (features - mean) / spread

    def loss(parameters):
        z = scaled @ parameters[:-1] + parameters[-1]
        probability = 1.0 / (1.0 + np.exp(-z))
        pointwise = (weights * (np.logaddexp(0.0, z) - labels * z)).sum() / weights.sum()
        gradient_z = weights * (probability - labels) / weights.sum()
        # Conditional logit: -log(sum_right exp z / sum_all exp z) per pair with a right one.
        top = np.full(len(pairs), -np.inf)
        np.maximum.at(top, pair_index, z)
        e = np.exp(z - top[pair_index])
        all_sum, right_sum = np.zeros(len(pairs)), np.zeros(len(pairs))
        np.add.at(all_sum, pair_index, e)
        np.add.at(right_sum, pair_index, e * labels)
        used = has_right
        ranking = np.sum(pw[used] * (np.log(all_sum[used]) - np.log(right_sum[used]))) / pw[used].sum()
        share_all = e / all_sum[pair_index]
        share_right = np.where(labels > 0, e / np.where(right_sum[pair_index] > 0, right_sum[pair_index], 1.0), 0.0)
        gradient_rank = np.where(used[pair_index], pw[pair_index] * (share_all - share_right), 0.0) / pw[used].sum()
        gz = gradient_z + RANKING_WEIGHT * gradient_rank
        value = pointwise + RANKING_WEIGHT * ranking + cs.L2_PENALTY * np.sum(parameters[:-1] ** 2)
        gradient = np.append(scaled.T @ gz, gz.sum())
        gradient[:-1] += 2 * cs.L2_PENALTY * parameters[:-1]
        return value, gradient

    solution = minimize(loss, np.zeros(features.shape[1] + 1), jac=True, method="L-BFGS-B").x
    coefficients = solution[:-1] / spread
    bias = float(solution[-1] - np.sum(solution[:-1] * mean / spread))
    fitted = dataclasses.replace(base, weights=tuple(coefficients.tolist()), bias=bias)
    outcomes = cs.flag_outcomes(rows, fitted)
    keys = sorted(outcomes)
    threshold = cs.choose_threshold(
        np.array([outcomes[p]["confidence"] for p in keys]), np.array([outcomes[p]["refined_right"] for p in keys])
    )
    return dataclasses.replace(fitted, success_threshold=threshold)


def held_out(rows, base, shapes, folds, fitter):
    unique = sorted(set(shapes.values()))
    order = np.random.default_rng([cs.SEED, folds]).permutation(len(unique))
    fold_of = {unique[i]: rank % folds for rank, i in enumerate(order)}
    outcomes = {}
    for fold in range(folds):
        training = [r for r in rows if fold_of[shapes[r["pair"]]] != fold]
        judged = [r for r in rows if fold_of[shapes[r["pair"]]] == fold]
        outcomes.update(cs.flag_outcomes(judged, fitter(training, base)))
    return outcomes


def main() -> None:
    cache = Path(sys.argv[1])
    cached = json.loads((cache / "hypotheses.json").read_text())
    base = VerificationConfig.from_dict(cached["config"])
    rows = [r for v in cached["rows"].values() for r in v]
    shapes = cs.pair_shapes(sorted({r["pair"] for r in rows}), "three-way")
    groups = sorted({r["group"] for r in rows})
    for name, fitter in (("today's fit", cs.calibrate), ("with the ranking term", fit_with_ranking)):
        outcomes = held_out(rows, base, shapes, 5, fitter)
        print(name)
        for group in ["all", *groups]:
            member = [p for p in outcomes if group == "all" or p.startswith(group + "/")]
            verified = sum(outcomes[p]["refined_right"] for p in member)
            unrefined = sum(outcomes[p]["unrefined_right"] for p in member)
            quality = {mode: cs.flag_quality(np.array([outcomes[p][f"{mode}_claimed"] for p in member]),
                                             np.array([outcomes[p][f"{mode}_right"] for p in member]))
                       for mode in ("refined", "unrefined")}
            print(f"  {group:24s} pairs {len(member):4d} verified right {verified:4d} without ICP right {unrefined:4d} "
                  f"precision {quality['refined']['precision']:.3f} / {quality['unrefined']['precision']:.3f} "
                  f"recall {quality['refined']['recall']:.3f} / {quality['unrefined']['recall']:.3f}")


if __name__ == "__main__":
    main()
