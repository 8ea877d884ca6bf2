#!/usr/bin/env bash
# The v21 rule's validation pairs: seed 10 (pairs no model was judged on before), 480 per
# protocol, through register() without ICP. usage: validate.sh MODEL_DIR|bundled OUTDIR [THREADS]
set -euo pipefail
cd "$(dirname "$0")/../../.."
MODEL=$1; OUT=$2; THREADS=${3:-2}
MODEL_ARGS=(); [ "$MODEL" != bundled ] && MODEL_ARGS=(--model-dir "$MODEL")
mkdir -p "$OUT"
for P in scan partial resampled_partial; do
  .venv/bin/python benchmarks/scan_pairs.py --split val --seed 10 --pairs 480 --protocol $P --methods logdesc_auto \
    --threads "$THREADS" "${MODEL_ARGS[@]}" --out "$OUT/$P" > "$OUT/$P.log" 2>&1
  echo "validated $P $(date +%T)"
done
