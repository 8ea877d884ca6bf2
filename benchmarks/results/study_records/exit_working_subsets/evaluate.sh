#!/usr/bin/env bash
set -euo pipefail
cd /work/main
PY=.venv/bin/python; OUT=runs/exitw; COUNT=120; THREADS=2
GROUPS_=(val_in_range val_any_rotation val_small_overlap val_resampled_partial val_scan)
cp runs/v7/eval/calib/model.json /dev/null
$PY benchmarks/calibrate_success.py fit --split three-way --cache runs/v7/eval/calib --groups "${GROUPS_[@]}" --folds 5 \
    --manifest "$OUT/model" --report "$OUT/success_calibration" > "$OUT/fit.log" 2>&1
echo "fitted $(date +%T)"
for P in scan partial resampled_partial; do
  $PY benchmarks/scan_pairs.py --split val --pairs "$COUNT" --protocol $P --methods logdesc_auto \
    --threads "$THREADS" --model-dir "$OUT/model" --out "$OUT/val/$P" > "$OUT/val_$P.log" 2>&1
  echo "val $P $(date +%T)"
done
touch "$OUT/EVAL_DONE"
