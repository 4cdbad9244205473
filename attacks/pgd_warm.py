"""Attack ``pgd-warm``: the cheaper oracle, a preset of ``pgd``.

Beyond the paper. The projected gradient ascent of :mod:`icpbench.attacks.pgd` (Madry et al.,
ICLR 2018) started from the iterated analytic attack (the one-step worst case of Laconte et al.,
RA-L 2024, re-linearised 8 times where the 100-iteration surrogate lands, on 5 cm approximate
correspondences; :mod:`icpbench.core.iterated_sector`), then 2 steps of 0.1 lambda through that
surrogate with the implicit-function gradient. On 48 lidar-sim test scans it
reached 1.05x / 1.25x the 30-step oracle's mean error at lambda = 1 / 4 m in a third / two thirds
of its time (docs/performance.md, "The PGD oracle and its warm start").
"""

from __future__ import annotations

from typing import Any, ClassVar

from icpbench.attacks.pgd import PGDAttack


class WarmPGDAttack(PGDAttack):
    """:class:`PGDAttack` with the cheaper oracle's defaults (:attr:`preset`); same settings,
    shapes, frames and budget guarantee."""

    name: ClassVar[str] = "pgd-warm"
    description: ClassVar[str] = (
        "A few projected gradient steps from the iterated analytic attack: the cheaper oracle "
        "(beyond the paper)"
    )
    preset: ClassVar[dict[str, Any]] = {"steps": 2, "icp_iterations": 100, "backprop": "implicit",
                                        "init": "sector-iter", "icp_nn_reuse": 0.05,
                                        "sector_iter": {"iterations": 8, "icp_nn_reuse": 0.05}}
