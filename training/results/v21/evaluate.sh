#!/usr/bin/env bash
# Evaluate a v21 checkpoint by its ship rule (ship_rule.md): export; collect the calibration pairs
# and fit the flag and exit model (120 pairs per validation group, as for v15-v19); then the fresh
# validation pairs (seed 10, 480 per protocol) through register() without ICP.
# usage: evaluate.sh CKPT OUTDIR [THREADS]
set -euo pipefail
cd "$(dirname "$0")/../../.."
CKPT=$1; OUT=$2; THREADS=${3:-2}
PY=.venv/bin/python
GROUPS_=(val_in_range val_any_rotation val_small_overlap val_resampled_partial val_scan)
mkdir -p "$OUT"
$PY export/to_onnx.py "$CKPT" --out "$OUT/model" > "$OUT/export.log" 2>&1
echo "exported $(date +%T)"
$PY benchmarks/calibrate_success.py collect --split three-way --model-dir "$OUT/model" --cache "$OUT/calib" \
  --groups "${GROUPS_[@]}" --count 120 --threads "$THREADS" > "$OUT/collect.log" 2>&1
echo "collected $(date +%T)"
$PY benchmarks/calibrate_success.py fit --split three-way --cache "$OUT/calib" --groups "${GROUPS_[@]}" --folds 5 \
  --manifest "$OUT/model" --report "$OUT/success_calibration_model" > "$OUT/fit_model.log" 2>&1
echo "fitted $(date +%T)"
training/results/v21/validate.sh "$OUT/model" "$OUT/val" "$THREADS"
touch "$OUT/EVAL_DONE"
