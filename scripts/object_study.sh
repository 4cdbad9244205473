#!/usr/bin/env bash
# Object case study (paper §IV-C2, figure 4): train three generators on `objects` with the
# theta-only, x-only and x-y loss weights (quick CPU settings, ~9 min each on 2 cores), ship them as
# package checkpoints, and regenerate results/object-study/.
# Set RETRAIN=1 to retrain; otherwise the shipped checkpoints are used.
set -euo pipefail
cd "$(dirname "$0")/.."
CK=icpbench/checkpoints/objects
if [ "${RETRAIN:-0}" = 1 ]; then
  for w in theta-only x-only xy; do
    icpbench train --preset quick-objects --weights $w --train-samples 128 --eval-samples 16 \
      --pretrain-epochs 0 --epochs 6 --batch-size 8 --max-minutes 12 --out runs/objects-$w
  done
  cp runs/objects-xy/generator.pt $CK/generator.pt; cp runs/objects-xy/generator.json $CK/generator.json
  for w in theta-only x-only; do
    cp runs/objects-$w/generator.pt $CK/$w.pt; cp runs/objects-$w/generator.json $CK/$w.json
  done
fi
icpbench object-study --model theta-only=$CK/theta-only.pt --model x-only=$CK/x-only.pt \
  --model xy=$CK/generator.pt --budget 0.05 --objects 24 --figure-objects 4 --out results/object-study
