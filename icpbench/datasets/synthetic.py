"""Dataset ``synthetic``: small lidar-like scenes (ground, boxes, poles) with exact normals.

Fast to generate (no ray casting); used by tests, benchmarks and quick demos. Each sample is an
independent surface sampling of the same scene seen from a randomly offset sensor frame
(see :func:`icpbench.datasets.synthetic_scene.scene_sample`).
"""

from __future__ import annotations

import math
from typing import ClassVar

from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.core.types import Sample
from icpbench.datasets.base import Dataset
from icpbench.datasets.synthetic_scene import scene_sample

#: Largest sensor noise (metres) of the synthetic scenes; beyond it a scan is no longer a scene.
MAX_NOISE_M = 10.0


class SyntheticSceneDataset(Dataset):
    """Lidar-like synthetic scenes for tests and demos (no ray casting)."""

    name: ClassVar[str] = "synthetic"
    param_ranges: ClassVar[dict[str, Range]] = {
        "n_samples": Range(0, 10_000_000), "n_scan": Range(6, 10_000_000),
        "n_map": Range(6, 100_000_000), "noise_m": Range(0.0, 10.0)}
    description: ClassVar[str] = "Small lidar-like synthetic scenes (ground, boxes, poles); tests/demos"
    icp_preset: ClassVar[str] = "lidar"

    def __init__(self, *, seed: int = 0, split: str = "test", n_samples: int = 16,
                 n_scan: int = 2_000, n_map: int = 20_000, noise_m: float = 0.02) -> None:
        if split not in ("train", "test", "all"):
            raise InputError(f"split must be one of train, test, all; got {split!r}")
        if n_samples < 0:
            raise InputError(f"n_samples must be >= 0, got {n_samples}")
        for key, n in (("n_scan", n_scan), ("n_map", n_map)):
            if n < 6:
                raise InputError(f"{key} must be >= 6 points (a 6-DoF pose needs 6), got {n}")
        if not (math.isfinite(noise_m) and 0 <= noise_m <= MAX_NOISE_M):
            raise InputError(f"noise_m must be a number of metres from 0 to {MAX_NOISE_M:g} (the "
                             f"scenes are tens of metres across), got {noise_m}")
        super().__init__(seed=seed, split=split, n_samples=n_samples, n_scan=n_scan, n_map=n_map,
                         noise_m=noise_m)
        self.n_samples, self.n_scan, self.n_map, self.noise_m = n_samples, n_scan, n_map, noise_m
        self._offset = {"test": 0, "train": 100_000, "all": 0}[split]

    def __len__(self) -> int:
        return self.n_samples

    def sample_id(self, i: int) -> str:
        return f"synthetic/{self.split}/{i:06d}"

    def __getitem__(self, i: int) -> Sample:
        if not 0 <= i < len(self):
            raise IndexError(f"sample index {i} out of range for {len(self)} samples")
        s = scene_sample(self.n_scan, self.n_map, seed=self._offset + self.seed * 1_000 + i,
                         noise_m=self.noise_m, scene_seed=self.seed)
        return Sample(id=self.sample_id(i), scan=s.scan, map=s.map, map_normals=s.map_normals,
                      T_gt=s.T_gt, T_init=s.T_init, meta={"scene": self.seed})
