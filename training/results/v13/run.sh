#!/usr/bin/env bash
# v13 training (training/results/v13/ship_rule.md): v7's network with 20 edge neighbours,
# warm-started from v7, v7's recipe. A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v13 --out runs/v13 --resume auto \
  --init-from training/checkpoints/v7.pt \
  --workers 1 --threads 1 --geometry-on-device --max-steps 1200 --checkpoint-minutes 10 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1200 \
  --protocol-mix scan:0.55,partial:0.2,resampled:0.05,resampled_partial:0.2 \
  --working-size 384 --scan-points-per-cloud 384 --split three-way --val-every 400 --val-pairs 96
