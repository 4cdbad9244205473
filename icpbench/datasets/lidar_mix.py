"""Several ``lidar-sim`` towns and sensors as one dataset (training on variety).

``LidarSimDataset.create(town_seed=[1, 2, 3], sensor=["sim32", "hdl64"], split="train")`` (or on the
command line ``--dataset-param town_seed=[1,2,3] --dataset-param sensor=[sim32,hdl64]``) returns
a :class:`LidarSimMix`: one single-town :class:`~icpbench.datasets.lidar_sim.LidarSimDataset` per
(town, sensor) combination, built with the same other parameters, each generated and cached once
in its own folder (the cache key holds the town seed and the sensor), and their samples shuffled
together with a seeded permutation, so ``take(k)`` draws from every combination. Sample ids carry
the town and sensor (``lidar-sim/town3/hdl64/pass2/000041``), so they are unique across the mix.

A generalisation split trains on one list of town seeds and evaluates on others (e.g. train on
``town_seed=[1,2,3]``, run Table 1 on ``town_seed=101``): the towns share no geometry.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

from icpbench.core.errors import InputError
from icpbench.core.types import Sample
from icpbench.datasets import submaps as sm
from icpbench.datasets.base import Dataset
from icpbench.datasets.sensors import DEFAULT_SENSOR

#: Random stream of the mix's shuffling (distinct from the single-town streams).
_MIX_ORDER = 101


def _as_list(value: Any, what: str) -> list:
    vals = list(value) if isinstance(value, list | tuple) else [value]
    if not vals:
        raise InputError(f"{what} list is empty")
    if len(set(map(str, vals))) != len(vals):
        raise InputError(f"{what} list has duplicates: {vals}")
    return vals


class LidarSimMix(Dataset):
    """Every (town seed, sensor) combination of ``lidar-sim``, shuffled together.

    Args:
        town_seed: town seeds (None in the list: the original town).
        sensor: sensor presets.
        seed, split, order, and every other keyword: passed to each single-town dataset.
    """

    name: ClassVar[str] = "lidar-sim"
    description: ClassVar[str] = "Several lidar-sim towns and sensors"
    icp_preset: ClassVar[str] = "lidar"
    default_budgets: ClassVar[tuple[float, ...]] = (1.0, 2.0, 3.0, 4.0, 5.0)

    def __init__(self, *, seed: int = 0, split: str = "test",
                 town_seed: int | Sequence[int] | None = None,
                 sensor: str | Sequence[str] = DEFAULT_SENSOR, order: str = "shuffled",
                 **kwargs: Any) -> None:
        from icpbench.datasets.lidar_sim import LidarSimDataset

        towns = _as_list(town_seed, "town_seed")
        sensors = _as_list(sensor, "sensor")
        self.parts = [LidarSimDataset(seed=seed, split=split, town_seed=t, sensor=s, order=order,
                                      **kwargs) for t in towns for s in sensors]
        super().__init__(seed=seed, split=split, **{
            **{k: v for k, v in self.parts[0].params.items() if k not in ("town_seed", "sensor")},
            "town_seed": towns, "sensor": sensors})
        index = [(k, i) for k, part in enumerate(self.parts) for i in range(len(part))]
        if order == "shuffled":
            perm = sm.sample_rng(seed, _MIX_ORDER, len(index)).permutation(len(index))
            index = [index[i] for i in perm]
        self._index = index

    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, i: int) -> Sample:
        if not -len(self) <= i < len(self):
            raise IndexError(f"sample index {i} out of range for {len(self)} samples")
        k, j = self._index[i]
        return self.parts[k][j]

    def sample_id(self, i: int) -> str:
        """The id of sample ``i`` without generating it."""
        k, j = self._index[i]
        return self.parts[k].sample_id(j)

    def prepare(self, progress: bool | None = None) -> None:
        """Generate (or check the cache of) every part."""
        for part in self.parts:
            part.prepare(progress)
