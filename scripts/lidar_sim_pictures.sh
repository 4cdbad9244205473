#!/usr/bin/env bash
# Pictures of the simulated lidar data in results/lidar-sim/ (every axis in metres):
#   lidar-sim_route.png, lidar-sim_scan_on_submap.png   the default town and one scan on its submap
#   towns.png     three towns (town_seed 1, 2, 3) from above, route coloured by place
#   sensors.png   one place (town_seed 1, pass 1, location 30, a suburban street) seen by the
#                 vlp16, hdl32, hdl64 and os128 presets: full sweeps before the subsampling to N
# About 3 minutes on one core (three towns are built and ray-cast from above).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-results/lidar-sim}
icpbench show-dataset lidar-sim --out "$OUT"
python - "$OUT" <<'PY'
import sys

from icpbench.analysis.dataset_figures import sensors_figure, towns_figure
from icpbench.datasets.lidar_sim import LidarSimDataset

out = sys.argv[1]
print(towns_figure([LidarSimDataset(town_seed=t) for t in (1, 2, 3)], f"{out}/towns.png"))
sensors = [LidarSimDataset(town_seed=1, sensor=s) for s in ("vlp16", "hdl32", "hdl64", "os128")]
print(sensors_figure(sensors, f"{out}/sensors.png", pass_id=1, frame=30))
PY
