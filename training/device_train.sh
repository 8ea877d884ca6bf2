#!/usr/bin/env bash
# One prepared training run for a lent GPU machine: continue v3 from its committed checkpoint for
# a fixed number of minutes and bring back the checkpoints and the log. Nothing exploratory.
#
# Here, first (the device tool carries at most 64 MiB, so the shared data travels packed):
#     python training/pack_data.py .device_pack --decimals 4   # about 27 MiB, training shapes only
# (the working tree travels too, and tree + .device_pack must stay under 64 MiB: about 61 MiB
# at this commit; check with `git ls-files -z | xargs -0 du -cb | tail -1; du -sb .device_pack`)
# Then, through the device tool, from the repository root (carry .device_pack):
#     bash training/device_train.sh
# and afterwards, here: copy $OUT/run/last.pt (and best.pt, log.jsonl) next to the committed
# checkpoint, evaluate with `python -m training.evaluate ... --split val [--any-orientation]`.
#
# Environment overrides (defaults in brackets), so the same script is tested on the CPU:
#   RESUME [training/checkpoints/v3.pt]  DEVICE [cuda]  MINUTES [9]  BATCH [48]
#   WORKERS [4]  DATA [.device_pack]  OUT [$OUT, or runs/device]  EXTRA [--amp]
# The schedule is the CPU run's from its step 1103 to 6022 (cosine to step 8000); the CPU run then
# ended its cosine at step 7500. Continuing past that needs a new cycle, chosen through EXTRA
# (later flags win: --max-steps, --decay-steps, --lr); no such cycle has been tried yet. The protocol mix is the CPU run's since its step 3825: 55 % resampled
# pairs (each cloud its own samples, as real scans; 30 % from step 1206: at step 1003 v3 registered
# 4 % of resampled validation pairs, v2 92 %; at step 2208 19.5 %), 35 % partial, and few clean or
# noisy ones (where v3 already beats v2; reasons in training/checkpoints/v3_cpu_notes.json); the
# validation pairs stay those of the mix from step 309, so the log stays comparable.
# The geometry runs on the GPU with the batch (--geometry-on-device: the torch port of the
# NumPy reference, tests/test_geometry_torch.py), so a few workers only draw pairs.
set -euo pipefail
cd "$(dirname "$0")/.."

resume=${RESUME:-training/checkpoints/v3.pt}
out=${OUT:-runs/device}/run
mkdir -p "$out"
python -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
python -m training.train \
    --preset v3 --resume "$resume" --out "$out" \
    --device "${DEVICE:-cuda}" --geometry-on-device --workers "${WORKERS:-4}" \
    --batch-size "${BATCH:-48}" --points-per-cloud 1024 \
    --max-minutes "${MINUTES:-9}" --checkpoint-minutes 2 --val-every 300 --val-pairs 128 \
    --max-steps 8000 --decay-steps 8000 --lr 1e-3 --warmup-steps 100 \
    --protocol-mix clean:0.02,noisy:0.08,partial:0.35,resampled:0.2,resampled_partial:0.35 \
    --val-protocol-mix clean:0.1,noisy:0.3,partial:0.6 \
    --data-root "${DATA:-.device_pack}" --no-progress --log-every 20 ${EXTRA---amp}
ls -la "$out"
