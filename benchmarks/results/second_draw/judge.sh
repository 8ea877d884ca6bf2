#!/usr/bin/env bash
# The second draw's judging run (README.md): 480 fresh seed-9 validation pairs per protocol,
# register() without ICP with and without the second draw on the same matches, 2 threads.
# As run at the judging commit, `logdesc_auto` had the second draw on (its default then) and
# `logdesc_first_draw` ran without it.
cd "$(dirname "$0")/../../.."
for protocol in scan partial resampled_partial; do
  .venv/bin/python benchmarks/scan_pairs.py --split val --seed 9 --pairs 480 --protocol "$protocol" \
    --methods logdesc_auto logdesc_first_draw --threads 2 --out runs/second_draw/seed9 --fresh
done
