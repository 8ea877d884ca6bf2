#!/usr/bin/env bash
# v17 training (training/results/v17/ship_rule.md): v16's run (v15 at a working size of 320 points)
# continued for a second cosine cycle. Needs runs/v17/last.pt: a copy of v16's runs/v16/last.pt at
# step 1,000 (commit 7eefdc1 holds v16's weights). A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v13 --out runs/v17 --resume auto \
  --workers 1 --threads 1 --geometry-on-device --max-steps 2000 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 --cycle-start 1000 \
  --protocol-mix scan:0.4,partial:0.35,resampled:0.05,resampled_partial:0.2 \
  --working-size 320 --scan-points-per-cloud 320 --split three-way --val-every 500 --val-pairs 96
