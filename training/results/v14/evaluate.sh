#!/usr/bin/env bash
# Evaluate a v14 checkpoint by its ship rule: export, collect, fit the flag, validation pairs
# through register() without ICP. usage: evaluate.sh CKPT OUTDIR [COUNT] [THREADS]
set -euo pipefail
cd "$(dirname "$0")/../../.."
CKPT=$1; OUT=$2; COUNT=${3:-120}; THREADS=${4:-2}
PY=.venv/bin/python
GROUPS_=(val_in_range val_any_rotation val_small_overlap val_resampled_partial val_scan)
mkdir -p "$OUT"
$PY export/to_onnx.py "$CKPT" --out "$OUT/model" > "$OUT/export.log" 2>&1
echo "exported $(date +%T)"
$PY benchmarks/calibrate_success.py collect --split three-way --model-dir "$OUT/model" --cache "$OUT/calib" \
  --groups "${GROUPS_[@]}" --count "$COUNT" --threads "$THREADS" > "$OUT/collect.log" 2>&1
echo "collected $(date +%T)"
$PY benchmarks/calibrate_success.py fit --split three-way --cache "$OUT/calib" --groups "${GROUPS_[@]}" --folds 5 \
  --manifest "$OUT/model" --report "$OUT/success_calibration_model" > "$OUT/fit_model.log" 2>&1
echo "fitted $(date +%T)"
for P in scan partial resampled_partial; do
  $PY benchmarks/scan_pairs.py --split val --pairs "$COUNT" --protocol $P --methods logdesc_auto \
    --threads "$THREADS" --model-dir "$OUT/model" --out "$OUT/val/model/$P" > "$OUT/val_model_$P.log" 2>&1
  echo "val model $P $(date +%T)"
done
touch "$OUT/EVAL_DONE"
