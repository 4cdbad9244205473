#!/usr/bin/env bash
# The main job: regenerate the committed result tables from committed code and config.
# Until the learned generator ships, Table 1 is produced on the procedural `objects` data with the
# PGD oracle as the reference attack ("% Ours is Larger" = % PGD is larger).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/objects-demo
rm -rf "$OUT"
icpbench run --dataset objects --attacks none,uniform,normal,sector,pgd --targets p2plane \
  --budgets 0.02,0.05 --samples 20 --reference pgd --out "$OUT" --quiet
for fmt in md latex csv; do
  ext=$fmt; [ "$fmt" = latex ] && ext=tex
  icpbench table "$OUT" --format "$fmt" --reference pgd --out "$OUT/table1.$ext"
done
cat "$OUT/table1.md"
