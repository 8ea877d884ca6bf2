#!/usr/bin/env bash
# v16 training (training/results/v16/ship_rule.md): v15 (the bundled model) at a working size of
# 320 points per cloud, warm-started from v15, one cosine cycle with v15's last mix.
# A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v13 --out runs/v16 --resume auto \
  --init-from training/checkpoints/v15.pt \
  --workers 1 --threads 1 --geometry-on-device --max-steps 1000 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 \
  --protocol-mix scan:0.35,partial:0.35,resampled:0.05,resampled_partial:0.25 \
  --working-size 320 --scan-points-per-cloud 320 --split three-way --val-every 500 --val-pairs 96
