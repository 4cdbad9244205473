#!/usr/bin/env bash
# Danger maps on lidar-sim (paper §IV-D): worst-case error per location at λ = 1 m over the test
# passes. The analytic sector map runs as is; with a lidar-sim generator checkpoint, the generator
# map and the comparison figure (paper fig. 6) are produced by the second command.
# CHECKPOINT=path/to/generator.pt maps another generator than the default lidar-sim one, into
# GEN_OUT (default results/lidar-sim-map-generator).
set -euo pipefail
cd "$(dirname "$0")/.."
icpbench map --attack sector --budget 1 --dataset lidar-sim --out results/lidar-sim-map-sector
CHECKPOINT=${CHECKPOINT:-}
if [ -n "$CHECKPOINT" ] || [ -f icpbench/checkpoints/lidar-sim/generator.pt ]; then
  icpbench map --attack generator --compare sector --budget 1 --dataset lidar-sim \
    ${CHECKPOINT:+--attack-param "generator.checkpoint=$CHECKPOINT"} \
    --out "${GEN_OUT:-results/lidar-sim-map-generator}"
fi
