#!/usr/bin/env bash
# v19 training (training/results/v19/ship_rule.md): v18's run (v15 at a working size of 320 points,
# three cycles) continued for a fourth cosine cycle with scans and partial pairs balanced. Needs
# runs/v19/last.pt: a copy of v18's runs/v18/last.pt at step 3,000 (commit 7540d10 holds v18's
# weights). A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v13 --out runs/v19 --resume auto \
  --workers 1 --threads 1 --geometry-on-device --max-steps 4000 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 --cycle-start 3000 \
  --protocol-mix scan:0.4,partial:0.4,resampled:0.05,resampled_partial:0.15 \
  --working-size 320 --scan-points-per-cloud 320 --split three-way --val-every 500 --val-pairs 96
