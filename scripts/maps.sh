#!/usr/bin/env bash
# Danger maps on lidar-sim at λ = 1 m over every test place x 2 passes (paper figs. 5 and 6): the
# analytic sector attack, then the shipped generator compared with it. Resumable (re-run continues).
# EXECUTOR=local runs in one process (default ray: one worker per core).
set -euo pipefail
cd "$(dirname "$0")/.."
EXECUTOR=${EXECUTOR:-ray}
icpbench map --attack sector --budget 1 --dataset lidar-sim --executor "$EXECUTOR" \
  --out results/lidar-sim-map-sector
icpbench map --attack generator --compare sector --budget 1 --dataset lidar-sim --executor "$EXECUTOR" \
  --out results/lidar-sim-map-generator
# The error no integrity monitor catches: the drift attack told the monitors (each calibrated for 1%
# false alarms on 100 clean train scans registered by p2plane), beside its unmonitored error.
icpbench map --attack drift --monitors all --monitor-aware --budget 1 --dataset lidar-sim \
  --executor "$EXECUTOR" --out results/lidar-sim-map-undetected
