"""Corruption base class: a realistic, seeded degradation of one lidar scan at a severity level.

A corruption models something physical that happens to a real scan (fog, snow, a lost laser, a
vehicle next to the sensor, ...), unlike an attack, which moves points adversarially within a
budget. Severity is graded 1..5 as in Robo3D (Kong et al., "Robo3D: Towards Robust and Reliable 3D
Perception against Corruptions", ICCV 2023): every corruption class maps each level to physical
parameters in its table :attr:`Corruption.LEVELS` (documented, with units, in the class docstring).

The contract: a subclass sets ``name``, ``description`` and ``LEVELS`` and implements
:meth:`Corruption._corrupt`; :meth:`Corruption.apply`, which subclasses cannot override, checks the
input, draws the random stream, checks what the subclass returned and writes the record (share of
points replaced or moved, mean displacement, the parameters used). The point count N never changes:
a point the physics removes is replaced as the model says (resampled from the surviving points, or
moved to a model-specific return along its own ray).

Frame and units: the scan is (N, 3) in the sensor frame (origin at the optical centre, z along the
spin axis, x forward, y left), metres.
"""

from __future__ import annotations

import zlib
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, final

import numpy as np

from icpbench.core.errors import InputError

__all__ = ["SEVERITIES", "Corruption", "CorruptionRecord", "CorruptionResult", "rays"]

#: The severity levels every corruption defines (Robo3D's five levels).
SEVERITIES: tuple[int, ...] = (1, 2, 3, 4, 5)

#: Points closer to the sensor than this (metres) have no usable ray direction.
MIN_RANGE_M = 1e-6


@dataclass(frozen=True)
class CorruptionRecord:
    """What a corruption did to one scan.

    Attributes:
        name: the corruption's registry name.
        severity: the level 1..5.
        seed: the seed of the random stream.
        share_replaced: fraction of the N points replaced or moved (0..1).
        mean_displacement_m: mean over all N points of ``|new - old|`` (metres).
        params: the physical parameters used: the level's row of ``LEVELS`` and the model's
            settings (units in the names: ``_m`` metres, ``_per_m`` 1/m, ``_deg`` degrees, ...).
        details: per-scan draws and counts of the model (e.g. the occluder's pose, the rings lost).
    """

    name: str
    severity: int
    seed: int
    share_replaced: float
    mean_displacement_m: float
    params: Mapping[str, Any]
    details: Mapping[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """The record as plain Python values (for JSON)."""
        return {"name": self.name, "severity": self.severity, "seed": self.seed,
                "share_replaced": self.share_replaced, "mean_displacement_m": self.mean_displacement_m,
                "params": _plain(self.params), "details": _plain(self.details)}


@dataclass(frozen=True)
class CorruptionResult:
    """A corrupted scan and its record.

    Attributes:
        scan: (N, 3) corrupted scan, sensor frame, metres, same dtype as the input.
        replaced: (N,) bool, True for the points replaced or moved.
        record: the :class:`CorruptionRecord`.
    """

    scan: np.ndarray
    replaced: np.ndarray
    record: CorruptionRecord

    @property
    def share_replaced(self) -> float:
        """Fraction of points replaced or moved."""
        return self.record.share_replaced

    @property
    def mean_displacement_m(self) -> float:
        """Mean displacement over all points (metres)."""
        return self.record.mean_displacement_m


def rays(scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ranges (N,) in metres and unit ray directions (N, 3) of a scan (N, 3), sensor frame."""
    r = np.linalg.norm(scan, axis=1)
    return r, scan / np.maximum(r, MIN_RANGE_M)[:, None]


class Corruption(ABC):
    """Base class of every corruption, and the whole contract of a corruption plugin.

    A subclass sets the class attributes below and implements :meth:`_corrupt`; :meth:`apply` (final)
    validates the input, seeds the random stream, checks the output and writes the record.

    Construction: ``cls(**settings)``, where the settings are the named keyword parameters of the
    subclass's ``__init__`` (:meth:`param_types`; model constants such as a sensor height), checked
    with :func:`icpbench.core.registry.check_params` before the corruption is built.
    """

    #: Registry key; must equal the entry-point name the plugin is registered under.
    name: ClassVar[str] = ""
    #: One line for ``icpbench list``.
    description: ClassVar[str] = ""
    #: Severity level (1..5) -> physical parameters of that level (names carry their units).
    LEVELS: ClassVar[dict[int, dict[str, Any]]] = {}
    #: Whether the output depends on the seed (False: a deterministic model).
    random: ClassVar[bool] = True

    def __init__(self, **params: Any) -> None:
        self.params = params  # a subclass passes its own settings here to record them

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "apply" in cls.__dict__:
            raise TypeError(f"{cls.__name__} overrides Corruption.apply, which is final (it checks the "
                            "input and the output and writes the record); implement _corrupt")
        if "LEVELS" in cls.__dict__ and set(cls.LEVELS) != set(SEVERITIES):
            raise TypeError(f"{cls.__name__}.LEVELS must define the severities {list(SEVERITIES)}, "
                            f"got {sorted(cls.LEVELS)}")

    @classmethod
    def param_types(cls) -> dict[str, Any]:
        """Settings the corruption accepts (name -> type hint): the named keyword parameters of its
        ``__init__``. Unknown settings are refused and values are coerced to these types."""
        from icpbench.core.registry import keyword_params

        return keyword_params(cls.__init__)

    def settings(self) -> dict[str, Any]:
        """The constructor settings (recorded with the level's parameters)."""
        return dict(self.params)

    @abstractmethod
    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """Corrupt one scan.

        Args:
            scan: (N, 3) float64 clean scan, sensor frame, metres (validated: finite, no point at
                the origin).
            level: the row of :attr:`LEVELS` for the requested severity.
            rng: the only source of randomness (seeded from the seed and the corruption's name).

        Returns:
            (scan, replaced, details): the (N, 3) corrupted scan, an (N,) bool mask of the points
            replaced or moved, and per-scan draws and counts for the record.
        """

    @final
    def apply(self, scan: np.ndarray, severity: int, seed: int = 0) -> CorruptionResult:
        """Corrupt ``scan`` at ``severity`` with the random stream of ``seed``.

        Args:
            scan: (N, 3) floating-point array, sensor frame, metres.
            severity: level 1..5 (Robo3D's scale).
            seed: integer >= 0; the same (scan, severity, seed) always gives the same result.

        Returns:
            :class:`CorruptionResult` with the corrupted (N, 3) scan (input dtype) and its record.

        Raises:
            InputError: a scan that is not a finite (N, 3) floating-point array with N >= 1 and no
                point at the sensor origin, a severity outside 1..5, or a seed that is not an
                integer >= 0.
        """
        arr = _check_scan(scan)
        severity = _check_severity(severity)
        seed = _check_seed(seed)
        level = dict(self.LEVELS[severity])
        # The stream depends on the seed and the corruption, not on the severity: levels of one seed
        # share their draws (common random numbers), so a higher level degrades the same scan more.
        rng = np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(self.name.encode())]))
        clean = arr.astype(np.float64)
        out, replaced, details = self._corrupt(clean.copy(), level, rng)
        out = np.asarray(out, dtype=np.float64)
        replaced = np.asarray(replaced, dtype=bool)
        if out.shape != clean.shape:
            raise RuntimeError(f"corruption {self.name!r} returned shape {out.shape}, expected "
                               f"{clean.shape} (the point count must not change)")
        if replaced.shape != (clean.shape[0],):
            raise RuntimeError(f"corruption {self.name!r} returned a mask of shape {replaced.shape}, "
                               f"expected ({clean.shape[0]},)")
        if not np.all(np.isfinite(out)):
            raise RuntimeError(f"corruption {self.name!r} returned non-finite coordinates")
        moved = np.any(out != clean, axis=1)
        if np.any(moved & ~replaced):
            raise RuntimeError(f"corruption {self.name!r} moved points it did not mark as replaced")
        disp = np.linalg.norm(out - clean, axis=1)
        record = CorruptionRecord(
            name=self.name, severity=severity, seed=seed,
            share_replaced=float(replaced.mean()), mean_displacement_m=float(disp.mean()),
            params={**level, **self.settings()}, details=details)
        return CorruptionResult(scan=out.astype(arr.dtype), replaced=replaced, record=record)


def _check_scan(scan: Any) -> np.ndarray:
    if not isinstance(scan, np.ndarray):
        raise InputError(f"scan must be a numpy array of shape (N, 3), got {type(scan).__name__}")
    if scan.ndim != 2 or scan.shape[1] != 3:
        raise InputError(f"scan must have shape (N, 3) (sensor frame, metres), got {scan.shape}")
    if scan.shape[0] == 0:
        raise InputError("scan is empty (0 points)")
    if not np.issubdtype(scan.dtype, np.floating):
        raise InputError(f"scan must be a floating-point array, got dtype {scan.dtype}")
    finite = np.isfinite(scan).all(axis=1)
    if not finite.all():
        raise InputError(f"scan has {int((~finite).sum())} point(s) with NaN or Inf coordinates")
    at_origin = np.linalg.norm(scan.astype(np.float64), axis=1) < MIN_RANGE_M
    if at_origin.any():
        raise InputError(f"scan has {int(at_origin.sum())} point(s) at the sensor origin (range 0), "
                         "whose ray direction is undefined; drop them first")
    return scan


def _check_severity(severity: Any) -> int:
    if isinstance(severity, bool) or not isinstance(severity, int | np.integer):
        raise InputError(f"severity must be an integer 1..5, got {severity!r}")
    if int(severity) not in SEVERITIES:
        raise InputError(f"severity must be 1..5, got {severity}")
    return int(severity)


def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"seed must be an integer >= 0, got {seed!r}")
    return int(seed)


def _plain(value: Any) -> Any:
    """numpy scalars and arrays inside mappings/lists as plain Python values."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
