"""The ``objects`` dataset: ShapeNet-style procedural objects (Zhang et al., ICRA 2025, §IV-A).

The paper attacks ICP on ShapeNetCore models (Chang et al., arXiv 1512.03012). ShapeNet cannot be
downloaded at run time, so this dataset builds stand-ins from Open3D primitives (box, cylinder,
sphere, cone, torus) with random proportions, in 11 categories: ``airplane, bench, bookshelf,
bottle, car, chair, lamp, monitor, mug, sofa, table``. Every category has geometry that pins the
yaw (a backrest, a handle, flat sides, an arm, ...): no object is a surface of revolution about z,
so clean ICP is well posed for all of them. Models stand on z = 0 with z up before normalisation.

Each mesh becomes a sample with :func:`icpbench.datasets.meshes.mesh_sample`: normalised to the
unit sphere (bounding-box centre at the origin, largest 3-D radius 1; optionally the x-y radius),
map = 20,000 area-weighted surface samples with exact face normals, scan = 2,048 independent surface
samples + N(0, 0.025) noise moved by a random ``T_gt`` (±0.08 in x, y; ±10° yaw), ``T_init`` = I.

Pass ``mesh_dir=PATH`` to take the meshes from a folder instead (e.g. ShapeNetCore); this delegates
to :class:`icpbench.datasets.meshes.MeshFolderDataset` (also registered on its own as ``meshes``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import ClassVar

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.core.types import Sample
from icpbench.datasets.base import Dataset, Split
from icpbench.datasets.meshes import MeshFolderDataset, ObjectSampling, mesh_sample

Part = tuple[np.ndarray, np.ndarray]  # vertices (V, 3) float64, triangles (T, 3) int64
_TM = o3d.geometry.TriangleMesh
_RES = 20  # angular resolution of round primitives
_SPLIT_CODE = {"test": 1, "train": 2}


# --------------------------------------------------------------------------------------------
# Primitives (placed copies of Open3D meshes as numpy arrays)
# --------------------------------------------------------------------------------------------
def _arrays(mesh: o3d.geometry.TriangleMesh) -> Part:
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)


def _rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def _align_z(d: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) taking +z to the unit direction of ``d``."""
    d = np.asarray(d, dtype=np.float64) / np.linalg.norm(d)
    axis = np.cross([0.0, 0.0, 1.0], d)
    s, c = np.linalg.norm(axis), d[2]
    if s < 1e-12:
        return np.eye(3) if c > 0 else _rot("x", 180.0)
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()


def _place(part: Part, R: np.ndarray | None, t: Sequence[float]) -> Part:
    V, F = part
    if R is not None:
        V = V @ R.T
    return V + np.asarray(t, dtype=np.float64), F


def box(size: Sequence[float], center: Sequence[float], R: np.ndarray | None = None) -> Part:
    """Box of edge lengths ``size`` (x, y, z) centred at ``center``, rotated by ``R`` about it."""
    V, F = _arrays(_TM.create_box(*size))
    return _place((V - 0.5 * np.asarray(size), F), R, center)


def rod(p0: Sequence[float], p1: Sequence[float], radius: float) -> Part:
    """Closed cylinder of ``radius`` from point ``p0`` to point ``p1``."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    part = _arrays(_TM.create_cylinder(radius, float(np.linalg.norm(p1 - p0)), _RES, 1))
    return _place(part, _align_z(p1 - p0), 0.5 * (p0 + p1))


def disc(radius: float, height: float, center: Sequence[float]) -> Part:
    """Vertical closed cylinder (axis z) centred at ``center``."""
    return _place(_arrays(_TM.create_cylinder(radius, height, _RES, 1)), None, center)


def sphere(radius: float, center: Sequence[float]) -> Part:
    return _place(_arrays(_TM.create_sphere(radius, _RES // 2)), None, center)


def cone(radius: float, height: float, base: Sequence[float], direction: Sequence[float]) -> Part:
    """Closed cone with its base disc centred at ``base`` and its tip ``height`` along ``direction``."""
    return _place(_arrays(_TM.create_cone(radius, height, _RES, 1)), _align_z(direction), base)


def torus(major: float, minor: float, center: Sequence[float], R: np.ndarray | None = None) -> Part:
    """Torus (ring in the local x-y plane) centred at ``center``."""
    return _place(_arrays(_TM.create_torus(major, minor, _RES, _RES // 2)), R, center)


def merge(parts: Sequence[Part]) -> Part:
    """Concatenate parts into one mesh (no boolean union; overlaps stay as in CAD models)."""
    Vs, Fs, off = [], [], 0
    for V, F in parts:
        Vs.append(V)
        Fs.append(F + off)
        off += len(V)
    return np.vstack(Vs), np.vstack(Fs)


# --------------------------------------------------------------------------------------------
# Categories: each builder maps a Generator to the parts of one object (metres, z up, +y = back)
# --------------------------------------------------------------------------------------------
def _legs(g: np.random.Generator, w: float, d: float, h: float, inset: float) -> list[Part]:
    """Four legs from z=0 to z=h under a w x d top, square or round."""
    lt = g.uniform(0.025, 0.05)
    square = g.random() < 0.5
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - lt / 2 - inset), sy * (d / 2 - lt / 2 - inset)
            out.append(box((lt, lt, h), (x, y, h / 2)) if square else rod((x, y, 0), (x, y, h), lt / 2))
    return out


def chair(g: np.random.Generator) -> list[Part]:
    w, d, h, t = g.uniform(0.4, 0.6), g.uniform(0.38, 0.55), g.uniform(0.4, 0.5), g.uniform(0.03, 0.07)
    parts = [box((w, d, t), (0, 0, h - t / 2))]
    parts += _legs(g, w, d, h - t, g.uniform(0.0, 0.04))
    bh, bt, tilt = g.uniform(0.3, 0.6), g.uniform(0.02, 0.05), g.uniform(0.0, 15.0)
    parts.append(_place(box((w, bt, bh), (0, 0, bh / 2)), _rot("x", -tilt), (0, d / 2 - bt / 2, h)))
    if g.random() < 0.4:  # armrests on posts
        ah, at = g.uniform(0.18, 0.25), g.uniform(0.03, 0.06)
        for sx in (-1, 1):
            x = sx * (w / 2 - at / 2)
            parts.append(box((at, d * 0.9, at), (x, 0, h + ah)))
            parts.append(rod((x, -d * 0.35, h), (x, -d * 0.35, h + ah), at / 3))
    return parts


def table(g: np.random.Generator) -> list[Part]:
    w, h, t = g.uniform(0.8, 1.6), g.uniform(0.6, 0.8), g.uniform(0.03, 0.06)
    d = w * g.uniform(0.45, 0.85)
    parts = [box((w, d, t), (0, 0, h - t / 2))]
    inset = g.uniform(0.02, 0.1)
    parts += _legs(g, w, d, h - t, inset)
    if g.random() < 0.5:  # apron under the top
        ah = g.uniform(0.06, 0.12)
        for s in (-1, 1):
            parts.append(box((w - 2 * inset, 0.02, ah), (0, s * (d / 2 - inset - 0.04), h - t - ah / 2)))
            parts.append(box((0.02, d - 2 * inset, ah), (s * (w / 2 - inset - 0.04), 0, h - t - ah / 2)))
    if g.random() < 0.4:  # lower shelf
        parts.append(box((w - 2 * inset - 0.06, d - 2 * inset - 0.06, t * 0.7), (0, 0, g.uniform(0.12, 0.3))))
    return parts


def lamp(g: np.random.Generator) -> list[Part]:
    """Desk lamp: base, two tilted arms with joints, a cone shade at the end."""
    hb, ar = g.uniform(0.02, 0.05), g.uniform(0.008, 0.015)
    if g.random() < 0.5:
        parts = [disc(g.uniform(0.08, 0.15), hb, (0, 0, hb / 2))]
    else:
        parts = [box((g.uniform(0.15, 0.3), g.uniform(0.12, 0.22), hb), (0, 0, hb / 2))]
    a1, a2, a3 = np.radians(g.uniform(10, 35)), np.radians(g.uniform(50, 110)), np.radians(g.uniform(10, 50))
    j0 = np.array([0.0, 0.0, hb])
    j1 = j0 + g.uniform(0.3, 0.5) * np.array([-np.sin(a1), 0.0, np.cos(a1)])
    j2 = j1 + g.uniform(0.25, 0.45) * np.array([np.sin(a2), 0.0, np.cos(a2)])
    parts += [rod(j0, j1, ar), rod(j1, j2, ar), sphere(ar * 2.0, j1), sphere(ar * 1.6, j0)]
    rs, hs = g.uniform(0.06, 0.12), g.uniform(0.08, 0.15)
    s = np.array([np.sin(a3), 0.0, -np.cos(a3)])  # from the tip towards the opening
    parts.append(cone(rs, hs, j2 + hs * s, -s))
    return parts


def mug(g: np.random.Generator) -> list[Part]:
    r, hgt = g.uniform(0.035, 0.06), g.uniform(0.07, 0.12)
    rt = hgt * g.uniform(0.25, 0.4)
    parts = [disc(r, hgt, (0, 0, hgt / 2))]
    centre = (r + rt * g.uniform(0.3, 0.6), 0, hgt * g.uniform(0.45, 0.6))
    parts.append(torus(rt, rt * g.uniform(0.12, 0.25), centre, _rot("x", 90.0)))
    return parts


def car(g: np.random.Generator) -> list[Part]:
    L, W, H = g.uniform(3.6, 5.0), g.uniform(1.6, 2.0), g.uniform(0.45, 0.7)
    r, ww, c = g.uniform(0.28, 0.38), g.uniform(0.2, 0.3), g.uniform(0.1, 0.2)
    parts = [box((L, W, H), (0, 0, c + H / 2))]
    cl, cw, ch = L * g.uniform(0.35, 0.55), W * g.uniform(0.8, 0.92), g.uniform(0.4, 0.6)
    parts.append(box((cl, cw, ch), (-L * g.uniform(0.0, 0.15), 0, c + H + ch / 2)))
    xw = L * g.uniform(0.3, 0.36)
    for sx in (-1, 1):
        for sy in (-1, 1):
            y = sy * (W / 2 - ww / 2 + 0.05)
            parts.append(rod((sx * xw, y - ww / 2, r), (sx * xw, y + ww / 2, r), r))
    if g.random() < 0.3:  # rear spoiler
        parts.append(box((0.25, W * 0.9, 0.04), (-L / 2 + 0.15, 0, c + H + 0.2)))
    return parts


def airplane(g: np.random.Generator) -> list[Part]:
    Lf = g.uniform(3.0, 5.0)
    rf = Lf * g.uniform(0.05, 0.08)
    nose, tail = Lf * g.uniform(0.08, 0.15), Lf * g.uniform(0.1, 0.2)
    parts = [rod((-Lf / 2, 0, 0), (Lf / 2, 0, 0), rf),
             cone(rf, nose, (Lf / 2, 0, 0), (1, 0, 0)), cone(rf, tail, (-Lf / 2, 0, 0), (-1, 0, 0))]
    span, chord, tw = Lf * g.uniform(0.8, 1.3), Lf * g.uniform(0.12, 0.22), Lf * 0.015
    sweep, xw, zw = g.uniform(0.0, 30.0), Lf * g.uniform(-0.1, 0.15), rf * g.uniform(-0.5, 0.3)
    for sy in (-1, 1):
        half = box((chord, span / 2, tw), (0, sy * span / 4, 0))
        parts.append(_place(half, _rot("z", -sy * sweep), (xw, 0, zw)))
    ct, ht = Lf * g.uniform(0.1, 0.16), Lf * g.uniform(0.12, 0.22)
    parts.append(box((ct, tw, ht), (-Lf / 2 + ct / 2, 0, rf * 0.8 + ht / 2)))
    parts.append(box((ct, Lf * g.uniform(0.25, 0.4), tw), (-Lf / 2 + ct / 2, 0, rf * 0.3)))
    if g.random() < 0.5:  # two engines under the wings
        re, le = rf * g.uniform(0.4, 0.6), chord * g.uniform(0.6, 0.9)
        for sy in (-1, 1):
            y = sy * span * 0.2
            x = xw - abs(y) * np.tan(np.radians(sweep)) + chord * 0.3
            parts.append(rod((x - le, y, zw - tw / 2 - re), (x, y, zw - tw / 2 - re), re))
    return parts


def bottle(g: np.random.Generator) -> list[Part]:
    """Flask with a rectangular body (flat sides), a round shoulder, neck and cap."""
    w, hb = g.uniform(0.06, 0.1), g.uniform(0.15, 0.25)
    dep = w * g.uniform(0.5, 0.85)
    sh, rn, hn = g.uniform(0.02, 0.05), g.uniform(0.012, 0.018), g.uniform(0.03, 0.07)
    hc = g.uniform(0.01, 0.02)
    return [box((w, dep, hb), (0, 0, hb / 2)), cone(dep / 2, sh, (0, 0, hb), (0, 0, 1)),
            disc(rn, hn, (0, 0, hb + sh * 0.5 + hn / 2)),
            disc(rn * 1.25, hc, (0, 0, hb + sh * 0.5 + hn + hc / 2))]


def bench(g: np.random.Generator) -> list[Part]:
    L, d, h, t = g.uniform(1.0, 2.0), g.uniform(0.3, 0.5), g.uniform(0.4, 0.5), g.uniform(0.03, 0.06)
    n = int(g.integers(1, 5))  # 1 slab or 2-4 slats
    gap = 0.0 if n == 1 else g.uniform(0.01, 0.03)
    sw = (d - gap * (n - 1)) / n
    parts = [box((L, sw, t), (0, -d / 2 + sw / 2 + k * (sw + gap), h - t / 2)) for k in range(n)]
    xs = L / 2 - g.uniform(0.05, 0.2)
    if g.random() < 0.5:  # side panels
        pt = g.uniform(0.03, 0.06)
        parts += [box((pt, d * 0.9, h - t), (sx * xs, 0, (h - t) / 2)) for sx in (-1, 1)]
    else:
        parts += _legs(g, 2 * xs, d, h - t, 0.0)
    if g.random() < 0.5:  # backrest on two posts
        bh = g.uniform(0.25, 0.45)
        parts.append(box((L, 0.03, bh * 0.6), (0, d / 2, h + bh * 0.7)))
        parts += [rod((sx * xs, d / 2, h), (sx * xs, d / 2, h + bh), 0.02) for sx in (-1, 1)]
    return parts


def sofa(g: np.random.Generator) -> list[Part]:
    W, D, hb = g.uniform(1.4, 2.4), g.uniform(0.75, 1.0), g.uniform(0.2, 0.35)
    at, ah, bt, bh = g.uniform(0.1, 0.25), g.uniform(0.15, 0.3), g.uniform(0.15, 0.25), g.uniform(0.35, 0.55)
    ch = g.uniform(0.08, 0.15)
    parts = [box((W, D, hb), (0, 0, hb / 2)),
             box((W, bt, bh + ch), (0, D / 2 - bt / 2, hb + (bh + ch) / 2))]
    parts += [box((at, D, ch + ah), (sx * (W / 2 - at / 2), 0, hb + (ch + ah) / 2)) for sx in (-1, 1)]
    n = int(g.integers(1, 4))
    wi = W - 2 * at
    cw = (wi - 0.01 * (n - 1)) / n
    for k in range(n):
        parts.append(box((cw, D - bt, ch), (-wi / 2 + cw / 2 + k * (cw + 0.01), -bt / 2, hb + ch / 2)))
    if g.random() < 0.25:  # chaise: an L-shaped sectional
        cl = g.uniform(0.5, 0.8)
        parts.append(box((wi / n, cl, hb + ch), (-wi / 2 + wi / n / 2, -D / 2 - cl / 2, (hb + ch) / 2)))
    return parts


def bookshelf(g: np.random.Generator) -> list[Part]:
    W, D, H, pt = g.uniform(0.6, 1.2), g.uniform(0.25, 0.4), g.uniform(0.8, 2.0), g.uniform(0.015, 0.03)
    parts = [box((pt, D, H), (sx * (W / 2 - pt / 2), 0, H / 2)) for sx in (-1, 1)]
    parts.append(box((W, pt / 2, H), (0, D / 2 - pt / 4, H / 2)))  # back panel
    n = int(g.integers(2, 7))
    zs = np.linspace(pt / 2, H - pt / 2, n + 2)
    zs[1:-1] += g.uniform(-0.3, 0.3, n) * (H / (n + 1)) * 0.5
    parts += [box((W - 2 * pt, D, pt), (0, 0, z)) for z in zs]
    return parts


def monitor(g: np.random.Generator) -> list[Part]:
    sw = g.uniform(0.45, 0.75)
    sh, st, hs = sw * g.uniform(0.5, 0.65), g.uniform(0.015, 0.05), g.uniform(0.08, 0.2)
    tilt = g.uniform(-10.0, 10.0)
    parts = [_place(box((sw, st, sh), (0, 0, sh / 2)), _rot("x", tilt), (0, 0, hs))]
    nw, nd = g.uniform(0.04, 0.08), g.uniform(0.02, 0.04)
    parts.append(box((nw, nd, hs + sh * 0.4), (0, st / 2 + nd / 2, (hs + sh * 0.4) / 2)))
    if g.random() < 0.5:
        parts.append(box((g.uniform(0.2, 0.3), g.uniform(0.15, 0.22), 0.015), (0, 0.03, 0.0075)))
    else:
        parts.append(box((g.uniform(0.12, 0.2), g.uniform(0.12, 0.2), 0.015), (0, 0.04, 0.0075),
                         _rot("z", 45.0)))
    return parts


#: Category name -> builder.
CATEGORIES: dict[str, Callable[[np.random.Generator], list[Part]]] = {
    "airplane": airplane, "bench": bench, "bookshelf": bookshelf, "bottle": bottle, "car": car,
    "chair": chair, "lamp": lamp, "monitor": monitor, "mug": mug, "sofa": sofa, "table": table,
}


def build_object(category: str, rng: np.random.Generator) -> Part:
    """One random object of ``category`` as (vertices (V, 3), triangles (T, 3)), metres, z up.

    Raises:
        InputError: unknown category.
    """
    if category not in CATEGORIES:
        raise InputError(f"unknown object category {category!r}; valid: {', '.join(CATEGORIES)}")
    return merge(CATEGORIES[category](rng))


# --------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------
class ObjectsDataset(Dataset):
    """Procedural ShapeNet-style objects (or a mesh folder), one registration problem each.

    Sample ``i`` of a split has category ``categories[i % len(categories)]`` (balanced) and random
    proportions; all its randomness comes from ``(seed, split, i)``, so train and test objects are
    different objects and every sample can be generated alone. Ids: ``objects/<split>/<category>/<i:06d>``;
    ``meta`` holds ``category``, ``split`` and ``index``. Split ``"all"`` is the test samples
    followed by the train samples.

    Args:
        seed: random seed.
        split: ``"test"``, ``"train"`` or ``"all"``.
        n_samples: samples per split (default 200 for test, 1000 for train).
        categories: subset of :data:`CATEGORIES` (names, or one comma-separated string).
        mesh_dir: take the meshes from this folder instead (delegates to
            :class:`~icpbench.datasets.meshes.MeshFolderDataset` with ids ``objects/<model id>``;
            ``categories`` is then ignored, ``n_samples`` caps the split, default all).
        test_fraction: with ``mesh_dir``: share of models in the test split.
        n_map_points, n_scan_points, noise_std, max_trans, max_yaw_deg, radius: see
            :class:`~icpbench.datasets.meshes.ObjectSampling` (paper defaults).
    """

    name: ClassVar[str] = "objects"
    param_ranges: ClassVar[dict[str, Range]] = {
        "n_samples": Range(0, 10_000_000), "test_fraction": Range(0.0, 1.0),
        "n_map_points": Range(6, 100_000_000), "n_scan_points": Range(6, 100_000_000),
        "noise_std": Range(0.0, 1e3), "max_trans": Range(0.0, 1e3), "max_yaw_deg": Range(0.0, 180.0)}
    description: ClassVar[str] = (
        "ShapeNet-style procedural objects in 11 categories (or a mesh folder), paper §IV-A"
    )
    icp_preset: ClassVar[str] = "objects"
    default_budgets: ClassVar[tuple[float, ...]] = (0.02, 0.05)
    DEFAULT_N: ClassVar[dict[str, int]] = {"test": 200, "train": 1000}

    def __init__(self, *, seed: int = 0, split: Split = "test", n_samples: int | None = None,
                 categories: Sequence[str] | str | None = None, mesh_dir: str | None = None,
                 test_fraction: float = 0.2, n_map_points: int = 20_000, n_scan_points: int = 2_048,
                 noise_std: float = 0.025, max_trans: float = 0.08, max_yaw_deg: float = 10.0,
                 radius: str = "3d") -> None:
        self.sampling = ObjectSampling.from_params(
            n_map_points=n_map_points, n_scan_points=n_scan_points, noise_std=noise_std,
            max_trans=max_trans, max_yaw_deg=max_yaw_deg, radius=radius)
        self._folder: MeshFolderDataset | None = None
        if mesh_dir is not None:
            self._folder = MeshFolderDataset(mesh_dir, seed=seed, split=split, test_fraction=test_fraction,
                                             n_samples=n_samples, id_prefix="objects",
                                             **self.sampling.as_dict())
            super().__init__(seed=seed, split=split, mesh_dir=str(mesh_dir), n_samples=n_samples,
                             test_fraction=float(test_fraction), **self.sampling.as_dict())
            return
        if isinstance(categories, str):
            categories = [c.strip() for c in categories.split(",") if c.strip()]
        cats = sorted(CATEGORIES) if categories is None else list(categories)
        unknown = [c for c in cats if c not in CATEGORIES]
        if unknown or not cats:
            raise InputError(f"unknown object categories {unknown or cats}; valid: {', '.join(CATEGORIES)}")
        self.categories = cats
        try:
            n = None if n_samples in (None, "", "None") else int(n_samples)
        except (TypeError, ValueError) as exc:
            raise InputError(f"n_samples must be an integer, got {n_samples!r}") from exc
        if n is not None and n < 0:
            raise InputError(f"n_samples must be >= 0, got {n}")
        self.n_per_split = {s: (self.DEFAULT_N[s] if n is None else n) for s in ("test", "train")}
        super().__init__(seed=seed, split=split, n_samples=n, categories=cats,
                         **self.sampling.as_dict())

    def _locate(self, i: int) -> tuple[str, int]:
        """(split, index within that split) of position ``i``."""
        if self.split != "all":
            return self.split, i
        n_test = self.n_per_split["test"]
        return ("test", i) if i < n_test else ("train", i - n_test)

    def __len__(self) -> int:
        if self._folder is not None:
            return len(self._folder)
        if self.split == "all":
            return self.n_per_split["test"] + self.n_per_split["train"]
        return self.n_per_split[self.split]

    def __getitem__(self, i: int) -> Sample:
        if self._folder is not None:
            return self._folder[i]
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"index {i} out of range for {n} samples")
        split, j = self._locate(i % n)
        category = self.categories[j % len(self.categories)]
        entropy = [self.seed, _SPLIT_CODE[split], j]
        shape_rng = np.random.default_rng(np.random.SeedSequence([*entropy, 0]))
        V, F = build_object(category, shape_rng)
        return mesh_sample(V, F, sample_id=f"objects/{split}/{category}/{j:06d}", seed=[*entropy, 1],
                           sampling=self.sampling,
                           meta={"category": category, "split": split, "index": j})
