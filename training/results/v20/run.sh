#!/usr/bin/env bash
# v20 training (training/results/v20/ship_rule.md): v19's run (v15's network at a working size of
# 320 points, four cycles) continued for a fifth cosine cycle at 288 points per cloud, v19's mix.
# Needs runs/v20/last.pt: a copy of v19's runs/v19/last.pt at step 4,000 (training/checkpoints/v19.pt
# holds its weights, without the Adam moments). A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v13 --out runs/v20 --resume auto \
  --workers 1 --threads 1 --geometry-on-device --max-steps 5000 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 --cycle-start 4000 \
  --protocol-mix scan:0.4,partial:0.4,resampled:0.05,resampled_partial:0.15 \
  --working-size 288 --scan-points-per-cloud 288 --split three-way --val-every 500 --val-pairs 96
