"""Every figure the package writes labels its numeric axes (colour bars included) with a unit."""

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure

from icpbench.analysis.danger_map import plot_comparison, plot_route
from icpbench.analysis.object_study import figure as object_figure
from icpbench.analysis.plotting import axes_without_units, pyplot
from icpbench.core.types import Sample
from icpbench.datasets.base import Dataset


@pytest.fixture
def saved(monkeypatch):
    """Record, for every figure saved during the test, the axes that lack a unit."""
    found: list[list[str]] = []
    real = Figure.savefig

    def check_then_save(fig, *args, **kwargs):
        found.append(axes_without_units(fig))
        return real(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", check_then_save)
    return found


def test_check_finds_a_missing_unit_and_accepts_categories_and_shared_axes():
    plt = pyplot()
    fig, (a, b, c) = plt.subplots(1, 3, sharey=True)
    a.plot([0, 1], [0, 2])
    a.set_xlabel("x [m]")
    a.set_ylabel("error")  # no unit: reported
    b.plot([0, 1], [0, 2])
    b.set_xlabel("time (s)")  # y tick labels hidden by sharey: covered by a's y label
    c.violinplot([np.arange(5.0)])
    c.set_xticks([1], ["generator"])  # category names: no unit needed
    c.set_xlabel("")
    sc = c.scatter([1], [1], c=[1.0])
    fig.colorbar(sc, ax=c)  # colour bar without a label: reported
    missing = axes_without_units(fig)
    plt.close(fig)
    assert len(missing) == 2
    assert any("y axis label 'error'" in m for m in missing)
    assert sum("y axis label ''" in m for m in missing) == 1  # the colour bar
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y, lateral (m)")
    assert axes_without_units(fig) == []
    plt.close(fig)


def test_route_maps_and_comparison_have_metres_on_both_axes(saved, tmp_path):
    per_loc = pd.DataFrame({"x": np.arange(10) * 20.0, "y": np.zeros(10), "stretch": "open",
                            "trans_err_xy": np.linspace(0.1, 2.0, 10)})
    plot_route(per_loc, tmp_path / "map.png", title="route")
    cmp = per_loc.assign(difference=np.linspace(-1.0, 1.0, 10))
    plot_comparison(cmp, tmp_path / "cmp.png", "generator", "sector")
    assert saved == [[], []]


def test_object_study_figure_labels_normalised_axes(saved, tmp_path):
    rng = np.random.default_rng(0)
    clean = rng.normal(size=(2, 50, 3))
    clouds = {"_clean": clean, "original": clean, "uniform": clean + 0.05,
              "uniform (strict)": clean + 0.05}
    rows = pd.DataFrame([{"attack": a, "sample_id": f"o{i}", "heading_err_deg": 1.0, "xy_err": 0.1}
                         for a in ("original", "uniform") for i in range(2)])
    object_figure(rows, clouds, tmp_path / "objects.png")
    assert saved == [[]]


class _Route(Dataset):
    """Four samples along a line with route positions in their metadata."""

    name = "route-fixture"

    def __len__(self) -> int:
        return 4

    def __getitem__(self, i: int) -> Sample:
        rng = np.random.default_rng(i)
        pts = rng.uniform(-20, 20, size=(200, 3)).astype(np.float32)
        normals = np.tile(np.float32([0, 0, 1]), (200, 1))
        return Sample(id=f"r/{i}", scan=pts, map=pts, map_normals=normals, T_gt=np.eye(4),
                      meta={"x": 10.0 * i, "y": 0.0, "pass": 1})


def test_dataset_pictures_label_their_axes(saved, tmp_path):
    from icpbench.analysis.dataset_figures import show_dataset

    paths = show_dataset(_Route(), tmp_path)
    assert [p.exists() for p in paths] == [True, True]
    assert saved == [[], []]


def test_validation_route_figure_labels_every_panel(saved, tmp_path):
    from icpbench.analysis.danger_validation import quantity_columns
    from icpbench.analysis.validation_figure import danger_percentile, plot_validation_route

    rng = np.random.default_rng(0)
    quantities = quantity_columns(["generator"])
    places = pd.DataFrame({"x": rng.uniform(0, 500, 30), "y": rng.uniform(0, 500, 30),
                           "realistic_s3": rng.uniform(0, 2, 30),
                           **{q: rng.uniform(1, 9, 30) for q in quantities}})
    plot_validation_route(places, quantities, 3, 0.5, tmp_path / "route.png", title="t")
    assert (tmp_path / "route.png").stat().st_size > 0
    assert saved == [[]]
    # danger percentiles: negated quantities rank their smallest value most dangerous
    assert list(danger_percentile(np.array([1.0, 3.0, 2.0]), -1)) == pytest.approx([1, 1 / 3, 2 / 3])
    assert danger_percentile(np.array([1.0, np.inf]), 1)[1] == 1.0


def _board(amp: dict[str, float], half_width: float, budget: float = 1.0) -> pd.DataFrame:
    """A board of one budget: each variant's mean worst case (metres) with a symmetric interval."""
    worst = pd.Series(amp) * budget
    return pd.DataFrame({"variant": list(amp), "budget": budget, "worst_mean": worst.values,
                         "worst_lo": worst.values - half_width, "worst_hi": worst.values + half_width,
                         "amplification": list(amp.values())})


def test_board_figures_draw_intervals_and_two_domains(saved, tmp_path):
    from icpbench.harness.board_figures import _interval, board_figure, domain_figure

    town = _board({"kiss-icp": 2.3, "p2point": 2.6, "gicp": 18.0}, 0.2)
    unseen = _board({"kiss-icp": 2.4, "gicp": 38.0, "p2point": 3.4, "new": 5.0}, 1.0, budget=2.0)
    # the bars' half widths in units of lambda: 1 m / 2 m either side on the 2 m board
    np.testing.assert_allclose(_interval(unseen), 0.5)
    np.testing.assert_allclose(_interval(town.drop(columns=["worst_lo", "worst_hi"])), 0.0)
    board_figure(unseen, tmp_path / "board.png", 1.5)
    # only the three variants both boards rank are drawn; fewer than two: nothing is written
    assert domain_figure(unseen, town, tmp_path / "domains.png", label="unseen",
                         other_label="town", title="tau") == 3
    assert domain_figure(unseen, town.iloc[:1], tmp_path / "none.png", label="unseen",
                         other_label="town", title="tau") == 1
    assert not (tmp_path / "none.png").exists()
    assert (tmp_path / "board.png").stat().st_size > 10_000
    assert (tmp_path / "domains.png").stat().st_size > 10_000
    assert saved == [[], []]
