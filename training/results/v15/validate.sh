#!/usr/bin/env bash
# The v15 rule's validation pairs: seed 1 (pairs no model was judged on before), 240 per protocol,
# through register() without ICP; the second rule's: seed 2, 480 per protocol.
# usage: validate.sh MODEL_DIR|bundled OUTDIR [THREADS] [SEED] [PAIRS]
set -euo pipefail
cd "$(dirname "$0")/../../.."
MODEL=$1; OUT=$2; THREADS=${3:-2}; SEED=${4:-1}; PAIRS=${5:-240}
MODEL_ARGS=(); [ "$MODEL" != bundled ] && MODEL_ARGS=(--model-dir "$MODEL")
mkdir -p "$OUT"
for P in scan partial resampled_partial; do
  .venv/bin/python benchmarks/scan_pairs.py --split val --seed "$SEED" --pairs "$PAIRS" --protocol $P --methods logdesc_auto \
    --threads "$THREADS" "${MODEL_ARGS[@]}" --out "$OUT/$P" > "$OUT/$P.log" 2>&1
  echo "validated $P $(date +%T)"
done
