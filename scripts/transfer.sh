#!/usr/bin/env bash
# Transfer table on lidar-sim at λ = 1 m: attacks crafted on the differentiable p2plane
# surrogate, evaluated on every target. ~5 min for 20 samples with EXECUTOR=ray on 2 cores (PGD dominates).
# CHECKPOINT=path/to/generator.pt runs another generator than the default lidar-sim one;
# EXECUTOR=ray spreads the units over the cores (default: one process).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/lidar-sim-transfer
rm -rf "$OUT"
icpbench run --dataset lidar-sim --attacks none,uniform,normal,sector,generator,pgd \
  --targets p2plane,p2point,open3d,kiss-icp,small-gicp --budgets 1 --samples 20 --batch-size 4 \
  --reference pgd --executor "${EXECUTOR:-local}" \
  ${CHECKPOINT:+--attack-param "generator.checkpoint=$CHECKPOINT"} --out "$OUT"
icpbench table "$OUT" --transfer 1 --out "$OUT/transfer.md"
icpbench table "$OUT" --reference pgd --target p2plane --out "$OUT/table1_p2plane.md"
