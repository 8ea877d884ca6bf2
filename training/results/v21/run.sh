#!/usr/bin/env bash
# v21 training (training/results/v21/ship_rule.md): v19's run continued for a fifth cosine cycle
# with the soft correspondence distance beside the task loss. Needs runs/v21/last.pt: a copy of
# v19's runs/v19/last.pt at step 4,000 (commit 1df598d holds v19's weights). A stop resumes
# with the same command.
cd "$(dirname "$0")/../../.."
exec .venv/bin/python -m training.train --preset v13 --out runs/v21 --resume auto \
  --workers 1 --threads 2 --geometry-on-device --max-steps 5000 --checkpoint-minutes 5 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1000 --cycle-start 4000 \
  --protocol-mix scan:0.4,partial:0.4,resampled:0.05,resampled_partial:0.15 \
  --working-size 320 --scan-points-per-cloud 320 --split three-way --val-every 500 --val-pairs 96 \
  --soft-correspondence-weight 5
