"""The plugin contract lives in the base classes and the registry enforces it: a plugin must
subclass the base of its kind, its ``name`` must equal its key, ``Attack.run`` is final, the hooks
the runner reads are declared with defaults, and plugin settings are checked (names and types)."""

from importlib.metadata import EntryPoint

import pytest
import torch
from typer.testing import CliRunner

from icpbench.attacks.base import Attack
from icpbench.attacks.none import NoAttack
from icpbench.attacks.uniform import UniformTranslationAttack
from icpbench.cli import app
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.datasets.base import Dataset
from icpbench.harness.runner import RunConfig
from icpbench.targets.base import Target
from icpbench.targets.p2plane import PointToPlaneICP


class _Misnamed(Attack):
    name = "class-name"

    def _perturb(self, batch, budget_m, *, surrogate, generator):
        return batch.scans.clone()


class _NotAnAttack:
    name = "not-an-attack"


def test_registering_a_plugin_whose_name_differs_from_its_key_is_a_clean_error():
    with pytest.raises(InputError, match=r"has name 'class-name'; the name must equal the key "
                                         r"'other-key'"):
        registry.attacks.register("other-key", _Misnamed)
    assert "other-key" not in registry.attacks.names()


def test_registering_a_class_that_is_not_an_attack_is_a_clean_error():
    with pytest.raises(InputError, match="_NotAnAttack is not a subclass of "
                                         "icpbench.attacks.base.Attack"):
        registry.attacks.register("not-an-attack", _NotAnAttack)
    with pytest.raises(InputError, match="is not a subclass of icpbench.targets.base.Target"):
        registry.targets.register("uniform", UniformTranslationAttack)
    with pytest.raises(InputError, match="is not a subclass of icpbench.datasets.base.Dataset"):
        registry.datasets.register("p2plane", PointToPlaneICP)


def test_an_entry_point_breaking_the_contract_is_reported_not_loaded(monkeypatch):
    """Installed plugins are checked when loaded: `run` stops with one line, `list` marks them."""
    reg = registry.attacks
    reg.discover()
    monkeypatch.setitem(reg._entry_points, "mismatch",
                        EntryPoint("mismatch", "icpbench.attacks.uniform:UniformTranslationAttack",
                                   "icpbench.attacks"))
    monkeypatch.setitem(reg._entry_points, "notattack",
                        EntryPoint("notattack", "icpbench.targets.p2plane:PointToPlaneICP",
                                   "icpbench.attacks"))
    try:
        with pytest.raises(InputError, match="has name 'uniform'; the name must equal the key "
                                             "'mismatch'"):
            reg.get("mismatch")
        ok, reason = reg.available("notattack")
        assert not ok and "not a subclass of icpbench.attacks.base.Attack" in reason
        res = CliRunner().invoke(app, ["run", "--dataset", "synthetic", "--attacks", "mismatch",
                                       "--samples", "1", "--out", "/nonexistent/x"])
        assert res.exit_code == 2 and "the name must equal the key 'mismatch'" in res.output
        assert "Traceback" not in res.output
    finally:
        reg._classes.pop("mismatch", None)
        reg._classes.pop("notattack", None)


def test_attack_run_is_final():
    with pytest.raises(TypeError, match="overrides Attack.run, which is final"):
        class _Overrides(Attack):  # noqa: F841 - the class statement itself must fail
            name = "overrides"

            def _perturb(self, batch, budget_m, *, surrogate, generator):
                return batch.scans

            def run(self, batch, budget_m, **kw):
                return None


def test_hooks_are_declared_on_the_bases_with_defaults():
    assert Attack.needs_surrogate is False and Attack.wants_context is False
    assert Attack.budget_invariant is False and NoAttack.budget_invariant is True
    assert Target.differentiable is False and Target.config is None
    assert UniformTranslationAttack.param_types() == {}  # strict is the run's --strict
    assert set(Dataset.param_types()) == set()
    t = PointToPlaneICP("lidar", max_iterations=40)
    short = t.with_max_iterations(7)
    assert type(short) is PointToPlaneICP and short.config.max_iterations == 7
    assert t.config.max_iterations == 40  # the original is unchanged
    assert short.config.cauchy_c == t.config.cauchy_c


def test_all_attacks_run_cheapest_first_and_the_ensemble_last():
    cfg = RunConfig(dataset="synthetic").validate()  # attacks: all
    classes = [registry.attacks.get(a).cost_class for a in cfg.attacks]
    assert classes == sorted(classes)
    assert cfg.attacks[0] == "none" and cfg.attacks[-1] == "ensemble"
    named = RunConfig(dataset="synthetic", attacks=["ensemble", "none"]).validate()
    assert named.attacks == ["ensemble", "none"]  # a list the user wrote keeps its order


@pytest.mark.parametrize("cfg, needle", [
    (dict(attacks=["pgd"], attack_params={"pgd": {"step": 5}}),
     r"unknown setting\(s\) 'step' for attack 'pgd'; valid: .*icp_iterations, .*step_size, "
     "steps, weights"),
    (dict(attacks=["none"], attack_params={"none": {"bogus": 1}}), "for attack 'none'; valid: "),
    (dict(attacks=["uniform"], attack_params={"uniform": {"bogus": 1}}), "attack 'uniform'"),
    (dict(attacks=["normal"], attack_params={"normal": {"bogus": 1}}), "attack 'normal'"),
    (dict(dataset_params={"n_samples": 2, "bogus": 1}),
     r"unknown setting\(s\) 'bogus' for dataset 'synthetic'; valid: n_map, n_samples, n_scan, "
     "noise_m"),
    (dict(attack_params={"bogus": {"steps": 3}}),
     r"settings given for attack\(s\) 'bogus' that are not in this run"),
    (dict(attacks=["uniform"], attack_params={"pgd": {"steps": 3}}),
     r"settings given for attack\(s\) 'pgd' that are not in this run"),
    (dict(target_params={"open3d": {"max_iterations": 3}}),
     r"settings given for target\(s\) 'open3d' that are not in this run"),
    (dict(attacks=["pgd"], attack_params={"pgd": {"steps": "abc"}}),
     "setting 'steps' of attack 'pgd' must be an integer, got 'abc'"),
    (dict(target_params={"p2plane": {"max_iterations": "abc"}}),
     "setting 'max_iterations' of target 'p2plane' must be an integer, got 'abc'"),
    (dict(dataset_params={"n_samples": "many"}),
     "setting 'n_samples' of dataset 'synthetic' must be an integer, got 'many'"),
])
def test_plugin_settings_are_checked_for_every_plugin(cfg, needle):
    base = dict(dataset="synthetic", attacks=["uniform"], targets=["p2plane"], budgets=[1.0],
                samples=1)
    with pytest.raises(InputError, match=needle):
        RunConfig(**{**base, **cfg}).validate()


def test_setting_values_are_coerced_to_the_declared_types():
    cfg = RunConfig(dataset="synthetic", attacks=["pgd"], targets=["p2plane"], budgets=[1.0],
                    attack_params={"pgd": {"step_size": "1e-3", "steps": 2.0,
                                           "icp_nn_reuse": "0"}},
                    target_params={"p2plane": {"d_max": None, "tol": "1e-5"}},
                    dataset_params={"n_samples": 2}).validate()
    assert cfg.attack_params["pgd"] == {"step_size": 1e-3, "steps": 2, "icp_nn_reuse": 0.0}
    assert cfg.target_params["p2plane"] == {"d_max": None, "tol": 1e-5}


def test_a_black_box_surrogate_for_a_gradient_attack_is_a_configuration_error():
    with pytest.raises(InputError, match=r"pgd need a differentiable surrogate; 'open3d' is a "
                                         "black box"):
        RunConfig(dataset="synthetic", attacks=["pgd"], surrogate="open3d", budgets=[1.0]).validate()


def test_pgd_uses_the_surrogate_iteration_cap_through_the_target_hook(monkeypatch):
    from icpbench.attacks.pgd import PGDAttack

    seen = []
    orig = Target.with_max_iterations

    def spy(self, n):
        seen.append(n)
        return orig(self, n)

    monkeypatch.setattr(Target, "with_max_iterations", spy)
    from icpbench.core.types import Batch
    from icpbench.datasets.synthetic import SyntheticSceneDataset

    batch = Batch.from_samples([SyntheticSceneDataset(n_samples=1, n_scan=200, n_map=2000)[0]])
    PGDAttack(steps=1, icp_iterations=3).run(batch, 0.5, surrogate=PointToPlaneICP("lidar"),
                                             generator=0)
    assert seen == [3]
    assert torch.get_num_threads() == 1
