#!/usr/bin/env bash
# v15 training (training/results/v15/ship_rule.md): v14's run (v7's network with 20 edge neighbours)
# continued for a third cosine cycle. Needs runs/v15/last.pt: a copy of v14's runs/v14/last.pt at
# step 2,200 (commit 274678d holds v14's weights). A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v4 --out runs/v15 --resume auto \
  --workers 1 --threads 1 --geometry-on-device --max-steps 3200 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 --cycle-start 2200 \
  --protocol-mix scan:0.35,partial:0.35,resampled:0.05,resampled_partial:0.25 \
  --working-size 384 --scan-points-per-cloud 384 --split three-way --val-every 500 --val-pairs 96
