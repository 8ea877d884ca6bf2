#!/usr/bin/env bash
# The verified-pose fallback's judging run (README.md): 480 fresh seed-11 validation pairs per
# protocol, register() without ICP with the fallback (logdesc_auto, verified_fallback_rmse = 0.5)
# and without it (logdesc_refit_only) on the same matches, 2 threads.
cd "$(dirname "$0")/../../.."
for protocol in scan partial resampled_partial; do
  .venv/bin/python benchmarks/scan_pairs.py --split val --seed 11 --pairs 480 --protocol "$protocol" \
    --methods logdesc_auto logdesc_refit_only --threads 2 --out runs/verified_fallback/seed11 --fresh
done
