"""Adaptive attacks against the evaluated target: the query oracle, ``sector-adaptive``, ``search``,
``ensemble`` and ``--surrogate self``.

What they show: queries are counted exactly; every attack keeps the budget; the query-only attacks
run against black boxes; the ensemble is never below any member on any scan and records the
winner; the runner attacks each target separately and records queries per row.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from icpbench.attacks.ensemble import (
    DEFAULT_MEMBERS,
    MEMBERS,
    VALLEY_LINE_STEPS,
    EnsembleAttack,
    column,
)
from icpbench.attacks.normal import NormalTranslationAttack
from icpbench.attacks.search import QuerySearchAttack
from icpbench.attacks.sector import SectorAttack
from icpbench.attacks.sector_adaptive import SectorAdaptiveAttack
from icpbench.attacks.uniform import UniformTranslationAttack
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.harness.results import load_results
from icpbench.harness.runner import RunConfig, run
from icpbench.targets.kiss import KissICPTarget
from icpbench.targets.oracle import QueryOracle
from icpbench.targets.p2plane import PointToPlaneICP
from icpbench.targets.p2point import PointToPointICP
from icpbench.targets.self_surrogate import SelfSurrogate, self_surrogate

torch.set_num_threads(1)
LAM = 0.5


@pytest.fixture(scope="module")
def batch(scene_pair) -> Batch:
    return scene_pair


def _oracle(target, batch: Batch) -> QueryOracle:
    return QueryOracle.prepared(target, batch)


def _within_budget(adv: torch.Tensor, batch: Batch, lam: float) -> None:
    d = torch.linalg.norm(adv.to(torch.float64) - batch.scans.to(torch.float64), dim=-1)
    assert float(d.max()) <= lam * (1 + 1e-6)


def test_oracle_counts_queries_and_measures_the_table_error(batch):
    o = _oracle(PointToPlaneICP("lidar"), batch)
    T, err, status = o.register(batch.scans)
    xi = pose_error(torch.as_tensor(T), batch.T_gt)
    np.testing.assert_allclose(err, torch.linalg.norm(xi[:, :2], dim=-1).numpy())
    assert err.max() < 0.05 and status == ["ok", "ok"]
    o.errors(batch.scans[1:], [1])
    np.testing.assert_array_equal(o.queries, [1, 2])
    with pytest.raises(InputError):
        o.errors(batch.scans, [1])


@pytest.mark.parametrize("target", [PointToPlaneICP("lidar"), PointToPointICP("lidar"),
                                    KissICPTarget("lidar")], ids=["p2plane", "p2point", "kiss"])
def test_sector_adaptive_keeps_the_budget_counts_queries_and_never_loses_its_start(batch, target):
    attack = SectorAdaptiveAttack(iterations=2)
    out = attack.run(batch, LAM, oracle=_oracle(target, batch), generator=0)
    _within_budget(out.scans, batch, LAM)
    np.testing.assert_array_equal(out.extra["queries"].numpy(), [3, 3])
    # the returned iterate is the best of those queried, the start (iterate 0) included
    start = SectorAdaptiveAttack(iterations=0).run(batch, LAM, oracle=_oracle(target, batch))
    o = _oracle(target, batch)
    assert np.all(o.errors(out.scans) >= o.errors(start.scans) - 1e-9)


def test_sector_adaptive_needs_an_oracle(batch):
    with pytest.raises(InputError, match="oracle"):
        SectorAdaptiveAttack().run(batch, LAM)


def test_search_spends_its_queries_and_only_climbs(batch):
    target = PointToPlaneICP("lidar")
    o = _oracle(target, batch)
    out = QuerySearchAttack(queries=6, wedges=4).run(batch, LAM, oracle=o, generator=1)
    _within_budget(out.scans, batch, LAM)
    np.testing.assert_array_equal(out.extra["queries"].numpy(), [6, 6])
    start = QuerySearchAttack(queries=1, wedges=4).run(batch, LAM, oracle=_oracle(target, batch),
                                                        generator=1)
    o2 = _oracle(target, batch)
    assert np.all(o2.errors(out.scans) >= o2.errors(start.scans) - 1e-9)
    np.testing.assert_allclose(out.extra["search_err"].numpy(), o2.errors(out.scans))


def test_search_traces_its_best_error_as_the_budget_is_spent(batch):
    o = _oracle(PointToPlaneICP("lidar"), batch)
    out = QuerySearchAttack(queries=51, wedges=4).run(batch, LAM, oracle=o, generator=2)
    at20, at50 = out.extra["search_err_at_20"].numpy(), out.extra["search_err_at_50"].numpy()
    final = out.extra["search_err"].numpy()
    assert "search_err_at_100" not in out.extra  # only counts below the budget
    assert np.all(at20 <= at50) and np.all(at50 <= final)  # best so far: never falls
    assert np.all(at20 > 0.5 * LAM)  # at least the start's error (a translation by lambda)
    # no trace for a budget of 20 queries or less: default runs keep their columns
    short = QuerySearchAttack(queries=20, wedges=4).run(batch, LAM, oracle=_oracle(
        PointToPlaneICP("lidar"), batch), generator=2)
    assert not any(k.startswith("search_err_at_") for k in short.extra)


@pytest.mark.parametrize("target", [PointToPlaneICP("lidar"), KissICPTarget("lidar")],
                         ids=["p2plane", "kiss"])
def test_ensemble_is_never_below_any_member(batch, target):
    surrogate = self_surrogate(target)
    ens = EnsembleAttack(members=",".join(MEMBERS), pgd_steps=1, sector_iterations=1, queries=3,
                         spoof_queries=2, valley_queries=2)
    out = ens.run(batch, LAM, surrogate=surrogate, oracle=_oracle(target, batch), generator=7)
    _within_budget(out.scans, batch, LAM)
    o = _oracle(target, batch)
    final = o.errors(out.scans)
    # the members alone, with the same seed, give the errors the ensemble recorded
    alone = {"uniform": UniformTranslationAttack(), "normal": NormalTranslationAttack(),
             "sector": SectorAttack(), "sector-adaptive": SectorAdaptiveAttack(iterations=1)}
    for name, attack in alone.items():
        kw = {"oracle": _oracle(target, batch)} if attack.needs_oracle else {}
        err = o.errors(attack.run(batch, LAM, generator=7, **kw).scans)
        np.testing.assert_allclose(out.extra[column(name)].numpy(), err, rtol=1e-9)
        assert np.all(final >= err - 1e-9)
    recorded = np.stack([out.extra[column(m)].numpy() if m in ens.active else np.full(2, np.nan)
                         for m in MEMBERS])
    np.testing.assert_allclose(final, np.nanmax(recorded, axis=0), rtol=1e-9)
    winner = out.extra["winner"].numpy().astype(int)
    np.testing.assert_allclose(recorded[winner, [0, 1]], final, rtol=1e-9)
    if not target.differentiable and surrogate is None:
        assert np.isnan(out.extra["err_pgd"].numpy()).all()


def test_self_surrogate_keeps_the_targets_cap_and_uses_the_implicit_gradient():
    s = self_surrogate(PointToPointICP("lidar", max_iterations=300))
    assert isinstance(s, SelfSurrogate)
    assert s.with_max_iterations(25) is s
    assert s.config.max_iterations == 300 and s.config.backprop == "implicit"
    assert s.with_settings(max_iterations=5).config.max_iterations == 300


def test_runner_attacks_each_target_separately_with_surrogate_self(tmp_path):
    cfg = RunConfig(dataset="synthetic", dataset_params={"n_scan": 600, "n_map": 6000},
                    attacks=["uniform", "sector-adaptive"], targets=["p2plane", "p2point"],
                    budgets=[LAM], samples=2, surrogate="self",
                    attack_params={"sector-adaptive": {"iterations": 1}})
    run(cfg, tmp_path / "r", progress=False)
    df = load_results(tmp_path / "r")
    assert len(df) == 8 and (df.status != "error").all()
    ad = df[df.attack == "sector-adaptive"]
    assert (ad["extra.queries"] == 2).all()
    # each target was attacked through itself: the rows differ between targets
    a = ad.set_index(["sample_id", "target"]).trans_err_xy.unstack()
    assert not np.allclose(a["p2plane"], a["p2point"])


def test_ensemble_traces_its_worst_case_against_the_search_budget(batch):
    target = PointToPlaneICP("lidar")
    ens = EnsembleAttack(members="uniform,sector-adaptive,search", sector_iterations=1,
                         queries=22)
    out = ens.run(batch, LAM, surrogate=None, oracle=_oracle(target, batch), generator=3)
    at20 = out.extra["search_best_at_20"].numpy()
    first = MEMBERS[:MEMBERS.index("search")]  # the members that run before the search
    before = np.nanmax(np.stack([out.extra[column(m)].numpy() for m in first
                                 if column(m) in out.extra]), axis=0)
    assert np.all(at20 >= before - 1e-12)  # the search starts from the members' best
    assert np.all(out.extra["err_search"].numpy() >= at20)


def test_search_patience_stops_a_scan_on_the_same_path_and_saves_its_queries(batch):
    """A scan's random draws do not depend on when the others stop, so with a patience each scan
    follows the path of the full search and stops on it: never above the full search's error,
    equal to it where the scan ran to the end, and its queries are not spent."""
    target = PointToPlaneICP("lidar")
    full = QuerySearchAttack(queries=16, wedges=4).run(batch, LAM, oracle=_oracle(target, batch),
                                                       generator=5)
    lazy = QuerySearchAttack(queries=16, wedges=4, patience=2).run(
        batch, LAM, oracle=_oracle(target, batch), generator=5)
    q = lazy.extra["queries"].numpy()
    e_full, e_lazy = full.extra["search_err"].numpy(), lazy.extra["search_err"].numpy()
    assert np.all(q <= 16) and q.min() < 16
    assert np.all(e_lazy <= e_full + 1e-12)
    np.testing.assert_allclose(e_lazy[q == 16], e_full[q == 16], rtol=1e-12)
    with pytest.raises(InputError):
        QuerySearchAttack(patience=-1)


def test_ensemble_members_are_named_once_and_checked():
    assert EnsembleAttack().active == DEFAULT_MEMBERS
    assert set(DEFAULT_MEMBERS) <= set(MEMBERS) and DEFAULT_MEMBERS[-1] == "search"
    # the monitor-aware members run after every default one and are not defaults
    assert MEMBERS[-2:] == ("drift", "refine") and not {"drift", "refine"} & set(DEFAULT_MEMBERS)
    ens = EnsembleAttack(members=" valley, uniform ")
    assert ens.active == ("uniform", "valley")  # run in the order of MEMBERS
    for bad in ("uniform,bogus", "uniform,uniform", " , "):
        with pytest.raises(InputError, match="ensemble members"):
            EnsembleAttack(members=bad)
    # valley's line steps are the ensemble's setting, recorded with the others
    assert EnsembleAttack().members["valley"].line_steps == VALLEY_LINE_STEPS
    two = EnsembleAttack(valley_line_steps=2)
    assert two.members["valley"].line_steps == 2 and two.settings()["valley_line_steps"] == 2
    for bad_steps in (0, 1.5, True):
        with pytest.raises(InputError, match="valley_line_steps"):
            EnsembleAttack(valley_line_steps=bad_steps)
    # valley's kernel model: Geman-McClure's where the target has it (protocol v3), recorded
    assert EnsembleAttack().members["valley"].kernel_model == "geman-mcclure"
    assert EnsembleAttack().settings()["valley_kernel_model"] == "geman-mcclure"
    own = EnsembleAttack(valley_kernel_model="own")
    assert own.members["valley"].kernel_model == "own"
    with pytest.raises(InputError, match="kernel_model"):
        EnsembleAttack(valley_kernel_model="yes")


def test_the_generator_takes_each_targets_own_surrogate_under_surrogate_self(tmp_path):
    """``generator-refine`` steps through a surrogate: under ``--surrogate self`` that is each
    target itself (an attack that uses a surrogate says so, or it would get none and fail)."""
    assert all(registry.attacks.get(a).adaptive(True)
               for a in ("generator", "generator-refine", "pgd", "sector-iter", "ensemble"))
    cfg = RunConfig(dataset="lidar-sim", attacks=["generator-refine"], targets=["p2point"],
                    budgets=[LAM], samples=1, surrogate="self",
                    attack_params={"generator-refine": {"refine_steps": 1}})
    run(cfg, tmp_path / "r", progress=False)
    df = load_results(tmp_path / "r")
    assert (df.status != "error").all(), df.error.tolist()
