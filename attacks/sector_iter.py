"""Attack ``sector-iter``: the analytic sector step, re-linearised where the attacked ICP lands.

Beyond the paper; the computation and its settings are in :mod:`icpbench.core.iterated_sector`
(Laconte et al., RA-L 2024, iterated as in Kurakin et al., ICLR workshop 2017). Its registered
defaults are what Table 1 runs, and the same settings make the shipped generator's prior, so in one
run the two rows share the computation (the generator's row then adds only its network).

Cost: ``iterations + 1`` forward surrogate ICPs and ``iterations`` nearest-neighbour queries and 6x6
solves per scan; no autograd. The budget holds exactly (projection), so the displacement audit
shows 0% over lambda. Knowledge assumed: the map, the true pose and the initial guess, as for the
PGD oracle.

Extras per sample: ``sector_iter_best`` (index of the returned iterate, 0 = the sector start),
``sector_iter_surrogate_xy`` (its surrogate error, metres) and ``reused_s`` (seconds per scan of
work this row took from the batch's memo instead of computing it; 0 when it computed it).
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack
from icpbench.core.errors import InputError
from icpbench.core.iterated_sector import SectorIterSettings, is_memoised, iterated_sector
from icpbench.core.registry import Range
from icpbench.core.types import Batch
from icpbench.targets.base import Target


class SectorIterAttack(Attack):
    """Iterated analytic worst case (see :class:`~icpbench.core.iterated_sector.SectorIterSettings`
    for the settings, their units and defaults)."""

    name: ClassVar[str] = "sector-iter"
    description: ClassVar[str] = (
        "Analytic sector step re-linearised at the pose the surrogate ICP reaches, repeated "
        "(beyond the paper)"
    )
    needs_surrogate: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {
        "iterations": Range(0, 100_000), "step_size": Range(0.0, 2.0, lo_open=True),
        "icp_iterations": Range(1, 1_000_000), "icp_nn_reuse": Range(0.0),
        "d_max": Range(0.0, lo_open=True)}

    def __init__(self, *, strict: bool = False, iterations: int = SectorIterSettings.iterations,
                 step_size: float = SectorIterSettings.step_size,
                 icp_iterations: int = SectorIterSettings.icp_iterations,
                 icp_nn_reuse: float = SectorIterSettings.icp_nn_reuse,
                 d_max: float | None = None, **params: Any) -> None:
        self.iter_settings = SectorIterSettings(iterations=iterations, step_size=step_size,
                                           icp_iterations=icp_iterations, icp_nn_reuse=icp_nn_reuse,
                                           d_max=d_max)
        super().__init__(strict=strict, **self.iter_settings.as_dict(), **params)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: torch.Generator) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        if surrogate is None:
            raise InputError(f"{self.name} needs a surrogate ICP target (--surrogate p2plane)")
        hit = is_memoised(batch, budget_m, surrogate, self.iter_settings)
        res = iterated_sector(batch, budget_m, surrogate, self.iter_settings)
        reused = res.seconds / len(batch) if hit else 0.0
        extra = {"sector_iter_best": res.best_iterate, "sector_iter_surrogate_xy": res.surrogate_xy,
                 "reused_s": np.full(len(batch), reused)}
        return torch.as_tensor(res.scans, dtype=batch.scans.dtype), extra
