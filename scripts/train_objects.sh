#!/usr/bin/env bash
# How the shipped objects generators icpbench/checkpoints/objects/{generator,x-only,theta-only}.pt
# were trained, one process at a time, torch 1 thread, on 2 shared CPU cores.
# All three use the bounded output (X + λ·u, |u| < 1): every displacement is within λ by
# construction, so strict evaluation changes nothing. Preset quick-objects (λ = 0.05, batch 8,
# AdamW lr 1e-3, surrogate p2plane objects-train), no pretraining (it would only pull the output
# towards zero), 160 training objects per epoch, 32 held-out objects in each card:
#   x-y (generator.pt) and x-only: with the sensitivity prior (prior=sector, association gate
#     prior_dmax = 0.3, the objects ICP preset's d_max): the untrained model is the sector attack
#     scaled by tanh(2), training learns corrections; x-y 3 epochs (463 s), x-only 2 epochs;
#   x-y: the 3-epoch x-y model above fine-tuned 2 more epochs with the same
#     adversarial loss on 256 training objects, lr 5e-4 (695 s; 1158 s in all, the card's
#     train_wall_s_total; its init_card is the 3-epoch model's card). Validation (100 objects of
#     the test split of dataset seed 1, not the demo's seed-0 objects; strict, λ = 0.05): mean
#     x-y error 0.0609 -> 0.0662, % larger vs normal 65.3 -> 92.0, vs uniform 97.4 -> 100.
#   x-only and theta-only: the models below fine-tuned the same way (2 epochs, 256
#     objects, lr 5e-4; 292 s and 306 s). Validation (same 100 seed-1 objects; means over
#     converged runs): heading error theta-only 0.0507 -> 0.0550 rad against x-only 0.0389 ->
#     0.0378 rad; x error x-only 0.0544 -> 0.0549 against theta-only 0.0333 -> 0.0320: the
#     paper's finding holds with wider margins, so both were replaced.
#   theta-only: fine-tuned from the 3-epoch x-y model (--init; same prior settings) with the
#     theta-only weights, 2 epochs (228 s). Trained from scratch without the prior (2 epochs, 244 s) it learned
#     next to nothing (max displacement 0.003, heading error 0.17 deg on 16 test objects, the
#     clean level, below the x-only model's 2.3 deg): the bounded output starts at zero and the
#     heading gradient there is too weak for such a short run.
# Measured before choosing (x-y weights, 32 held-out objects, mean x-y error at λ = 0.05, uniform
# 0.0499): untrained prior model 0.0500; bounded model without prior after 1 epoch 0.0500
# (training error 0.026) against the prior model's 0.054 training error after 1 epoch and 0.0598
# held-out after 3 epochs. The paper's soft-bound variant (output=residual, no projection in
# training) remains available with `--generator-param output=residual`; it is not shipped.
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${RUNS:-runs}
DEST=icpbench/checkpoints/objects
COMMON=(--preset quick-objects --pretrain-epochs 0 --train-samples 160 --eval-samples 32
        --generator-param output=bounded)
PRIOR=(--generator-param prior=sector --generator-param prior_dmax=0.3)
icpbench train "${COMMON[@]}" "${PRIOR[@]}" --weights xy --epochs 3 --out "$RUNS/objects-xy"
icpbench train "${COMMON[@]}" "${PRIOR[@]}" --weights x-only --epochs 2 --out "$RUNS/objects-x-only"
icpbench train "${COMMON[@]}" --weights theta-only --init "$RUNS/objects-xy/generator.pt" --epochs 2 \
  --out "$RUNS/objects-theta-only"
FT=(--preset quick-objects --pretrain-epochs 0 --train-samples 256 --eval-samples 8
    --generator-param output=bounded --epochs 2 --lr 5e-4 --alpha 1)
icpbench train "${FT[@]}" "${PRIOR[@]}" --weights xy --init "$RUNS/objects-xy/generator.pt" \
  --out "$RUNS/objects-xy-ft"
icpbench train "${FT[@]}" "${PRIOR[@]}" --weights x-only --init "$RUNS/objects-x-only/generator.pt" \
  --out "$RUNS/objects-x-only-ft"
icpbench train "${FT[@]}" --weights theta-only --init "$RUNS/objects-theta-only/generator.pt" \
  --out "$RUNS/objects-theta-only-ft"
mkdir -p "$DEST"
cp "$RUNS/objects-xy-ft/generator.pt" "$DEST/generator.pt"
cp "$RUNS/objects-xy-ft/generator.json" "$DEST/generator.json"
for w in x-only theta-only; do
  cp "$RUNS/objects-$w-ft/generator.pt" "$DEST/$w.pt"
  cp "$RUNS/objects-$w-ft/generator.json" "$DEST/$w.json"
done
