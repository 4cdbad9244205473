#!/usr/bin/env bash
# Table 1 through the path a user's own recordings take: a drive through an unseen lidar-sim town
# (town_seed 101, no generator was trained on it) seen by the 64-beam sensor (hdl64), written as a
# KITTI odometry sequence (scripts/kitti_from_sim.py) and read back by the `kitti` loader; attacks
# none, uniform, normal and the shipped lidar-sim generator ("Ours"), target p2plane, λ = 1, 3, 5 m.
# Writes $OUT/table1.{md,tex,csv} and $OUT/run/{results.csv,manifest.json}; re-running resumes.
#
# Settings (environment):
#   ROOT=<cache>/kitti-town101-hdl64 (the recording: 200 sweeps, 8.5 m apart, about 400 MB; kept)
#   SAMPLES=48 (a sample is every 4th sweep against the submap of its 3 neighbours on each side)
#   BUDGETS=1,3,5  OUT=results/unseen-kitti  EXECUTOR=processes
# Cost on 2 cores: about 7 min to ray-cast the recording, then about 10 min for the table.
# A quick check: ROOT=/tmp/k FRAMES=12 SAMPLES=2 BUDGETS=1 OUT=/tmp/unseen-kitti.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=${ROOT:-${ICPBENCH_CACHE:-$HOME/.cache/icpbench}/kitti-town101-hdl64}
FRAMES=${FRAMES:-200}
SAMPLES=${SAMPLES:-48}
BUDGETS=${BUDGETS:-1,3,5}
OUT=${OUT:-results/unseen-kitti}
EXECUTOR=${EXECUTOR:-processes}
python scripts/kitti_from_sim.py --out "$ROOT" --town 101 --sensor hdl64 --frames "$FRAMES" \
  --spacing 8.5 --start 20
icpbench run --dataset kitti --dataset-param "root=$ROOT" --dataset-param stride=4 \
  --dataset-param window=3 --attacks none,uniform,normal,generator --targets p2plane \
  --budgets "$BUDGETS" --samples "$SAMPLES" --batch-size 4 --reference generator \
  --attack-param generator.checkpoint=icpbench/checkpoints/lidar-sim/generator.pt \
  --executor "$EXECUTOR" --out "$OUT/run"
for fmt in md latex csv; do
  ext=$fmt; [ "$fmt" = latex ] && ext=tex
  icpbench table "$OUT/run" --format "$fmt" --reference generator --out "$OUT/table1.$ext"
done
cat "$OUT/table1.md"
