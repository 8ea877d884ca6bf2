"""Counts of the rule in README.md: per validation group, the pairs right without ICP (and the
flag's claims) as register() returns them now, and as it would with the fallback to the verified
pose where the re-fitted pose strays from it. Reads a calibrate_success.py hypotheses cache.

    python benchmarks/results/verified_fallback/count_fallback.py runs/calib_plane
"""
import collections
import json
import sys

import numpy as np

from logdesc_rt.network import bundled_model_dir, read_manifest
from logdesc_rt.verification import logistic_confidence

config = read_manifest(bundled_model_dir()).runtime_config().verification
rows = json.load(open(sys.argv[1] + "/hypotheses.json"))["rows"]
for fallback in (False, True):
    counts = collections.defaultdict(lambda: [0, 0, 0, 0])
    for pair, hypotheses in rows.items():
        if not hypotheses:
            continue
        scored = [(logistic_confidence(np.array(h["features"]), config), h) for h in hypotheses]
        confidence, chosen = max(scored, key=lambda item: item[0])  # the first among ties
        claimed = confidence >= config.success_threshold
        astray = not chosen["within_verified"]
        right = chosen["verified_right"] if (fallback and astray) else chosen["unrefined_right"]
        claimed_unrefined = claimed and (not astray or fallback)
        count = counts[pair.split("/")[0]]
        count[0] += 1
        count[1] += right
        count[2] += claimed_unrefined
        count[3] += claimed_unrefined and right
    print("with the fallback" if fallback else "as shipped")
    for group in sorted(counts):
        n, right, claimed, right_claimed = counts[group]
        print(f"  {group:24s} pairs {n:4d} right without ICP {right:4d} claimed {claimed:4d} right among claimed {right_claimed:4d}")
