"""The standard protocol of the leaderboard, as data: what a board is measured on and with.

RobustBench's numbers compare across entries because every entry is measured under one protocol
(Croce et al., "RobustBench: a standardized adversarial robustness benchmark", NeurIPS 2021
datasets and benchmarks track). Here a :class:`Protocol` fixes the data (dataset, its settings,
split, the number of scans: the first K of the split), the budgets lambda, the attack seed and the
settings of the ``ensemble`` (whose defaults are the harness's one definition of the worst case,
:mod:`icpbench.attacks.ensemble`). Each has a name and a version; every board records the protocol
it was made under (``manifest.json``), and a board is resumed, or rows are added to it, only under
the same protocol: :func:`protocol_differences` names what differs otherwise.

Two domains make the standard protocol, so that a ranking can be checked on data of another
shape: ``town`` (the default simulated town and sensor) and ``unseen`` (another town, seed 101,
seen by a 64-beam sensor model). A user's own recordings (``--dataset kitti``) are a third domain
with a protocol of their own (:func:`custom_protocol`).

Units: budgets in metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from icpbench.core.errors import InputError

#: Version of the standard protocol. Raise it whenever a change of the code or of the settings
#: below changes what a standard board computes (e.g. the ensemble's default members). Version 2
#: (2026-11-27): ``sector`` joins the default members and ``valley`` models the target's cost on 4
#: steps of its line (was 8). Version 3 (2026-11-29): ``valley`` models a Geman-McClure kernel
#: (KISS-ICP's) as itself (``valley_kernel_model="geman-mcclure"``; v2 modelled it as none); on
#: every other standard variant v3 computes what v2 did.
STANDARD_VERSION = 3


@dataclass(frozen=True)
class Protocol:
    """What a board is measured on and with (module docstring).

    Attributes:
        name: ``"standard"`` or ``"custom"``.
        version: :data:`STANDARD_VERSION` for the standard protocol, 0 for a custom one.
        domain: the data domain's name (``town``, ``unseen``, or ``custom``).
        dataset: dataset registry name.
        dataset_params: its settings.
        split: the split whose first ``samples`` scans are used.
        samples: scans per variant.
        budgets: lambda values, metres, ascending.
        seed: the attack seed.
        ensemble: settings of the ``ensemble`` attack given on top of its defaults ({}: the
            defaults, which a board also records in full in each variant's run manifest).
    """

    name: str
    version: int
    domain: str
    dataset: str
    dataset_params: dict[str, Any] = field(default_factory=dict)
    split: str = "test"
    samples: int = 48
    budgets: tuple[float, ...] = (1.0,)
    seed: int = 0
    ensemble: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """The protocol as JSON-ready data (budgets as a list)."""
        d = asdict(self)
        d["budgets"] = list(self.budgets)
        return d


#: The standard protocol's domains, by name.
STANDARD_DOMAINS: dict[str, Protocol] = {
    "town": Protocol("standard", STANDARD_VERSION, "town", "lidar-sim"),
    "unseen": Protocol("standard", STANDARD_VERSION, "unseen", "lidar-sim",
                       {"town_seed": 101, "sensor": "hdl64"}),
}


def standard_protocol(domain: str = "town") -> Protocol:
    """The standard protocol of one domain.

    Raises:
        InputError: an unknown domain (the message lists the known ones).
    """
    if domain not in STANDARD_DOMAINS:
        raise InputError(f"unknown domain {domain!r}; standard domains: "
                         f"{', '.join(STANDARD_DOMAINS)}")
    return STANDARD_DOMAINS[domain]


def custom_protocol(dataset: str, dataset_params: Mapping[str, Any], split: str, samples: int,
                    budgets: tuple[float, ...], seed: int, ensemble: Mapping[str, Any]
                    ) -> Protocol:
    """A protocol of the user's own (any setting that departs from a standard domain)."""
    return Protocol("custom", 0, "custom", dataset, dict(dataset_params), split, int(samples),
                    tuple(float(b) for b in budgets), int(seed), dict(ensemble))


def protocol_differences(stored: Mapping[str, Any] | None, now: Mapping[str, Any]) -> list[str]:
    """The fields (``field: stored X, now Y``) in which a stored protocol differs from ``now``
    (both as :meth:`Protocol.as_dict`); a board recorded without a protocol differs in all."""
    if stored is None:
        return ["protocol: the board records none (made before protocols were recorded)"]
    out = []
    for k in now:
        a, b = stored.get(k), now[k]
        if a != b:
            out.append(f"{k}: stored {a!r}, now {b!r}")
    return out
