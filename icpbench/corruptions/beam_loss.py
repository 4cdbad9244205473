"""Beam loss: whole lasers (rings) of a spinning lidar stop returning."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from icpbench.core.errors import InputError
from icpbench.corruptions.base import Corruption


def elevation_deg(scan: np.ndarray) -> np.ndarray:
    """Elevation angle (N,) in degrees of every point of ``scan`` (N, 3), sensor frame (z up)."""
    return np.degrees(np.arctan2(scan[:, 2], np.hypot(scan[:, 0], scan[:, 1])))


def estimate_rings(scan: np.ndarray, gap_deg: float = 0.15) -> np.ndarray:
    """The ring (laser) index (N,) of every point of ``scan`` (N, 3), sensor frame, metres.

    A spinning lidar fires each laser at a fixed elevation angle, so the points' elevation angles
    form one tight cluster per ring. The sorted elevations are cut wherever two neighbours differ by
    more than ``gap_deg`` degrees; rings are numbered 0.. from the lowest elevation up. Rings closer
    than ``gap_deg`` (or a scan tilted out of the sensor frame) merge into one.
    """
    elev = elevation_deg(scan)
    order = np.argsort(elev, kind="stable")
    starts = np.r_[False, np.diff(elev[order]) > gap_deg]
    rings = np.empty(elev.size, dtype=np.int64)
    rings[order] = np.cumsum(starts)
    return rings


class BeamLoss(Corruption):
    """Beam loss: whole rings of a spinning lidar are lost (a failed laser, dirt or a water drop on
    the window in front of one laser; Robo3D's "beam missing", Kong et al., ICCV 2023).

    Each point's ring is estimated from the scan geometry (:func:`estimate_rings`: the clusters of
    its elevation angle). A seeded random subset of the rings is lost; the lost points are replaced
    by duplicates of surviving points (drawn uniformly), so N is unchanged and the set of rings
    present shrinks. At least one ring is lost and at least one survives. With one seed, the rings
    lost at a level are also lost at every higher level.

    Levels (share of the rings lost; the count is rounded):

    ========  ===================
    severity  rings lost (share)
    ========  ===================
    1         0.10
    2         0.20
    3         0.35
    4         0.50
    5         0.65
    ========  ===================

    Setting ``ring_gap_deg`` (degrees, default 0.15): the smallest gap in elevation between two
    rings. The scan must be in the sensor frame (z along the spin axis).
    """

    name = "beam-loss"
    description = "Whole lidar rings lost (failed lasers); lost points duplicate survivors"
    LEVELS = {1: {"ring_share_lost": 0.10}, 2: {"ring_share_lost": 0.20},
              3: {"ring_share_lost": 0.35}, 4: {"ring_share_lost": 0.50},
              5: {"ring_share_lost": 0.65}}

    def __init__(self, ring_gap_deg: float = 0.15) -> None:
        if not (ring_gap_deg > 0 and math.isfinite(ring_gap_deg)):
            raise InputError(f"beam-loss ring_gap_deg must be a positive number of degrees, got "
                             f"{ring_gap_deg}")
        super().__init__(ring_gap_deg=float(ring_gap_deg))

    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        rings = estimate_rings(scan, self.params["ring_gap_deg"])
        n_rings = int(rings.max()) + 1
        if n_rings < 2:
            raise InputError(f"beam-loss found {n_rings} ring in the scan (elevation gaps over "
                             f"{self.params['ring_gap_deg']} degrees); it needs a spinning-lidar scan "
                             "in the sensor frame with at least 2 rings")
        n_lost = min(max(round(level["ring_share_lost"] * n_rings), 1), n_rings - 1)
        lost_rings = np.sort(rng.permutation(n_rings)[:n_lost])
        lost = np.isin(rings, lost_rings)
        survivors = np.flatnonzero(~lost)
        out = scan.copy()
        out[lost] = scan[survivors[rng.integers(0, survivors.size, int(lost.sum()))]]
        details = {"rings_found": n_rings, "rings_lost": lost_rings.tolist()}
        return out, lost, details
