"""Triangle-mesh utilities and the ``meshes`` dataset: any folder of OBJ/OFF/PLY/STL meshes.

Zhang et al. (ICRA 2025, §IV-A) build their object samples from ShapeNetCore meshes (Chang et al.,
arXiv 1512.03012). :func:`mesh_sample` turns one triangle mesh into a :class:`~icpbench.core.types.Sample`
the way the paper describes, and is shared by :mod:`icpbench.datasets.objects` (procedural meshes)
and :class:`MeshFolderDataset` (meshes read from disk):

1. **Normalise** (:func:`normalize_vertices`): centre the axis-aligned bounding box of the mesh at the
   origin and scale so that the largest *3-D* distance of a surface point from the origin is 1, i.e.
   the object fits in the unit sphere and hence in the paper's "unit circle centred at the origin"
   (``radius="xy"`` scales by the largest horizontal distance instead, so only the x-y footprint fits
   the unit circle). Units afterwards are "object radii" (scene scale 1).
2. **Map** Q: ``n_map_points`` (default 20,000) area-weighted uniform surface samples with the exact
   unit normals of the faces they lie on (orientation from the triangle winding).
3. **Scan**: ``n_scan_points`` (default 2,048) *independent* surface samples plus isotropic Gaussian
   noise N(0, ``noise_std``) (default 0.025) on every coordinate.
4. **Pose**: ``T_gt`` (scan->map) has a uniform translation in [-``max_trans``, ``max_trans``] along x
   and y (default 0.08) and a uniform yaw in [-``max_yaw_deg``, ``max_yaw_deg``] (default 10°);
   the scan is stored in the sensor frame, ``scan = inv(T_gt) (samples + noise)``; ``T_init`` is
   the identity.

Surface sampling is NumPy area-weighted barycentric sampling driven by ``np.random.default_rng``
(deterministic, and it yields the exact face normals), not Open3D's sampler.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.core.types import Sample
from icpbench.datasets.base import Dataset, Split
from icpbench.datasets.synthetic_scene import random_transform

#: File suffixes read as meshes (case-insensitive).
MESH_SUFFIXES: tuple[str, ...] = (".obj", ".off", ".ply", ".stl")
#: File stems that name a model by its folder (ShapeNetCore v1 ``model.obj``, v2
#: ``models/model_normalized.obj``).
GENERIC_STEMS: frozenset[str] = frozenset({"model", "model_normalized", "model_watertight"})

Radius = Literal["3d", "xy"]


# --------------------------------------------------------------------------------------------
# Sampling configuration
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ObjectSampling:
    """How a mesh becomes a sample (paper §IV-A defaults).

    Attributes:
        n_map_points: M, map surface samples.
        n_scan_points: N, scan surface samples.
        noise_std: standard deviation of the scan noise per coordinate (normalised units).
        max_trans: translation of ``T_gt`` is uniform in [-max_trans, max_trans] along x and y.
        max_yaw_deg: yaw of ``T_gt`` is uniform in [-max_yaw_deg, max_yaw_deg] degrees.
        radius: ``"3d"`` (fit in the unit sphere) or ``"xy"`` (fit the footprint in the unit circle).
    """

    n_map_points: int = 20_000
    n_scan_points: int = 2_048
    noise_std: float = 0.025
    max_trans: float = 0.08
    max_yaw_deg: float = 10.0
    radius: Radius = "3d"

    def __post_init__(self) -> None:
        for name in ("n_map_points", "n_scan_points"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 6:
                raise InputError(f"{name} must be an integer >= 6, got {v!r}")
        for name in ("noise_std", "max_trans", "max_yaw_deg"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be a finite number >= 0, got {v!r}")
        if self.max_yaw_deg > 180:
            raise InputError(f"max_yaw_deg must be <= 180, got {self.max_yaw_deg}")
        if self.radius not in ("3d", "xy"):
            raise InputError(f"radius must be '3d' or 'xy', got {self.radius!r}")

    @classmethod
    def from_params(cls, **kw: Any) -> ObjectSampling:
        """Build from keyword arguments, coercing numeric strings (CLI ``key=value`` pairs)."""
        try:
            for name in ("n_map_points", "n_scan_points"):
                if name in kw:
                    kw[name] = int(kw[name])
            for name in ("noise_std", "max_trans", "max_yaw_deg"):
                if name in kw:
                    kw[name] = float(kw[name])
        except (TypeError, ValueError) as exc:
            raise InputError(f"bad sampling parameter: {exc}") from exc
        return cls(**kw)

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (for manifests)."""
        return asdict(self)


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------
def triangle_areas_normals(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Areas (T,) and unit normals (T, 3) of the triangles (degenerate ones get a zero normal).

    Args:
        vertices: (V, 3) float vertex positions.
        triangles: (T, 3) integer vertex indices; normals follow the right-hand rule of the winding.
    """
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    norm = np.linalg.norm(cross, axis=1)
    normals = np.zeros_like(cross)
    ok = norm > 0
    normals[ok] = cross[ok] / norm[ok, None]
    return 0.5 * norm, normals


def normalize_vertices(vertices: np.ndarray, triangles: np.ndarray, radius: Radius = "3d") -> np.ndarray:
    """Centre the bounding box of the used vertices at the origin and scale to unit radius.

    Args:
        vertices: (V, 3) vertex positions (any unit).
        triangles: (T, 3) vertex indices; vertices no triangle uses are ignored for the centre
            and the scale.
        radius: ``"3d"``: the largest Euclidean distance of a vertex from the origin becomes 1
            (every surface point then lies in the unit sphere, since a triangle's farthest point
            from the origin is one of its vertices); ``"xy"``: the largest horizontal distance
            becomes 1 (z may exceed 1).

    Returns:
        (V, 3) float64 normalised vertices.

    Raises:
        InputError: all used vertices coincide (nothing to scale).
    """
    V = np.asarray(vertices, dtype=np.float64)
    used = V[np.unique(triangles)]
    centre = 0.5 * (used.min(axis=0) + used.max(axis=0))
    d = used - centre
    r = np.linalg.norm(d if radius == "3d" else d[:, :2], axis=1).max()
    if not r > 0:
        raise InputError(f"cannot normalise a mesh whose {radius} extent is zero")
    return (V - centre) / r


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, n: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` uniform (area-weighted) surface samples with the unit normals of their faces.

    Each sample picks a triangle with probability proportional to its area, then a uniform point
    in it from two uniform numbers (reflected into the triangle when ``u + v > 1``).

    Args:
        vertices: (V, 3) vertex positions.
        triangles: (T, 3) vertex indices.
        n: number of samples.
        rng: the only source of randomness.

    Returns:
        points (n, 3) float64 and normals (n, 3) float64 (unit length).

    Raises:
        InputError: the mesh has zero total area.
    """
    V = np.asarray(vertices, dtype=np.float64)
    areas, normals = triangle_areas_normals(V, triangles)
    total = areas.sum()
    if not (np.isfinite(total) and total > 0):
        raise InputError("mesh has zero surface area (all triangles are degenerate)")
    face = rng.choice(len(areas), size=n, p=areas / total)
    uv = rng.random((n, 2))
    flip = uv.sum(axis=1) > 1.0
    uv[flip] = 1.0 - uv[flip]
    tri = triangles[face]
    a = V[tri[:, 0]]
    pts = a + uv[:, :1] * (V[tri[:, 1]] - a) + uv[:, 1:] * (V[tri[:, 2]] - a)
    return pts, normals[face]


def mesh_sample(vertices: np.ndarray, triangles: np.ndarray, *, sample_id: str,
                seed: Sequence[int] | int, sampling: ObjectSampling = ObjectSampling(),
                meta: Mapping[str, Any] | None = None, normalized: bool = False) -> Sample:
    """Turn a triangle mesh into a registration problem (paper §IV-A; see the module docstring).

    Args:
        vertices: (V, 3) vertex positions (any unit unless ``normalized``).
        triangles: (T, 3) vertex indices.
        sample_id: the sample's id.
        seed: entropy of ``np.random.SeedSequence``; three independent streams are spawned from
            it for the map samples, the scan samples and noise, and the pose.
        sampling: sizes, noise and pose ranges.
        meta: extra metadata (e.g. ``category``); ``radius`` and ``seed`` are added.
        normalized: skip normalisation (vertices already fit the unit sphere/circle).

    Returns:
        Sample with scan (N, 3) float32 in the sensor frame, map (M, 3) float32 and unit
        map_normals (M, 3) float32 in the normalised object frame, T_gt (4, 4) float64
        (scan->map: planar translation and yaw), T_init = identity.
    """
    F = np.asarray(triangles, dtype=np.int64)
    V = np.asarray(vertices, dtype=np.float64) if normalized else normalize_vertices(
        vertices, F, sampling.radius)
    ss = np.random.SeedSequence(seed)
    rng_map, rng_scan, rng_pose = (np.random.default_rng(s) for s in ss.spawn(3))
    map_pts, map_nrm = sample_surface(V, F, sampling.n_map_points, rng_map)
    world, _ = sample_surface(V, F, sampling.n_scan_points, rng_scan)
    if sampling.noise_std > 0:
        world = world + rng_scan.normal(0.0, sampling.noise_std, world.shape)
    T_gt = random_transform(rng_pose, sampling.max_trans, sampling.max_yaw_deg, yaw_only=True)
    R, t = T_gt[:3, :3], T_gt[:3, 3]
    scan = (world - t) @ R  # inv(T_gt) applied to map-frame points: R^T (x - t)
    info = {**(meta or {}), "radius": sampling.radius,
            "seed": list(seed) if not isinstance(seed, int) else seed}
    return Sample(id=sample_id, scan=scan.astype(np.float32), map=map_pts.astype(np.float32),
                  map_normals=map_nrm.astype(np.float32), T_gt=T_gt, T_init=np.eye(4), meta=info)


# --------------------------------------------------------------------------------------------
# Reading meshes
# --------------------------------------------------------------------------------------------
def _read_head_tail(path: Path, n_head: int = 65_536, n_tail: int = 4096) -> tuple[bytes, bytes, int]:
    """First ``n_head`` and last ``n_tail`` bytes of a file, and its size."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(n_head)
        f.seek(max(size - n_tail, 0))
        tail = f.read(n_tail)
    return head, tail, size


def _declared_counts(path: Path) -> tuple[int | None, int | None, str]:
    """(vertices, faces) that a mesh file's header declares (None where the format declares
    none) and a non-empty reason when the file is structurally incomplete.

    Only the first 64 kB and the last 4 kB are read: OFF and PLY headers give the counts, a binary STL's
    size must be 84 + 50 bytes per declared triangle, an ASCII STL must end with ``endsolid``,
    and an OBJ's last ``v``/``f`` line must be complete (OBJ declares no counts).
    """
    head, tail, size = _read_head_tail(path)
    suffix = path.suffix.lower()
    if suffix == ".off":
        tokens: list[str] = []
        for line in head.decode("latin-1").splitlines():
            tokens.extend(line.split("#", 1)[0].split())
            if len(tokens) >= 4:
                break
        if not tokens or not tokens[0].upper().endswith("OFF"):
            return None, None, "it does not start with an OFF keyword"
        try:
            return int(tokens[1]), int(tokens[2]), ""
        except (IndexError, ValueError):
            return None, None, "the OFF header has no 'n_vertices n_faces n_edges' line"
    if suffix == ".ply":
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            return None, None, "no valid PLY header (expected 'ply' ... 'end_header')"
        header = head[:end].decode("latin-1")
        nv = re.search(r"^element\s+vertex\s+(\d+)", header, re.M)
        nf = re.search(r"^element\s+face\s+(\d+)", header, re.M)
        return (int(nv.group(1)) if nv else None), (int(nf.group(1)) if nf else None), ""
    if suffix == ".stl":
        if size >= 84:
            n = int(np.frombuffer(head[80:84], dtype="<u4")[0])
            if size == 84 + 50 * n:  # binary STL
                return None, n, ""
        if head.lstrip()[:5].lower() == b"solid":
            if b"endsolid" not in tail.lower():
                return None, None, "ASCII STL without a final 'endsolid' line (cut short)"
            return None, None, ""
        return None, None, ("neither an ASCII STL nor a binary STL of the size its header "
                            "declares (84 + 50 bytes per triangle)")
    if suffix == ".obj":
        last = tail.rstrip(b"\r\n\t ").rsplit(b"\n", 1)[-1].split(b"#", 1)[0].split()
        if last and last[0] in (b"v", b"f") and len(last) < 4:
            return None, None, f"its last line {b' '.join(last).decode('latin-1')!r} is cut short"
    return None, None, ""


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh with Open3D and check that it was read completely.

    Open3D returns an empty or partial mesh (with only a log warning) for missing, empty,
    truncated or corrupt files; this function detects those cases: no triangles, fewer vertices
    or faces than an OFF/PLY header or a binary STL size declares, an OBJ whose last line is cut,
    non-finite vertices or out-of-range indices.

    Args:
        path: an ``.obj``, ``.off``, ``.ply`` or ``.stl`` file (polygons are triangulated).

    Returns:
        vertices (V, 3) float64 and triangles (T, 3) int64, in the file's units and axes.

    Raises:
        InputError: naming the file and the problem.
    """
    import open3d as o3d

    p = Path(path)
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{p}: unsupported mesh format {p.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    if not p.is_file():
        raise InputError(f"mesh file {p} does not exist")
    if p.stat().st_size == 0:
        raise InputError(f"mesh file {p} is empty (0 bytes)")
    n_vert_decl, n_face_decl, problem = _declared_counts(p)
    if problem:
        raise InputError(f"mesh file {p} is truncated or corrupt: {problem}")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(p), enable_post_processing=False, print_progress=False)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.triangles, dtype=np.int64)
    if len(F) == 0:
        raise InputError(f"mesh file {p} gave no triangles: it is empty, truncated, corrupt or a "
                         "point cloud (Open3D could not read a triangle mesh from it)")
    if n_vert_decl is not None and len(V) != n_vert_decl:
        raise InputError(f"mesh file {p} is truncated or corrupt: its header declares "
                         f"{n_vert_decl} vertices but {len(V)} were read")
    if n_face_decl is not None and len(F) < n_face_decl:
        raise InputError(f"mesh file {p} is truncated or corrupt: its header declares "
                         f"{n_face_decl} faces but only {len(F)} triangles were read")
    if not np.all(np.isfinite(V)):
        raise InputError(f"mesh file {p} has NaN or Inf vertex coordinates")
    if F.min() < 0 or F.max() >= len(V):
        raise InputError(f"mesh file {p} has face indices outside its {len(V)} vertices")
    return V, F


@lru_cache(maxsize=64)
def _read_cached(path: str, mtime_ns: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    V, F = read_mesh(path)
    V.setflags(write=False)
    F.setflags(write=False)
    return V, F


def find_mesh_files(root: str | Path) -> list[Path]:
    """All mesh files under ``root`` (recursive, symlinks followed), sorted by relative path.

    Raises:
        InputError: ``root`` is missing or not a folder, or holds no mesh file.
    """
    r = Path(root).expanduser()
    if not r.exists():
        raise InputError(f"mesh folder {r} does not exist")
    if not r.is_dir():
        raise InputError(f"{r} is not a folder (give a folder of {'/'.join(MESH_SUFFIXES)} files)")
    files = sorted((p for p in r.rglob("*") if p.suffix.lower() in MESH_SUFFIXES and p.is_file()),
                   key=lambda p: p.relative_to(r).as_posix())
    if not files:
        raise InputError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) found under {r}")
    return files


def model_key(root: Path, path: Path) -> str:
    """Stable model id of ``path`` relative to ``root`` (POSIX, no suffix).

    ShapeNetCore layouts collapse to ``<synset>/<model_id>``: a generic file name
    (``model.obj``, ``model_normalized.obj``) is dropped together with a ``models`` folder.
    """
    parts = list(path.relative_to(root).with_suffix("").parts)
    if len(parts) > 1 and parts[-1].lower() in GENERIC_STEMS:
        parts.pop()
        if len(parts) > 1 and parts[-1].lower() == "models":
            parts.pop()
    return "/".join(parts)


def split_of(key: str, test_fraction: float) -> Literal["train", "test"]:
    """Deterministic split of a model id: ``test`` when the first 8 bytes of SHA-1(key), read as
    a fraction of 2^64, fall below ``test_fraction``."""
    h = int.from_bytes(hashlib.sha1(key.encode("utf-8")).digest()[:8], "big")
    return "test" if h / 2.0**64 < test_fraction else "train"


def _key_seed(key: str) -> int:
    """A 63-bit integer from a model id (for per-model random streams)."""
    return int.from_bytes(hashlib.sha1(b"sample:" + key.encode("utf-8")).digest()[:8], "big") >> 1


def _y_up_to_z_up(V: np.ndarray) -> np.ndarray:
    """Rotate +90° about x: (x, y, z) -> (x, -z, y), so a y-up model stands on z."""
    return np.c_[V[:, 0], -V[:, 2], V[:, 1]]


@dataclass(frozen=True)
class MeshEntry:
    """One mesh file of a folder: its path, model id, category and split."""

    path: Path
    key: str
    category: str
    split: Literal["train", "test"]


class MeshFolderDataset(Dataset):
    """Samples from a folder of triangle meshes (OBJ/OFF/PLY/STL, searched recursively).

    Works on a plain folder and on ShapeNetCore (v1 ``<synset>/<model_id>/model.obj``, v2
    ``<synset>/<model_id>/models/model_normalized.obj``). Files are taken in sorted order of their
    relative paths. Each file is one model:

    * model id (``key``): relative path without suffix, with ShapeNet's generic file names dropped
      (``03001627/1a6f615e8b1b5ae4dbbc9440457e303e``); sample id ``f"{id_prefix}/{key}"``;
    * ``meta["category"]``: the first folder under ``root`` (the synset for ShapeNet), or
      ``"uncategorized"`` for files directly in ``root``;
    * split: SHA-1 of the model id (:func:`split_of`), ``test_fraction`` of the models (default 0.2)
      go to ``test``; the split does not depend on ``seed`` or on which other files exist;
    * randomness (surface samples, noise, pose) comes from ``(seed, hash of the model id)``, so a
      sample does not change when files are added to the folder.

    Files are read lazily (on ``dataset[i]``; the last 64 are cached in memory); an unreadable
    file raises :class:`InputError` naming it then. A folder that is missing, holds no mesh files,
    or holds a 0-byte mesh file raises at construction.

    Args:
        root: the folder.
        seed: random seed of the sampling.
        split: ``"train"``, ``"test"`` or ``"all"``.
        test_fraction: share of models in the test split (0..1).
        n_samples: keep only the first ``n_samples`` models of the split (None: all).
        up_axis: ``"z"``, ``"y"`` (rotated to z-up by +90° about x) or ``"auto"``: ``"y"`` for
            ShapeNet-named files (``model.obj``, ``model_normalized.obj``, which are y-up), else
            ``"z"``. The yaw of ``T_gt`` is about the resulting z axis.
        id_prefix: first component of the sample ids.
        **sampling: :class:`ObjectSampling` fields (``n_map_points``, ``n_scan_points``,
            ``noise_std``, ``max_trans``, ``max_yaw_deg``, ``radius``).
    """

    name: ClassVar[str] = "meshes"
    param_ranges: ClassVar[dict[str, Range]] = {
        "test_fraction": Range(0.0, 1.0), "n_samples": Range(0, 10_000_000),
        "n_map_points": Range(6, 100_000_000), "n_scan_points": Range(6, 100_000_000),
        "noise_std": Range(0.0, 1e3), "max_trans": Range(0.0, 1e3), "max_yaw_deg": Range(0.0, 180.0)}
    description: ClassVar[str] = "Any folder of OBJ/OFF/PLY/STL meshes (ShapeNetCore layout included)"
    icp_preset: ClassVar[str] = "objects"
    default_budgets: ClassVar[tuple[float, ...]] = (0.02, 0.05)

    def __init__(self, root: str | Path | None = None, *, seed: int = 0, split: Split = "test",
                 test_fraction: float = 0.2, n_samples: int | None = None,
                 up_axis: Literal["auto", "y", "z"] = "auto", id_prefix: str = "meshes",
                 **sampling: Any) -> None:
        if root is None:
            raise InputError("the meshes dataset needs a folder: pass root=PATH")
        try:
            test_fraction = float(test_fraction)
            n_samples = None if n_samples in (None, "", "None") else int(n_samples)
        except (TypeError, ValueError) as exc:
            raise InputError(f"bad meshes dataset parameter: {exc}") from exc
        if not 0.0 <= test_fraction <= 1.0:
            raise InputError(f"test_fraction must be in [0, 1], got {test_fraction}")
        if n_samples is not None and n_samples < 0:
            raise InputError(f"n_samples must be >= 0, got {n_samples}")
        if up_axis not in ("auto", "y", "z"):
            raise InputError(f"up_axis must be 'auto', 'y' or 'z', got {up_axis!r}")
        self.sampling = ObjectSampling.from_params(**sampling)
        self.root = Path(root).expanduser()
        super().__init__(seed=seed, split=split, root=str(self.root), test_fraction=test_fraction,
                         n_samples=n_samples, up_axis=up_axis, **self.sampling.as_dict())
        self.up_axis = up_axis
        self.id_prefix = id_prefix
        self.entries = self._index(test_fraction)
        if n_samples is not None:
            self.entries = self.entries[:n_samples]

    @classmethod
    def param_types(cls) -> dict[str, Any]:
        """The named settings plus the :class:`ObjectSampling` fields (``**sampling``)."""
        from dataclasses import fields

        from icpbench.core.registry import keyword_params

        hints = keyword_params(ObjectSampling.__init__)
        return {**super().param_types(), **{f.name: hints.get(f.name, Any)
                                            for f in fields(ObjectSampling)}}

    def sample_id(self, i: int) -> str:
        """The id of sample ``i`` without reading its file."""
        return f"{self.id_prefix}/{self.entries[i].key}"

    def _index(self, test_fraction: float) -> list[MeshEntry]:
        files = find_mesh_files(self.root)
        keys = [model_key(self.root, p) for p in files]
        dup = {k for k in keys if keys.count(k) > 1} if len(set(keys)) < len(keys) else set()
        out = []
        for p, k in zip(files, keys, strict=True):
            if k in dup:  # e.g. chair.obj next to chair.ply: keep the suffix to tell them apart
                k = p.relative_to(self.root).as_posix()
            rel = p.relative_to(self.root).parts
            category = rel[0] if len(rel) > 1 else "uncategorized"
            s = split_of(k, test_fraction)
            if self.split in ("all", s):
                out.append(MeshEntry(p, k, category, s))
        return out

    def __len__(self) -> int:
        return len(self.entries)

    def _up(self, e: MeshEntry) -> str:
        if self.up_axis != "auto":
            return self.up_axis
        return "y" if e.path.stem.lower() in GENERIC_STEMS else "z"

    def __getitem__(self, i: int) -> Sample:
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} samples")
        e = self.entries[i]
        st = e.path.stat() if e.path.exists() else None
        if st is None:
            raise InputError(f"mesh file {e.path} disappeared since the dataset was indexed")
        V, F = _read_cached(str(e.path), st.st_mtime_ns, st.st_size)
        up = self._up(e)
        if up == "y":
            V = _y_up_to_z_up(V)
        meta = {"category": e.category, "model_id": e.key, "path": str(e.path), "split": e.split,
                "up_axis": up}
        try:
            return mesh_sample(V, F, sample_id=self.sample_id(i),
                               seed=[self.seed, _key_seed(e.key)], sampling=self.sampling, meta=meta)
        except InputError as exc:  # degenerate geometry: name the file it came from
            raise InputError(f"mesh file {e.path}: {exc}") from exc
