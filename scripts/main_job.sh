#!/usr/bin/env bash
# The main job: regenerate the committed result tables from committed code and config.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=results/synthetic-demo
icpbench run --dataset synthetic --attacks none,uniform,normal,sector --targets p2plane \
  --budgets 0.5,1.0 --samples 16 --reference normal --out "$OUT" --quiet
icpbench table "$OUT" --format md --reference normal --out "$OUT/table1.md"
icpbench table "$OUT" --format latex --reference normal --out "$OUT/table1.tex"
icpbench table "$OUT" --format csv --reference normal --out "$OUT/table1.csv"
