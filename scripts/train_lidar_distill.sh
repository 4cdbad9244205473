#!/usr/bin/env bash
# Issue 14, route "learn from the oracle" (session 6): a lidar-sim generator trained by imitation of
# cached PGD answers. NOT the shipped model: on 48 validation-pass scans it was not better than the
# shipped generator (docs/status.md, "Session 6: the learned attack"); kept so the route can be rerun
# and extended (more scans, mixed adversarial + imitation loss, more varied towns).
#
# What it does (docs/methods.md, "Learning from the oracle"):
#   1. caches, for each of the 144 training scans (passes 3-6) at one budget chosen from its id
#      (λ in 1..5 m), the answer of PGD warm-started from the sector attack (10 steps of 0.1 λ,
#      25-iteration surrogate): runs/oracle-cache, resumable; 32 min on one core of the shared
#      2-core VM in session 6 (about 13 s per scan, four other jobs running);
#   2. trains the sensitivity-prior generator (prior=sector, bounded, λ-conditioned; the shipped
#      model's architecture and initialisation) on the imitation loss alone (--alpha 0: no ICP in
#      the training step), lr 5e-4, batch 2, one core. Session 6 ran --epochs 5 and stopped it
#      after epoch 2: the imitation loss was 0.1264 after epoch 1 and 0.1265 after epoch 2
#      (877 s per epoch on the loaded machine), so the epoch-1 checkpoint was evaluated.
# Evaluate like any checkpoint, e.g. on the validation pass:
#   icpbench run --dataset lidar-sim --dataset-param n_passes=7 --dataset-param 'test_passes=[7]' \
#     --attacks generator --attack-param generator.checkpoint=$RUNS/lidar-gen-distill/generator.pt \
#     --targets p2plane --budgets 1,4 --samples 48 --out $RUNS/val-distill
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${RUNS:-runs}
EPOCHS=${EPOCHS:-1}
icpbench train --preset quick-lidar --generator-param prior=sector --generator-param output=bounded \
  --train-samples 144 --epochs "$EPOCHS" --lr 5e-4 --alpha 0 --imitation 1 \
  --oracle-param steps=10 --oracle-param init=sector --oracle-cache "$RUNS/oracle-cache" \
  --eval-samples 8 --out "$RUNS/lidar-gen-distill"
