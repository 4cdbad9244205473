"""Corruptions in the evaluation grid: realistic degradations run beside the attacks.

A corruption (:mod:`icpbench.corruptions`) is run where the runner runs an attack, through
:class:`CorruptionAttack`, an :class:`~icpbench.attacks.base.Attack` that applies it. Its rows are
ordinary result rows, told apart as follows:

* ``attack`` = the corruption's registry name (``fog``, ``snow``, ...); a corruption may not share
  its name with an attack of the same run;
* ``budget`` = the severity level 1..5 (a number, not metres), in place of the budget lambda;
* ``extra`` holds ``corruption_severity`` (the level again: the mark of a corruption row, see
  :func:`corruption_mask`), ``corruption_share_replaced`` (share of the N points replaced or moved)
  and ``corruption_mean_disp_m`` (mean displacement over all points, metres).

So a row's key (sample, corruption, target, severity, seed) is unique, and a run resumes its
corruption rows exactly like its attack rows. The displacement columns ``disp_*`` hold the
corruption's displacements (metres); ``frac_over_budget`` compares them with the severity read as
metres and means nothing for a corruption row.

Frames: a corruption models the sensor, so it acts in the sensor's own frame (origin at the optical
centre, z up). A sample's scan is the live scan moved by the random initial offset
(:func:`icpbench.datasets.submaps.make_sample`), and its map is expressed in the true vehicle frame
of that scan (origin at the lidar), so ``T_gt`` takes the scan into the sensor's true frame. The
adapter corrupts ``T_gt * scan`` there and moves the result back by ``inv(T_gt)``: ICP then sees a
corrupted scan with the same initial offset as the clean one. This holds for every lidar dataset of
icpbench (``lidar-sim``, ``kitti``, ``boreas``); corruptions are refused on datasets of normalised
objects, which have no sensor.

Random streams: each (seed, corruption, severity, sample) gets its own stream, the runner's rule for
attacks (:func:`icpbench.attacks.base.sample_seed`), so the levels of one sample do not share their
draws here (unlike :meth:`Corruption.apply` called with one seed for every level).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack, SampleGenerators
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.types import Batch
from icpbench.corruptions.base import SEVERITIES, Corruption

if TYPE_CHECKING:
    from icpbench.harness.runner import RunConfig

__all__ = ["SEVERITY_KEY", "CorruptionAttack", "build_corruption_attacks", "check_corruptions",
           "grid_units"]

#: The ``extra`` key that holds a corruption row's severity (and marks the row as a corruption).
SEVERITY_KEY = "corruption_severity"
#: Datasets without a sensor (normalised objects): corruptions are refused there.
NO_SENSOR_DATASETS = frozenset({"objects", "meshes"})


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


class CorruptionAttack(Attack):
    """A corruption run by the runner as if it were an attack; the budget is the severity.

    Args:
        corruption: the corruption model (built from the registry).

    ``name`` is the corruption's name (an instance attribute), so rows, random streams and the
    manifest carry it. Never strict: a corruption is not bounded by a ball of radius ``severity``.
    """

    description: ClassVar[str] = "A realistic corruption at a severity level (icpbench.corruptions)"

    def __init__(self, corruption: Corruption) -> None:
        super().__init__(strict=False, **corruption.settings())
        self.corruption = corruption
        self.name = corruption.name  # type: ignore[misc]

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Any,
                 generator: SampleGenerators) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        severity = int(round(budget_m))
        if severity != budget_m or severity not in SEVERITIES:
            raise InputError(f"corruption {self.name!r}: severity must be one of "
                             f"{list(SEVERITIES)}, got {budget_m!r}")
        scans = batch.scans.detach().to(torch.float64).cpu().numpy()
        T_gt = batch.T_gt.detach().to(torch.float64).cpu().numpy()
        out = scans.copy()
        B = scans.shape[0]
        share, disp = np.zeros(B), np.zeros(B)
        for b in range(B):
            # one integer of the sample's own stream seeds the corruption's numpy stream
            seed = int(torch.randint(0, 2**62, (1,), generator=generator[b]))
            sensor = _transform(T_gt[b], scans[b])  # the scan in the sensor's true frame
            res = self.corruption.apply(sensor, severity, seed=seed)
            out[b] = _transform(np.linalg.inv(T_gt[b]), res.scan)
            share[b], disp[b] = res.share_replaced, res.mean_displacement_m
        extra = {SEVERITY_KEY: np.full(B, float(severity)), "corruption_share_replaced": share,
                 "corruption_mean_disp_m": disp}
        return torch.as_tensor(out, dtype=batch.scans.dtype), extra


def check_corruptions(cfg: RunConfig) -> None:
    """Resolve and check ``cfg.corruptions`` and ``cfg.severities`` in place.

    ``corruptions``: ``[]`` (none), ``["all"]`` (every corruption that loads) or names.
    ``severities``: integers 1..5, each once (checked by ``RunConfig.validate``), sorted here.

    Raises:
        InputError: an unknown corruption, a corruption named like an attack of the run, or
            corruptions on a dataset without a sensor.
    """
    if not cfg.corruptions:
        cfg.corruptions = []
        return
    cfg.corruptions = registry.corruptions.resolve(cfg.corruptions)
    clash = sorted(set(cfg.corruptions) & set(cfg.attacks))
    if clash:
        raise InputError(f"corruption(s) {', '.join(clash)} share their name with an attack of the "
                         "run; their rows could not be told apart")
    if cfg.dataset in NO_SENSOR_DATASETS:
        raise InputError(f"corruptions model a lidar sensor; dataset {cfg.dataset!r} has none "
                         "(use a lidar dataset: lidar-sim, kitti, boreas)")
    # each level is an integer 1..5, given once: checked with every list field of the run
    # (icpbench.harness.settings.LIST_FIELDS), before this is called
    cfg.severities = sorted(int(s) for s in cfg.severities)


def build_corruption_attacks(cfg: RunConfig) -> dict[str, Attack]:
    """``{name: CorruptionAttack}`` for the run's corruptions (default settings of each model)."""
    return {n: CorruptionAttack(registry.corruptions.get(n)()) for n in cfg.corruptions}


def grid_units(cfg: RunConfig, attacks: Sequence[str]) -> list[tuple[float, str]]:
    """The (budget, name) units of one batch, in grid order: every attack at every budget, then
    every corruption at every severity (the severity in the budget's place)."""
    units = [(float(b), a) for b in cfg.budgets or [] for a in attacks if a not in cfg.corruptions]
    return units + [(float(s), c) for s in cfg.severities for c in cfg.corruptions]
