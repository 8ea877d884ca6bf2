#!/usr/bin/env bash
# v18 training (training/results/v18/ship_rule.md): v17's run (v15 at a working size of 320 points,
# two cycles) continued for a third cosine cycle with more partial pairs. Needs runs/v18/last.pt: a
# copy of v17's runs/v17/last.pt at step 2,000 (commit 80d891d holds v17's weights). A stop resumes
# with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v13 --out runs/v18 --resume auto \
  --workers 1 --threads 1 --geometry-on-device --max-steps 3000 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 --cycle-start 2000 \
  --protocol-mix scan:0.3,partial:0.45,resampled:0.05,resampled_partial:0.2 \
  --working-size 320 --scan-points-per-cloud 320 --split three-way --val-every 500 --val-pairs 96
