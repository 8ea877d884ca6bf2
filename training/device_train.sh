#!/usr/bin/env bash
# One prepared training run for a lent GPU machine: continue v3 from its committed checkpoint for
# a fixed number of minutes and bring back the checkpoints and the log. Nothing exploratory.
#
# Here, first (the device tool carries at most 64 MiB, so the shared data travels packed):
#     python training/pack_data.py .device_pack --decimals 4   # about 27 MiB, training shapes only
# (the working tree travels too, and tree + .device_pack must stay under 64 MiB: about
# 56 MB in session 10, 29 MB of it the tree; check with `git ls-files -z | xargs -0 du -cb | tail -1; du -sb .device_pack`)
# Then, through the device tool, from the repository root (carry .device_pack):
#     bash training/device_train.sh
# and afterwards, here: copy $OUT/run/last.pt (and best.pt, log.jsonl) next to the committed
# checkpoint, evaluate with `python -m training.evaluate ... --split val [--any-orientation]`.
#
# Environment overrides (defaults in brackets), so the same script is tested on the CPU:
#   RESUME [training/checkpoints/v3_cycle2.pt if committed, else v3.pt]  DEVICE [cuda]  MINUTES [9]
#   BATCH [48]  WORKERS [4]  DATA [.device_pack]  OUT [$OUT, or runs/device]  EXTRA [--amp]
# The schedule and protocol mix are those of v3's second CPU cycle (training/checkpoints/
# v3_cycle2_notes.json says why): a warm restart at step 7500 (--cycle-start), 50 warm-up steps,
# cosine over 2500 steps from lr 5e-4; 65 % resampled pairs (each cloud its own samples, as real
# scans: v3's weakest case), 28 % partial, few clean or noisy ones (where v3 already beats v2).
# The steps count batches, and a GPU batch holds 6x the CPU's 8 pairs: change the cycle through
# EXTRA (later flags win: --cycle-start, --max-steps, --decay-steps, --lr) for a cycle of its own.
# Dry-run on the CPU (session 10): PATH=.venv/bin:$PATH DATA=../shared/data DEVICE=cpu MINUTES=1
# BATCH=2 WORKERS=0 OUT=runs/device_dry EXTRA= bash training/device_train.sh resumed v3.pt, ran
# 72 steps with the lr warming up from 1 % to 5e-4 over steps 7500-7550, and wrote last.pt.
# The validation pairs stay those of the mix from step 309, so the log stays comparable.
# The geometry runs on the GPU with the batch (--geometry-on-device: the torch port of the
# NumPy reference, tests/test_geometry_torch.py), so a few workers only draw pairs.
set -euo pipefail
cd "$(dirname "$0")/.."

default_resume=training/checkpoints/v3_cycle2.pt
[ -f "$default_resume" ] || default_resume=training/checkpoints/v3.pt
resume=${RESUME:-$default_resume}
out=${OUT:-runs/device}/run
mkdir -p "$out"
python -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
python -m training.train \
    --preset v3 --resume "$resume" --out "$out" \
    --device "${DEVICE:-cuda}" --geometry-on-device --workers "${WORKERS:-4}" \
    --batch-size "${BATCH:-48}" --points-per-cloud 1024 \
    --max-minutes "${MINUTES:-9}" --checkpoint-minutes 2 --val-every 300 --val-pairs 128 \
    --cycle-start 7500 --max-steps 10000 --decay-steps 2500 --lr 5e-4 --warmup-steps 50 \
    --protocol-mix clean:0.02,noisy:0.05,partial:0.28,resampled:0.25,resampled_partial:0.4 \
    --val-protocol-mix clean:0.1,noisy:0.3,partial:0.6 \
    --data-root "${DATA:-.device_pack}" --no-progress --log-every 20 ${EXTRA---amp}
ls -la "$out"
