#!/usr/bin/env bash
# Do danger maps predict real trouble? For each place of two routes, the worst-case error (attacks
# generator and sector-iter at λ = 1 m), every corruption's error at severities 1..5 (target
# p2plane, lidar preset) and the cheap predictors (Hessian conditioning, X-ICP-style localisability,
# the analytic sector estimate); Spearman and ROC AUC with bootstrap 95 % intervals for "the place
# fails under realistic corruption" (largest error over corruptions at a severity > 0.5 m), and a
# route figure per route. Writes $OUT/test-route and $OUT/unseen-town (each: summary.json,
# summary.md, places.csv, route.png, manifest.json, run/ with the resumable error rows).
#
# Settings (environment):
#   SAMPLES=96  (places per route: the first scans of the shuffled test passes)
#   ATTACKS=generator,sector-iter  (add an attack and re-run: only its rows are computed)
#   SEVERITIES=1,2,3,4,5  OUT=results/danger-validation  EXECUTOR=local
#   ROUTES="test-route unseen-town"  (either alone to run one)
#   REDO=ensemble  (attacks whose stored rows are computed again, e.g. after their defaults changed)
# Cost on 2 cores (local executor, one process): about 10 min for the test route; the unseen town
# adds generating its scans with the 64-beam sensor (about 2 s per scan) to the same work.
# A quick check: SAMPLES=2 SEVERITIES=5 OUT=/tmp/dv bash scripts/danger_validation.sh
set -euo pipefail
cd "$(dirname "$0")/.."
SAMPLES=${SAMPLES:-96}
ATTACKS=${ATTACKS:-generator,sector-iter}
SEVERITIES=${SEVERITIES:-1,2,3,4,5}
OUT=${OUT:-results/danger-validation}
EXECUTOR=${EXECUTOR:-local}
ROUTES=${ROUTES:-test-route unseen-town}
REDO=${REDO:-}
for route in $ROUTES; do
  case $route in
    test-route) params=() ;;
    unseen-town) params=(--dataset-param town_seed=101 --dataset-param sensor=hdl64) ;;
    *) echo "unknown route $route (test-route, unseen-town)" >&2; exit 2 ;;
  esac
  start=$(date +%s)
  icpbench validate-map --dataset lidar-sim --split test --samples "$SAMPLES" "${params[@]}" \
    --attacks "$ATTACKS" --budget 1 --corruptions all --severities "$SEVERITIES" \
    --fail-m 0.5 --headline-severity 3 --executor "$EXECUTOR" --route "$route" --redo "$REDO" \
    --out "$OUT/$route"
  echo "$route: $(( $(date +%s) - start )) s"
done
