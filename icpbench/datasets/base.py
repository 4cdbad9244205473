"""Dataset base class: an indexable, deterministic sequence of :class:`~icpbench.core.types.Sample`."""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar, Literal

from icpbench.core.errors import InputError
from icpbench.core.types import Sample

Split = Literal["train", "test", "all"]


def default_cache_dir() -> Path:
    """Where generated datasets are cached: ``$ICPBENCH_CACHE`` or ``~/.cache/icpbench``."""
    return Path(os.environ.get("ICPBENCH_CACHE", Path.home() / ".cache" / "icpbench"))


class Dataset(ABC):
    """A deterministic collection of samples.

    Class attributes:
        name: registry key.
        description: one line for ``icpbench list``.
        icp_preset: the ICP preset matching the data's scale (``"objects"`` or ``"lidar"``).
        default_budgets: budgets (metres or normalised units) used when none are given.

    ``dataset[i]`` returns the i-th sample of the chosen split; the same constructor arguments
    always give the same samples. Construction: the runner calls ``cls.create(seed=..., split=...,
    **settings)`` with the user's ``--dataset-param KEY=VALUE`` settings, checked against
    :meth:`param_types`; :meth:`create` is ``cls(...)`` unless a dataset overrides it (a
    factory: ``lidar-sim`` with several towns or sensors builds a mix of single-town datasets).
    A sample whose input file is bad raises :class:`InputError` naming the file
    from ``dataset[i]``; the runner then skips that sample (error rows) unless ``strict_files``.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    icp_preset: ClassVar[str] = "lidar"
    default_budgets: ClassVar[tuple[float, ...]] = (1.0, 2.0, 3.0, 4.0, 5.0)

    @classmethod
    def create(cls, **settings: Any) -> Dataset:
        """The dataset for these constructor settings (a subclass may return another
        :class:`Dataset` made of instances of itself, e.g. a mix)."""
        return cls(**settings)

    @classmethod
    def param_types(cls) -> dict[str, Any]:
        """Settings the dataset accepts (name -> type hint), i.e. its ``--dataset-param`` keys: the
        named keyword parameters of ``__init__`` except ``seed`` and ``split`` (set by the run).
        Unknown settings are refused and values are coerced to these types before it is built."""
        from icpbench.core.registry import keyword_params

        return keyword_params(cls.__init__, skip=("seed", "split"))

    def sample_id(self, i: int) -> str:
        """The id of sample ``i`` (default: loads the sample; datasets override it with a cheap
        lookup, so the runner can name a sample whose file cannot be read)."""
        return self[i].id

    def __init__(self, *, seed: int = 0, split: Split = "test", **params: Any) -> None:
        if split not in ("train", "test", "all"):
            raise InputError(f"split must be one of train, test, all; got {split!r}")
        self.seed = int(seed)
        self.split = split
        self.params = params

    @abstractmethod
    def __len__(self) -> int:
        """Number of samples in the split."""

    @abstractmethod
    def __getitem__(self, i: int) -> Sample:
        """The i-th sample (0 <= i < len)."""

    def __iter__(self) -> Iterator[Sample]:
        for i in range(len(self)):
            yield self[i]

    def take(self, k: int | None) -> list[Sample]:
        """The first ``k`` samples of the split (all when ``k`` is None)."""
        n = len(self) if k is None else min(int(k), len(self))
        return [self[i] for i in range(n)]

    def describe(self) -> dict[str, Any]:
        """Parameters recorded in manifests."""
        return {"name": self.name, "seed": self.seed, "split": self.split, **self.params}
