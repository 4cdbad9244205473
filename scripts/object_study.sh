#!/usr/bin/env bash
# Object case study (paper §IV-C2, figure 4): the shipped objects generators trained with the
# theta-only, x-only and x-y loss weights (scripts/train_objects.sh; bounded output, so every
# displacement is within λ by construction) attack 120 held-out objects at λ = 0.05 beside uniform,
# normal and the sector attack, and regenerate results/object-study/ (table + figure with the
# displacement arrows of each model). Strict by default: every attack stays within the λ-balls.
# SOFT_BOUND=1 adds rows for the unprojected model outputs (the paper's soft bound, labelled
# "(soft-bound)"; identical for bounded models). RETRAIN=1 retrains the three models first.
# ~3 min on 2 shared cores without retraining.
set -euo pipefail
cd "$(dirname "$0")/.."
CK=icpbench/checkpoints/objects
[ "${RETRAIN:-0}" = 1 ] && bash scripts/train_objects.sh
EXTRA=()
[ "${SOFT_BOUND:-0}" = 1 ] && EXTRA+=(--soft-bound)
icpbench object-study --model theta-only=$CK/theta-only.pt --model x-only=$CK/x-only.pt \
  --model xy=$CK/generator.pt --budget 0.05 --objects 120 --figure-objects 4 \
  --out results/object-study "${EXTRA[@]}"
