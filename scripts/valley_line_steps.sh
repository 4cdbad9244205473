#!/usr/bin/env bash
# valley's plan on 4 line steps against the standard 8, the member run alone on the first 16
# scans of the town board, for three variants (scripts/member_ab.py; 2 workers, about 20 min on
# 2 cores). Writes results/valley-line-steps/<variant>.csv and .json, and summary.md.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS=1
OUT=results/valley-line-steps
mkdir -p "$OUT"
{
  echo "# valley: 4 line steps against 8 (the member alone, first 16 town-board scans)"
  echo
  echo 'Made by `bash scripts/valley_line_steps.sh`; arm A is the standard valley (8 steps), arm B'
  echo '`line_steps=4`; seconds per scan from this run (2 workers); worst_estimate: per scan the'
  echo 'larger of the board'"'"'s other members and the arm'"'"'s valley (the search is not rerun).'
} > "$OUT/summary.md"
for v in "small-gicp plane ICP" "p2plane (Cauchy)" "p2point"; do
  slug=$(echo "$v" | sed -E 's/[^A-Za-z0-9._-]+/-/g; s/^[-.]+//; s/[-.]+$//')
  { echo; echo '```'; python scripts/member_ab.py --board results/leaderboard-v1 --variant "$v" \
      --member valley --set line_steps=4 --samples 16 --workers 2 --out "$OUT/$slug.csv"
    echo '```'; } | tee -a "$OUT/summary.md"
done
