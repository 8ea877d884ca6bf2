#!/usr/bin/env bash
# v14 training (training/results/v14/ship_rule.md): v13's run (20 edge neighbours) continued for a
# second cosine cycle with more partial pairs in its mix. Needs runs/v14/last.pt: a copy of v13's
# runs/v13/last.pt at step 1,200 (commit 575c63e holds v13's weights). A stop resumes with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v4 --out runs/v14 --resume auto \
  --workers 1 --threads 2 --geometry-on-device --max-steps 2200 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 --cycle-start 1200 \
  --protocol-mix scan:0.4,partial:0.3,resampled:0.05,resampled_partial:0.25 \
  --working-size 384 --scan-points-per-cloud 384 --split three-way --val-every 500 --val-pairs 96
