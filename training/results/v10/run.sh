#!/usr/bin/env bash
# v10 training (training/results/v10/ship_rule.md): v7's run continued for a second cosine cycle.
cd /work/main
exec .venv/bin/python -m training.train --preset v4 --out runs/v10 --resume auto \
  --workers 1 --threads 1 --geometry-on-device --max-steps 2800 --checkpoint-minutes 10 \
  --log-every 10 --no-progress --lr 0.0001 --warmup-steps 50 --decay-steps 1600 --cycle-start 1200 \
  --protocol-mix scan:0.55,partial:0.2,resampled:0.05,resampled_partial:0.2 \
  --working-size 384 --scan-points-per-cloud 384 --split three-way --val-every 400 --val-pairs 96
