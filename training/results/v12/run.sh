#!/usr/bin/env bash
# v12 training (training/results/v12/ship_rule.md): v7's network with two transformer pairs,
# warm-started from v7 and distilled from it, v7's recipe. A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v12 --out runs/v12 --resume auto \
  --init-from training/checkpoints/v7.pt --distill-from training/checkpoints/v7.pt --distill-weight 1.0 \
  --workers 1 --threads 1 --geometry-on-device --max-steps 1200 --checkpoint-minutes 10 \
  --log-every 10 --no-progress --lr 0.0002 --warmup-steps 50 --decay-steps 1200 \
  --protocol-mix scan:0.55,partial:0.2,resampled:0.05,resampled_partial:0.2 \
  --working-size 384 --scan-points-per-cloud 384 --split three-way --val-every 400 --val-pairs 96
