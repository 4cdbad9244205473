#!/usr/bin/env bash
# Table 1 on an unseen lidar-sim town with the 64-beam sensor: attacks none, uniform, normal, sector
# and a generator ("Ours"), target p2plane, λ = 1..5 m, on the test passes of town_seed 101 (no
# generator has been trained on it) seen by the hdl64 preset (Velodyne HDL-64E beam layout).
# Writes $OUT/table1.{md,tex,csv} and $OUT/run/{results.csv,manifest.json}; re-running resumes.
#
# Settings (environment):
#   TOWN=101  SENSOR=hdl64  SAMPLES=48 (the first test-pass scans of a shuffled order; a larger
#   count on the same OUT resumes and adds only the new scans)  BUDGETS=1,2,3,4,5
#   CHECKPOINT=  (a generator .pt; empty: the shipped lidar-sim generator)
#   OUT=results/lidar-sim-unseen  EXECUTOR=ray (one worker per core; local: one process)
# Cost: generating the town and the scans' submaps takes about 2 s of CPU per scan with hdl64, the
# attacks then cost what the main job costs (scripts/main_job.sh: about 8 minutes on 2 cores for 48
# scans). A quick check of the script: SAMPLES=2 BUDGETS=1 EXECUTOR=local OUT=/tmp/unseen.
set -euo pipefail
cd "$(dirname "$0")/.."
TOWN=${TOWN:-101}
SENSOR=${SENSOR:-hdl64}
SAMPLES=${SAMPLES:-48}
BUDGETS=${BUDGETS:-1,2,3,4,5}
CHECKPOINT=${CHECKPOINT:-}
OUT=${OUT:-results/lidar-sim-unseen}
EXECUTOR=${EXECUTOR:-ray}
extra=()
if [ -n "$CHECKPOINT" ]; then
  extra+=(--attack-param "generator.checkpoint=$CHECKPOINT")
fi
icpbench run --dataset lidar-sim --dataset-param "town_seed=$TOWN" --dataset-param "sensor=$SENSOR" \
  --attacks none,uniform,normal,sector,generator --targets p2plane --budgets "$BUDGETS" \
  --samples "$SAMPLES" --batch-size 4 --reference generator --executor "$EXECUTOR" \
  "${extra[@]}" --out "$OUT/run"
for fmt in md latex csv; do
  ext=$fmt; [ "$fmt" = latex ] && ext=tex
  icpbench table "$OUT/run" --format "$fmt" --reference generator --out "$OUT/table1.$ext"
done
cat "$OUT/table1.md"
