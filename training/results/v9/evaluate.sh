#!/usr/bin/env bash
# Evaluate a v6 checkpoint by the ship rule: export, collect, fit the flag (default verification
# caps and 1000/4000), validation pairs through register() without ICP for both.
# usage: evaluate.sh CKPT OUTDIR [COUNT] [THREADS]
set -euo pipefail
cd /work/main
CKPT=$1; OUT=$2; COUNT=${3:-120}; THREADS=${4:-2}
PY=.venv/bin/python
GROUPS_=(val_in_range val_any_rotation val_small_overlap val_resampled_partial val_scan)
mkdir -p "$OUT"
$PY export/to_onnx.py "$CKPT" --out "$OUT/model" > "$OUT/export.log" 2>&1
echo "exported $(date +%T)"
$PY benchmarks/calibrate_success.py collect --split three-way --model-dir "$OUT/model" --cache "$OUT/calib" \
  --groups "${GROUPS_[@]}" --count "$COUNT" --threads "$THREADS" > "$OUT/collect.log" 2>&1
echo "collected $(date +%T)"
# Verification caps (source_points target_points) by variant; "model" keeps the defaults.
declare -A CAPS=([model]="" [model_caps]="source_points=1000 target_points=4000" [model_caps512]="source_points=512 target_points=2048")
:
for MODEL in model; do
  SET=(); [ -n "${CAPS[$MODEL]}" ] && SET=(--set ${CAPS[$MODEL]})
  $PY benchmarks/calibrate_success.py fit --split three-way --cache "$OUT/calib" --groups "${GROUPS_[@]}" --folds 5 \
    "${SET[@]}" --manifest "$OUT/$MODEL" --report "$OUT/success_calibration_$MODEL" > "$OUT/fit_$MODEL.log" 2>&1 &
done
wait
echo "fitted $(date +%T)"
for MODEL in model; do
  for P in scan partial resampled_partial; do
    $PY benchmarks/scan_pairs.py --split val --pairs "$COUNT" --protocol $P --methods logdesc_auto \
      --threads "$THREADS" --model-dir "$OUT/$MODEL" --out "$OUT/val/$MODEL/$P" > "$OUT/val_${MODEL}_$P.log" 2>&1
    echo "val $MODEL $P $(date +%T)"
  done
done
touch "$OUT/EVAL_DONE"
