#!/usr/bin/env bash
# Model selection for the lidar-sim generator on a validation pass (issue 5).
#
# lidar-sim trains on repeat passes 3-6 and Table 1 is measured on passes 1-2. A seventh repeat pass
# of the same route (new lateral offsets, parked cars, trucks and initial offsets; generated on
# first use, about a minute for 48 scans) is disjoint from both, so candidates can be compared there
# without looking at the Table 1 sample:
#
#   bash scripts/validate_lidar.sh OUT [CHECKPOINT]     # CHECKPOINT defaults to the shipped model
#
# writes OUT/results.csv, OUT/manifest.json and prints the Table-1-style comparison (uniform, normal,
# generator; λ = 1..5 m; 48 scans; ~15 min on one core).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: validate_lidar.sh OUT [CHECKPOINT]}
ARGS=()
if [[ $# -ge 2 ]]; then
  ARGS=(--attack-param "generator.checkpoint=$2")
fi
OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} icpbench run --dataset lidar-sim --dataset-param n_passes=7 \
  --dataset-param "test_passes=[7]" --attacks uniform,normal,generator --targets p2plane \
  --budgets 1,2,3,4,5 --samples 48 --batch-size 4 --out "$OUT" "${ARGS[@]}"
