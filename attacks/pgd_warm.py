"""Attack ``pgd-warm``: the cheaper oracle, a few PGD steps from the iterated analytic attack.

Beyond the paper. The same projected gradient ascent as :mod:`icpbench.attacks.pgd` (Madry et al.,
ICLR 2018), with other defaults: it starts from the output of ``sector-iter`` (the one-step worst
case of Laconte et al., RA-L 2024, re-linearised 8 times on a 100-iteration surrogate ICP with 5 cm
approximate correspondences) and takes 2 steps of 0.1 lambda through the 100-iteration surrogate
on the same correspondences, with the implicit-function gradient. On 48 lidar-sim test scans its
mean error is 1.05x / 1.25x that of the 30-step oracle at lambda = 1 / 4 m at about a sixth /
a third of the original oracle's time (docs/performance.md, section 13). Every setting of ``pgd``
is a setting here too; ``pgd`` itself keeps the original oracle's defaults.
"""

from __future__ import annotations

from typing import Any, ClassVar

from icpbench.attacks.pgd import PGDAttack

#: the warm start: sector-iter with 8 re-linearisations on a 100-iteration, 5 cm reuse surrogate
WARM_START: dict[str, Any] = {"iterations": 8, "icp_iterations": 100, "icp_nn_reuse": 0.05}


class WarmPGDAttack(PGDAttack):
    """PGD warm-started from ``sector-iter``: :class:`PGDAttack` with the cheaper oracle's
    defaults (2 steps, 100-iteration surrogate with 5 cm correspondence reuse and the implicit
    gradient; start :data:`WARM_START` unless ``init_params`` says otherwise). Shapes, frames
    and the budget guarantee are those of :class:`PGDAttack`."""

    name: ClassVar[str] = "pgd-warm"
    description: ClassVar[str] = (
        "A few projected gradient steps from the iterated analytic attack: the cheaper oracle "
        "(beyond the paper)"
    )

    def __init__(self, *, strict: bool = False, steps: int = 2, step_size: float = 0.1,
                 weights: str | list[float] = "xy", icp_iterations: int = 100,
                 random_start: bool = True, restarts: int = 1, schedule: str = "constant",
                 final_step_size: float = 0.02, patience: int | None = None,
                 backprop: str | None = "implicit", init: str | None = "sector-iter",
                 icp_nn_reuse: float = 0.05, init_params: dict[str, Any] | None = None) -> None:
        if init_params is None and init == "sector-iter":
            init_params = dict(WARM_START)
        super().__init__(strict=strict, steps=steps, step_size=step_size, weights=weights,
                         icp_iterations=icp_iterations, random_start=random_start,
                         restarts=restarts, schedule=schedule, final_step_size=final_step_size,
                         patience=patience, backprop=backprop, init=init,
                         icp_nn_reuse=icp_nn_reuse, init_params=init_params)
