"""Pictures of a dataset: the route from above, and one scan overlaid on its submap.

``show_dataset("lidar-sim", "results/")`` writes

* ``<name>_route.png``: for ``lidar-sim`` the town from above (a height map of the static meshes
  in grey, ray-cast straight down) with the route coloured by place / stretch type; for other
  datasets the sample positions (meta ``x``, ``y``) coloured by stretch or sequence;
* ``<name>_scan_on_submap.png``: one sample from above, the submap in grey and the scan in colour,
  at the initial guess ``T_init`` (left) and at the ground truth ``T_gt`` (right).

For ``lidar-sim`` variety (``town_seed``, ``sensor``): :func:`towns_figure` draws several towns side
by side, :func:`sensors_figure` one place seen by several sensors (full sweeps, before the
subsampling to N points). Every axis is in metres.

Matplotlib with the Agg backend; nothing is shown on screen.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from icpbench.core.errors import InputError  # noqa: E402
from icpbench.core.filenames import safe_component  # noqa: E402
from icpbench.core.types import Sample  # noqa: E402
from icpbench.datasets import submaps as sm  # noqa: E402
from icpbench.datasets.base import Dataset  # noqa: E402
from icpbench.harness.outputs import save_figure

PLACE_COLOURS = {"suburb": "#d62728", "parking": "#ff7f0e", "field": "#bcbd22",
                 "highway": "#1f77b4", "underpass": "#9467bd"}
STRETCH_COLOURS = {"dense": "#d62728", "open": "#e6a100", "highway": "#1f77b4",
                   "underpass": "#9467bd"}


def _resolve(dataset: str | Dataset, kwargs: dict[str, Any]) -> Dataset:
    if isinstance(dataset, Dataset):
        return dataset
    if isinstance(dataset, str):
        from icpbench.core.registry import datasets

        return datasets.get(dataset).create(**kwargs)
    raise InputError(f"expected a dataset name or a Dataset, got {type(dataset).__name__}")


def show_dataset(dataset: str | Dataset, out_dir: str | Path, *, sample_index: int | None = None,
                 max_route_samples: int = 400, **dataset_kwargs: Any) -> list[Path]:
    """Write the route picture and the scan-on-submap picture of a dataset; return their paths.

    Args:
        dataset: a registered dataset name (built with ``dataset_kwargs``) or an instance.
        out_dir: output folder (created).
        sample_index: the sample to draw on its submap (default: the first from a dense stretch
            if the dataset labels stretches, else sample 0).
        max_route_samples: for datasets without a town, at most this many samples are loaded to
            draw their positions.
    """
    ds = _resolve(dataset, dataset_kwargs)
    if len(ds) == 0:
        raise InputError(f"dataset {ds.name!r} has no samples to draw")
    if sample_index is not None and not 0 <= sample_index < len(ds):
        raise InputError(f"sample index {sample_index} is out of range: dataset {ds.name!r} has "
                         f"{len(ds)} samples (0..{len(ds) - 1})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    name = (ds.name or type(ds).__name__).replace("/", "_")
    stem = safe_component(name)
    paths = [out / f"{stem}_route.png", out / f"{stem}_scan_on_submap.png"]
    if hasattr(ds, "town") and hasattr(ds, "route"):
        _town_figure(ds, paths[0])
    else:
        _positions_figure(ds, paths[0], max_route_samples)
    _scan_figure(_pick_sample(ds, sample_index), paths[1])
    return paths


def _pick_sample(ds: Dataset, index: int | None) -> Sample:
    if index is not None:
        return ds[index]
    if hasattr(ds, "_index") and hasattr(ds, "route"):  # lidar-sim: the first dense location
        for i, (_, f) in enumerate(ds._index):
            s = f * ds.sample_spacing_m
            if str(ds.route.place_at(s)) == "suburb":
                return ds[i]
    return ds[0]


def _height_map(ds: Any, res_m: float, pad: float = 150.0
                ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """Height above ground (H, W) in metres of the static town (and the teach pass's parked
    cars), on a grid of ``res_m`` covering the route plus ``pad`` metres."""
    from icpbench.datasets.lidar_model import make_scene

    town = ds.town
    x0, y0, x1, y1 = town.bounds
    x0, y0 = max(x0, town.route.xy[:, 0].min() - pad), max(y0, town.route.xy[:, 1].min() - pad)
    x1, y1 = min(x1, town.route.xy[:, 0].max() + pad), min(y1, town.route.xy[:, 1].max() + pad)
    xs, ys = np.arange(x0, x1, res_m), np.arange(y0, y1, res_m)
    X, Y = np.meshgrid(xs, ys)
    rays = np.zeros((X.size, 6), dtype=np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = X.ravel(), Y.ravel(), 100.0, -1.0
    import open3d as o3d

    top = np.full(X.size, -np.inf)
    for scene in (make_scene(town.vertices, town.triangles), ds._cars_scene(0)):
        if scene is None:
            continue
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        top = np.maximum(top, np.where(np.isfinite(t), 100.0 - t, -np.inf))
    ground = town.terrain.height(rays[:, :2].astype(np.float64))  # slopes, banks
    height = np.where(np.isfinite(top), top - ground, 0.0)
    return height.reshape(X.shape), (x0, x1, y0, y1)


def _town_figure(ds: Any, path: Path) -> None:
    route = ds.route
    span = float(np.ptp(route.xy, axis=0).max())
    H, extent = _height_map(ds, res_m=max(0.6, span / 2000))
    fig, ax = plt.subplots(figsize=(11, 9), dpi=150)
    im = _draw_heights(ax, H, extent)
    fig.colorbar(im, ax=ax, shrink=0.6, label="structure height above ground (m)")
    _draw_route(ax, route)
    ax.set_title(f"lidar-sim town ({_town_name(ds)}): {route.length / 1000:.2f} km loop, "
                 f"{ds.n_vertices} locations per pass; grey = structures (darker = taller)")
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def _draw_heights(ax: Any, H: np.ndarray, extent: tuple[float, float, float, float]) -> Any:
    """Structures taller than 0.3 m in grey (darker = taller, black from 8 m); returns the image."""
    from matplotlib.colors import LinearSegmentedColormap

    greys = LinearSegmentedColormap.from_list("greys", plt.get_cmap("Greys")(np.linspace(0.23, 1, 64)))
    shade = np.where(H < 0.3, np.nan, H)  # ground, curbs and sidewalks stay white
    return ax.imshow(shade, origin="lower", extent=extent, cmap=greys, vmin=0.0, vmax=8.0,
                     interpolation="nearest")


def _draw_route(ax: Any, route: Any, legend: bool = True) -> None:
    """The route coloured by place, a start arrow, equal axes in metres."""
    s = np.arange(0.0, route.length, 1.0)
    xy, _ = route.pose(s)
    seen = set()
    for a, b, place in route.intervals():
        m = (s >= a) & (s <= b)
        label = None if place in seen else f"{place} ({_stretch(place)})"
        seen.add(place)
        ax.plot(xy[m, 0], xy[m, 1], color=PLACE_COLOURS[place], lw=3.0, label=label,
                solid_capstyle="butt")
    start, h0 = route.pose(0.0)
    ax.annotate("", xy=start + 60 * np.array([np.cos(h0), np.sin(h0)]), xytext=start,
                arrowprops={"arrowstyle": "->", "lw": 2, "color": "k"})
    ax.plot(*start, "ko", ms=6)
    ax.text(start[0] - 12, start[1], "start", ha="right", va="center", fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if legend:
        ax.legend(loc="best", fontsize=9, title="place (stretch)")


def _town_name(ds: Any) -> str:
    t = getattr(ds, "town_seed", None)
    return f"seed {ds.seed}" if t is None else f"town_seed {t}"


def towns_figure(datasets: list[Any], path: str | Path) -> Path:
    """Several ``lidar-sim`` towns side by side from above (structures in grey by height, the
    route by place; axes in metres). ``datasets``: single-town ``LidarSimDataset`` s."""
    if not datasets:
        raise InputError("towns_figure needs at least one lidar-sim dataset")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(datasets), figsize=(6.5 * len(datasets), 6.4), dpi=150,
                             squeeze=False)
    im = None
    for k, (ax, ds) in enumerate(zip(axes[0], datasets, strict=True)):
        span = float(np.ptp(ds.route.xy, axis=0).max())
        H, extent = _height_map(ds, res_m=max(0.8, span / 1200), pad=60.0)
        im = _draw_heights(ax, H, extent)
        _draw_route(ax, ds.route, legend=k == 0)
        z = ds.ground.height_sd(np.arange(0.0, ds.route.length, 5.0), 0.0)
        ax.set_title(f"{_town_name(ds)}: {ds.route.length / 1000:.2f} km, "
                     f"{len(ds.route.layout)} stretches\nroad height {z.min():+.1f} to "
                     f"{z.max():+.1f} m, camber {100 * ds.ground.camber:.1f} %", fontsize=10)
    fig.tight_layout(rect=(0, 0, 0.94, 1))
    fig.colorbar(im, cax=fig.add_axes((0.95, 0.2, 0.01, 0.6)), label="structure height above ground (m)")
    save_figure(fig, path)
    plt.close(fig)
    return path


def sensors_figure(datasets: list[Any], path: str | Path, *, pass_id: int = 1, frame: int = 0,
                   radius_m: float = 40.0) -> Path:
    """The same place (repeat pass ``pass_id``, location ``frame``) seen by several sensors: the
    full sweep of each (before subsampling) from above, coloured by height, in the vehicle frame
    (x forward, y left, metres). ``datasets``: single-town ``LidarSimDataset`` s of one town with
    different sensors."""
    from icpbench.datasets.lidar_model import cast_scan

    if not datasets:
        raise InputError("sensors_figure needs at least one lidar-sim dataset")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = len(datasets)
    fig, axes = plt.subplots(1, n, figsize=(4.6 * n, 5.4), dpi=150, sharex=True, sharey=True,
                             squeeze=False)
    sc = None
    for ax, ds in zip(axes[0], datasets, strict=True):
        s_m, d, dyaw, _, _ = ds.live_pose(pass_id, frame)
        T = ds.sensor_pose(s_m, d, dyaw)
        scan = cast_scan([ds._static_scene(), ds._cars_scene(pass_id)], T, ds.lidar,
                         sm.sample_rng(pass_id, frame, 17))
        P = scan.points
        keep = np.linalg.norm(P[:, :2], axis=1) <= radius_m
        sc = ax.scatter(P[keep, 0], P[keep, 1], c=P[keep, 2], s=0.2, lw=0, cmap="viridis",
                        vmin=-ds.lidar.mount_height_m - 0.5, vmax=6.0)
        ax.plot(0, 0, "r^", ms=6)
        ax.set_aspect("equal")
        ax.set_xlim(-radius_m, radius_m)
        ax.set_ylim(-radius_m, radius_m)
        ax.set_xlabel("x, longitudinal (m)")
        el = ds.lidar.elevations()
        ax.set_title(f"{ds.sensor}: {ds.lidar.n_beams} beams, {el.min():+.1f} to "
                     f"{el.max():+.1f} deg\n{len(P)} returns (subsampled to {ds.n_points})", fontsize=10)
    axes[0][0].set_ylabel("y, lateral (m)")
    ds = datasets[0]
    fig.suptitle(f"lidar-sim {_town_name(ds)}, pass {pass_id}, location {frame} "
                 f"({ds.route.place_at(ds.live_pose(pass_id, frame)[0])}): full sweeps within "
                 f"{radius_m:g} m")
    fig.tight_layout(rect=(0, 0, 0.93, 0.95))
    fig.colorbar(sc, cax=fig.add_axes((0.945, 0.15, 0.01, 0.65)), label="z in the sensor frame (m)")
    save_figure(fig, path)
    plt.close(fig)
    return path


def _stretch(place: str) -> str:
    from icpbench.datasets.town import PLACES

    return PLACES.get(place, place)


def _positions_figure(ds: Dataset, path: Path, max_samples: int) -> None:
    step = max(1, len(ds) // max_samples)
    samples = [ds[i] for i in range(0, len(ds), step)]
    xs = np.array([float(s.meta.get("x", np.nan)) for s in samples])
    ys = np.array([float(s.meta.get("y", np.nan)) for s in samples])
    if not np.isfinite(xs).any():
        raise InputError(f"dataset {ds.name!r} has no x/y positions in its sample metadata")
    key = "stretch" if all("stretch" in s.meta for s in samples) else "pass"
    groups = [str(s.meta.get(key, "")) for s in samples]
    fig, ax = plt.subplots(figsize=(9, 8), dpi=150)
    cmap = plt.get_cmap("tab10")
    for k, g in enumerate(sorted(set(groups))):
        m = np.array([x == g for x in groups])
        ax.scatter(xs[m], ys[m], s=8, color=STRETCH_COLOURS.get(g, cmap(k % 10)), label=g or "samples")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{ds.name}: positions of {len(samples)} of {len(ds)} samples")
    ax.legend(fontsize=8, title=key)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def _scan_figure(sample: Sample, path: Path, radius_m: float = 45.0) -> None:
    Q = np.asarray(sample.map, dtype=np.float64)
    fig, axes = plt.subplots(1, 2, figsize=(14, 7), dpi=150, sharex=True, sharey=True)
    for ax, T, title in ((axes[0], sample.T_init, "initial guess (T_init)"),
                         (axes[1], sample.T_gt, "ground truth (T_gt)")):
        P = sm.transform(T, sample.scan)
        ax.scatter(Q[:, 0], Q[:, 1], s=0.15, c="0.6", lw=0, label=f"submap ({len(Q)} pts)")
        ax.scatter(P[:, 0], P[:, 1], s=0.6, c="#d62728", lw=0, label=f"scan ({len(P)} pts)")
        ax.plot(0, 0, "k^", ms=7)
        ax.annotate("", xy=(5, 0), xytext=(0, 0), arrowprops={"arrowstyle": "->", "lw": 1.5})
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.set_xlim(-radius_m, radius_m)
        ax.set_ylim(-radius_m, radius_m)
        ax.set_xlabel("x, longitudinal (m)")
        ax.legend(loc="upper right", fontsize=8, markerscale=12)
    axes[0].set_ylabel("y, lateral (m)")
    meta = sample.meta
    extra = ", ".join(f"{k}={meta[k]}" for k in ("stretch", "place", "pass", "frame") if k in meta)
    fig.suptitle(f"{sample.id}: scan on its submap, vehicle frame ({extra})")
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    save_figure(fig, path)
    plt.close(fig)
