#!/usr/bin/env bash
# Table 1 layout on the procedural `objects` data (results/objects-demo), PGD as the reference.
# (the main job before the lidar-sim generator shipped; ~4 min on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/objects-demo
rm -rf "$OUT"
icpbench run --dataset objects --attacks none,uniform,normal,sector,pgd --targets p2plane \
  --budgets 0.02,0.05 --samples 20 --reference pgd --out "$OUT"
for fmt in md latex csv; do
  ext=$fmt; [ "$fmt" = latex ] && ext=tex
  icpbench table "$OUT" --format "$fmt" --reference pgd --out "$OUT/table1.$ext"
done
cat "$OUT/table1.md"
