"""Dataset ``synthetic``: small lidar-like scenes (ground, boxes, poles) with exact normals.

Fast to generate (no ray casting); used by tests, benchmarks and quick demos. Each sample is an
independent surface sampling of the same scene seen from a randomly offset sensor frame
(see :func:`icpbench.synthetic.scene_sample`).
"""

from __future__ import annotations

from typing import Any, ClassVar

from icpbench.datasets.base import Dataset
from icpbench.synthetic import scene_sample
from icpbench.types import Sample


class SyntheticSceneDataset(Dataset):
    """Lidar-like synthetic scenes for tests and demos (no ray casting)."""

    name: ClassVar[str] = "synthetic"
    description: ClassVar[str] = "Small lidar-like synthetic scenes (ground, boxes, poles); tests/demos"
    icp_preset: ClassVar[str] = "lidar"

    def __init__(self, *, seed: int = 0, split: str = "test", n_samples: int = 16,
                 n_scan: int = 2_000, n_map: int = 20_000, noise_m: float = 0.02,
                 **params: Any) -> None:
        super().__init__(seed=seed, split=split, n_samples=n_samples, n_scan=n_scan, n_map=n_map,
                         noise_m=noise_m, **params)
        self.n_samples, self.n_scan, self.n_map, self.noise_m = n_samples, n_scan, n_map, noise_m
        self._offset = {"test": 0, "train": 100_000, "all": 0}[split]

    def __len__(self) -> int:
        return self.n_samples

    def sample_id(self, i: int) -> str:
        return f"synthetic/{self.split}/{i:06d}"

    def __getitem__(self, i: int) -> Sample:
        if not 0 <= i < len(self):
            raise IndexError(i)
        s = scene_sample(self.n_scan, self.n_map, seed=self._offset + self.seed * 1_000 + i,
                         noise_m=self.noise_m, scene_seed=self.seed)
        return Sample(id=self.sample_id(i), scan=s.scan, map=s.map, map_normals=s.map_normals,
                      T_gt=s.T_gt, T_init=s.T_init, meta={"scene": self.seed})
