"""Write a drive through a lidar-sim town as a KITTI odometry sequence (the layout a user's own
recordings have), so that the ``kitti`` loader can be checked on data of another shape than the
training town.

    python scripts/kitti_from_sim.py --out DIR [--town 101] [--sensor hdl64] [--frames 200]
        [--spacing 14] [--start 20]

Drives the lane centre from arc length ``--start`` metres, one sweep every ``--spacing`` metres
(the teach pass's parked cars, no movers), and writes ``DIR/sequences/00`` and ``DIR/poses/00.txt``
(:func:`icpbench.datasets.kitti_export.write_kitti_sequence`). A finished sequence is kept: the
script exits at once when ``DIR/poses/00.txt`` already lists ``--frames`` poses.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="KITTI root to write")
    ap.add_argument("--town", type=int, default=101, help="lidar-sim town_seed")
    ap.add_argument("--sensor", default="hdl64", help="lidar-sim sensor preset")
    ap.add_argument("--frames", type=int, default=200, help="sweeps to write (>= 2)")
    ap.add_argument("--spacing", type=float, default=14.0, help="metres between sweeps")
    ap.add_argument("--start", type=float, default=20.0, help="arc length of the first sweep [m]")
    args = ap.parse_args()

    from icpbench.core.errors import InputError
    from icpbench.datasets.kitti_export import write_kitti_sequence
    from icpbench.datasets.lidar_sim import LidarSimDataset

    poses = args.out / "poses" / "00.txt"
    if poses.is_file() and len(poses.read_text().splitlines()) == args.frames:
        print(f"{args.out}: {args.frames} sweeps already written", file=sys.stderr)
        return 0
    try:
        town = LidarSimDataset(town_seed=args.town, sensor=args.sensor)
        length = town.route.length
        if args.start + (args.frames - 1) * args.spacing > length:
            raise InputError(f"{args.frames} sweeps {args.spacing:g} m apart from {args.start:g} m "
                             f"run past the end of the route ({length:.0f} m)")
        t0 = time.perf_counter()
        seq = write_kitti_sequence(town, args.out, s_start_m=args.start, n_frames=args.frames,
                                   spacing_m=args.spacing)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{seq}: {args.frames} sweeps of town {args.town} ({args.sensor}) in "
          f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
