#!/usr/bin/env bash
# The PGD oracle against the shipped generator and the normal baseline on lidar-sim at λ = 1 m:
# per-scan projected gradient ascent through the differentiable p2plane ICP.
# Table with PGD as the reference ("% PGD is Larger"), its displacement audit (max ≤ λ) and the
# attack time per scan of each attack (ratio PGD / generator). ~6 min for 48 scans in one process
# (~3 min with EXECUTOR=ray on 2 cores).
# CHECKPOINT=path/to/generator.pt runs another generator than the default lidar-sim one; EXECUTOR=ray
# spreads the units over the cores (default: one process, which keeps the two attacks' times
# comparable).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/lidar-sim-oracle
SAMPLES=${SAMPLES:-48}
CHECKPOINT=${CHECKPOINT:-}
rm -rf "$OUT"
icpbench run --dataset lidar-sim --attacks normal,generator,pgd --targets p2plane --budgets 1 \
  --samples "$SAMPLES" --batch-size 4 --reference pgd --executor "${EXECUTOR:-local}" \
  ${CHECKPOINT:+--attack-param "generator.checkpoint=$CHECKPOINT"} --out "$OUT"
icpbench table "$OUT" --reference pgd --out "$OUT/table_pgd_reference.md"
icpbench table "$OUT" --reference generator --out "$OUT/table_generator_reference.md"
cat "$OUT/table_pgd_reference.md"
