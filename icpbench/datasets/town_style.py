"""What varies from one ``lidar-sim`` town to the next (``--dataset-param town_seed=N``).

A :class:`TownStyle` holds every number the town builders of :mod:`icpbench.datasets.town` use
that is not drawn per object: the route corners and the order and lengths of its stretches, road
widths, house sizes and set-backs, vegetation density, parking occupancy, fences, the shape of the
ground (slopes and road camber, :class:`~icpbench.datasets.ground.Ground`) and whether street
clutter is added (irregular trees and bushes, poles and signs, kerbs, moving road users in the
repeat passes; :mod:`icpbench.datasets.clutter`).

:data:`LEGACY` is the original town (``town_seed`` unset): the builders then draw exactly the
random numbers they always drew, so the default ``lidar-sim`` scans are unchanged bit for bit.
:func:`random_style` draws a new style from a town seed; every such town has all five places,
slopes, camber and clutter.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from icpbench.core.errors import InputError

#: Default route: corners of a hexagon-like loop (metres, about 2.8 km once the corners are rounded).
DEFAULT_CORNERS: tuple[tuple[float, float], ...] = (
    (0.0, 0.0), (600.0, 0.0), (900.0, 250.0), (900.0, 650.0), (350.0, 700.0), (0.0, 450.0),
)
#: Default layout: (start as a fraction of the route length, place), in driving order.
DEFAULT_LAYOUT: tuple[tuple[float, str], ...] = (
    (0.00, "suburb"), (0.22, "parking"), (0.30, "suburb"), (0.40, "field"), (0.52, "highway"),
    (0.70, "underpass"), (0.76, "highway"), (0.84, "field"), (0.93, "suburb"),
)
#: Road extent (d_right, d_left) in metres around the driven lane centre, per place. The lane to the
#: left (d = +3.5 m) is the oncoming / overtaking lane where the passing truck drives.
DEFAULT_ROAD: dict[str, tuple[float, float]] = {
    "suburb": (-4.5, 8.0),
    "parking": (-4.5, 8.0),
    "field": (-2.5, 5.5),
    "highway": (-3.5, 12.0),
    "underpass": (-3.5, 8.0),
}


@dataclass(frozen=True)
class TownStyle:
    """Per-town constants (metres unless stated).

    Attributes:
        name: ``"legacy"`` or ``"town<seed>"``.
        corners, layout: route polygon (town frame) and ((start fraction, place), ...).
        road: place -> (d_right, d_left) road extent around the driven lane centre.
        setback_m, lot_m, house_len_m, house_wid_m, house_h_m: suburban lots and houses (ranges).
        trees_per_lot: suburban trees per lot are drawn from 0 .. trees_per_lot - 1.
        field_tree_every_m, highway_tree_every_m: one tree per this many metres (Poisson mean).
        kerb_occupancy, lot_occupancy: probability that a parking space is usually occupied.
        fence_front_p, fence_side_p: probability of a front fence / a fence between lots.
        lamp_spacing_m: suburban street lamps.
        grade_waves: ((amplitude_m, wavelength_m, direction_rad, phase_rad), ...) plane waves of
            the ground height (slopes); empty: flat.
        camber: road cross-slope (m/m) down from the lane line at d = 1.75 m.
        clutter: add street clutter (irregular trees and bushes, poles, signs, kerbs).
        bush_every_m, sign_every_m, post_every_m: mean spacing of bushes, signs, bollards/posts
            per side along the dense and open stretches (clutter towns).
        movers_per_scan: mean number of moving road users (cars, cyclists, pedestrians) around
            a live scan of a repeat pass (never in the teach pass, hence never in the map).
        legacy: the original town's quirks (flat ground quad; poles' tops at an absolute height).
    """

    name: str = "legacy"
    corners: tuple[tuple[float, float], ...] = DEFAULT_CORNERS
    layout: tuple[tuple[float, str], ...] = DEFAULT_LAYOUT
    road: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(DEFAULT_ROAD))
    setback_m: tuple[float, float] = (3.0, 9.0)
    lot_m: tuple[float, float] = (14.0, 22.0)
    house_len_m: tuple[float, float] = (8.0, 14.0)
    house_wid_m: tuple[float, float] = (8.0, 12.0)
    house_h_m: tuple[float, float] = (3.0, 6.5)
    trees_per_lot: int = 3
    field_tree_every_m: float = 100.0
    highway_tree_every_m: float = 150.0
    kerb_occupancy: float = 0.35
    lot_occupancy: float = 0.4
    fence_front_p: float = 0.6
    fence_side_p: float = 0.5
    lamp_spacing_m: float = 35.0
    grade_waves: tuple[tuple[float, float, float, float], ...] = ()
    camber: float = 0.0
    clutter: bool = False
    bush_every_m: float = 0.0
    sign_every_m: float = 0.0
    post_every_m: float = 0.0
    movers_per_scan: float = 0.0
    legacy: bool = True

    def to_dict(self) -> dict:
        """JSON-ready summary (recorded with the dataset)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


LEGACY = TownStyle()

_PLACES = ("suburb", "parking", "field", "highway", "underpass")
#: Relative stretch lengths (before the random weights) and minimum lengths (fraction of the loop).
_WEIGHT = {"suburb": 1.0, "parking": 0.45, "field": 0.9, "highway": 1.1, "underpass": 0.3}


def _corners(rng: np.random.Generator) -> np.ndarray:
    """A star-shaped polygon (K, 2) of 5-7 corners, 220-420 m from its centre, no corner sharper
    than 75 degrees (the fillets need room)."""
    for _ in range(200):
        k = int(rng.integers(5, 8))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        gaps = np.diff(np.r_[ang, ang[0] + 2 * np.pi])
        if gaps.min() < 0.55 * 2 * np.pi / k:
            continue
        r = rng.uniform(220.0, 420.0, k)
        c = np.c_[r * np.cos(ang), r * np.sin(ang)]
        u = np.roll(c, -1, 0) - c
        v = c - np.roll(c, 1, 0)
        cosang = -(u * v).sum(1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        interior = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
        if interior.min() >= 75.0 and np.linalg.norm(u, axis=1).min() > 160.0:
            return c - c.min(0)
    raise InputError("could not draw a route polygon for this town seed")  # pragma: no cover


def _layout(rng: np.random.Generator) -> tuple[tuple[float, str], ...]:
    """Every place once plus 2-4 extra stretches, shuffled so that no place follows itself,
    with random lengths (the underpass short)."""
    extra = list(rng.choice(["suburb", "field", "highway", "parking"], int(rng.integers(2, 5))))
    for _ in range(500):
        seq = list(rng.permutation(list(_PLACES) + extra))
        if all(a != b for a, b in zip(seq, seq[1:] + seq[:1], strict=True)):
            break
    else:  # pragma: no cover
        raise InputError("could not order the stretches of this town seed")
    w = np.array([_WEIGHT[p] for p in seq]) * rng.uniform(0.6, 1.4, len(seq))
    frac = w / w.sum()
    frac = np.maximum(frac, 0.04)
    frac /= frac.sum()
    starts = np.r_[0.0, np.cumsum(frac)[:-1]]
    return tuple((float(round(s, 4)), str(p)) for s, p in zip(starts, seq, strict=True))


def random_style(town_seed: int) -> TownStyle:
    """The style of town ``town_seed`` (deterministic): route, layout, widths, sizes, densities,
    slopes, camber, with clutter."""
    if not isinstance(town_seed, int | np.integer) or isinstance(town_seed, bool) or town_seed < 0:
        raise InputError(f"town_seed must be a non-negative integer, got {town_seed!r}")
    rng = np.random.default_rng([int(town_seed), 7919])
    road = {p: (float(round(r * rng.uniform(0.9, 1.3), 2)), float(round(l_ * rng.uniform(0.95, 1.3), 2)))
            for p, (r, l_) in DEFAULT_ROAD.items()}
    lo = float(rng.uniform(1.5, 5.0))
    waves = tuple((float(rng.uniform(0.005, 0.014) * lam / (2 * np.pi)), float(lam),
                   float(rng.uniform(0, 2 * np.pi)), float(rng.uniform(0, 2 * np.pi)))
                  for lam in rng.uniform(300.0, 900.0, 3))
    return TownStyle(
        name=f"town{int(town_seed)}",
        corners=tuple((float(x), float(y)) for x, y in _corners(rng)),
        layout=_layout(rng),
        road=road,
        setback_m=(lo, lo + float(rng.uniform(3.0, 8.0))),
        lot_m=(float(rng.uniform(10.0, 16.0)), float(rng.uniform(18.0, 28.0))),
        house_len_m=(float(rng.uniform(6.0, 9.0)), float(rng.uniform(11.0, 20.0))),
        house_wid_m=(float(rng.uniform(6.0, 9.0)), float(rng.uniform(10.0, 15.0))),
        house_h_m=(float(rng.uniform(2.8, 4.0)), float(rng.uniform(5.5, 11.0))),
        trees_per_lot=int(rng.integers(1, 6)),
        field_tree_every_m=float(rng.uniform(30.0, 150.0)),
        highway_tree_every_m=float(rng.uniform(50.0, 200.0)),
        kerb_occupancy=float(rng.uniform(0.1, 0.7)),
        lot_occupancy=float(rng.uniform(0.2, 0.8)),
        fence_front_p=float(rng.uniform(0.1, 0.9)),
        fence_side_p=float(rng.uniform(0.1, 0.9)),
        lamp_spacing_m=float(rng.uniform(25.0, 50.0)),
        grade_waves=waves,
        camber=float(rng.uniform(0.01, 0.025)),
        clutter=True,
        bush_every_m=float(rng.uniform(8.0, 30.0)),
        sign_every_m=float(rng.uniform(40.0, 120.0)),
        post_every_m=float(rng.uniform(15.0, 60.0)),
        movers_per_scan=float(rng.uniform(1.0, 4.0)),
        legacy=False,
    )


def town_style(town_seed: int | None) -> TownStyle:
    """:data:`LEGACY` for None, else :func:`random_style`."""
    return LEGACY if town_seed is None else random_style(town_seed)
