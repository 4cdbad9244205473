"""Training loop: a tiny objects run writes a checkpoint + card, resumes, and the `generator`
attack loads it through the runner."""

import json

import pytest
import torch

from icpbench.core.errors import CheckpointError
from icpbench.harness.results import load_results
from icpbench.harness.runner import RunConfig, run
from icpbench.learning.training import train, train_config


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("train")
    cfg = train_config("quick-objects", train_samples=4, eval_samples=2, batch_size=2,
                       pretrain_epochs=1, epochs=1, dataset_params={"n_samples": 4})
    card = train(cfg, out, progress=False)
    return cfg, out, card


def test_checkpoint_card_and_history(trained):
    cfg, out, card = trained
    assert (out / "generator.pt").exists() and (out / "generator.json").exists()
    meta = json.loads((out / "generator.json").read_text())
    assert meta["card"]["epochs_done"] == 2 and meta["card"]["budgets_m"] == [0.05]
    ev = card["heldout_eval"]["0.05"]
    assert ev["samples"] == 2 and ev["disp_max_mean"] >= 0
    lines = (out / "history.csv").read_text().strip().splitlines()
    assert [ln.split(",")[1] for ln in lines[1:]] == ["pretrain", "attack"]


def test_resume_does_not_repeat_epochs(trained):
    cfg, out, _ = trained
    train(cfg, out, progress=False)
    assert len((out / "history.csv").read_text().strip().splitlines()) == 3


def test_generator_attack_via_runner(trained, tmp_path):
    _, out, _ = trained
    cfg = RunConfig(dataset="objects", attacks=["none", "generator"], targets=["p2plane"],
                    budgets=[0.05], samples=2, dataset_params={"n_samples": 2},
                    attack_params={"generator": {"checkpoint": str(out / "generator.pt")}})
    run(cfg, tmp_path, progress=False)
    df = load_results(tmp_path)
    g = df[df["attack"] == "generator"]
    assert len(g) == 2 and (g["status"] != "error").all(), g["error"].tolist()
    assert (g["disp_max"] > 0).all()


def test_missing_shipped_checkpoint_is_a_clear_error():
    from icpbench.attacks.generator import resolve_checkpoint

    with pytest.raises(CheckpointError, match="no shipped generator checkpoint"):
        resolve_checkpoint("no-such-dataset", 1.0)


def test_strict_training_keeps_the_budget(tmp_path):
    cfg = train_config("quick-objects", train_samples=2, eval_samples=2, batch_size=2,
                       pretrain_epochs=0, epochs=1, strict=True, dataset_params={"n_samples": 2})
    card = train(cfg, tmp_path, progress=False)
    assert card["strict_training"] is True
    assert card["heldout_eval"]["0.05"]["disp_max_mean"] <= 0.05 + 1e-6


def test_bounded_multi_budget_training_respects_every_budget(tmp_path):
    """output=bounded: one model, lambda as a scale; every held-out displacement stays below lambda
    and the generator attack passes the budget at run time (no projection needed)."""
    cfg = train_config("quick-objects", train_samples=2, eval_samples=2, batch_size=2,
                       pretrain_epochs=0, epochs=1, budgets=[0.02, 0.05], adv_per_budget=True,
                       generator_overrides={"output": "bounded", "conditioned": False},
                       dataset_params={"n_samples": 2})
    card = train(cfg, tmp_path / "gen", progress=False)
    assert card["adv_per_budget"] is True
    for lam in ("0.02", "0.05"):
        ev = card["heldout_eval"][lam]
        assert 0 < ev["disp_max_mean"] < float(lam)
    run(RunConfig(dataset="objects", attacks=["generator"], targets=["p2plane"], budgets=[0.02, 0.05],
                  samples=2, dataset_params={"n_samples": 2},
                  attack_params={"generator": {"checkpoint": str(tmp_path / "gen" / "generator.pt")}}),
        tmp_path / "run", progress=False)
    df = load_results(tmp_path / "run")
    assert len(df) == 4 and (df["status"] != "error").all(), df["error"].tolist()
    assert (df["disp_max"] < df["budget"]).all() and (df["frac_over_budget"] == 0).all()


def test_per_budget_checkpoint_takes_precedence(tmp_path, monkeypatch):
    import icpbench.attacks.generator as ga

    (tmp_path / "generator.pt").write_bytes(b"x")
    (tmp_path / "generator-l5.pt").write_bytes(b"x")
    monkeypatch.setattr(ga, "shipped_checkpoint_dir", lambda dataset: tmp_path)
    assert ga.resolve_checkpoint("lidar-sim", 5.0).name == "generator-l5.pt"
    assert ga.resolve_checkpoint("lidar-sim", 2.0).name == "generator.pt"
    assert ga.resolve_checkpoint("lidar-sim", 2.0, str(tmp_path / "x.pt")).name == "x.pt"


def test_fine_tuning_starts_from_the_given_weights(trained, tmp_path):
    """init_checkpoint: the model starts from the checkpoint's weights and config (not a fresh
    initialisation), and the card records where it came from."""
    from icpbench.learning.checkpoint import load_checkpoint

    cfg, out, _ = trained
    ft = train_config("quick-objects", train_samples=2, eval_samples=2, batch_size=2,
                      pretrain_epochs=0, epochs=1, lr=0.0, init_checkpoint=str(out / "generator.pt"),
                      dataset_params={"n_samples": 2})
    card = train(ft, tmp_path, progress=False)
    assert card["init_checkpoint"] == str(out / "generator.pt")
    parent = load_checkpoint(out / "generator.pt").card
    assert card["init_card"] == parent  # the lineage travels with the fine-tuned model
    assert card["train_wall_s_total"] == pytest.approx(card["train_wall_s"]
                                                       + parent["train_wall_s"], abs=0.11)
    before, after = load_checkpoint(out / "generator.pt"), load_checkpoint(tmp_path / "generator.pt")
    assert after.config == before.config
    for (k, a), b in zip(after.model.state_dict().items(), before.model.state_dict().values(),
                         strict=True):
        assert torch.equal(a, b), k  # lr 0: the weights are exactly the initial checkpoint's


def test_fine_tuning_can_add_the_prior(tmp_path):
    """generator_overrides prior="sector" with init_checkpoint of a bounded model without a prior:
    the fine-tuned model takes the prior channels (gain and gate from the overrides), every old
    weight is carried over into the widened layers, and training moves the new input weights."""
    from icpbench.learning.checkpoint import load_checkpoint
    from icpbench.learning.prior import PRIOR_CHANNELS

    small = {"train_samples": 2, "eval_samples": 1, "batch_size": 2, "pretrain_epochs": 0,
             "epochs": 1, "dataset_params": {"n_samples": 2}}
    base = train_config("quick-objects", generator_overrides={"output": "bounded"}, **small)
    train(base, tmp_path / "base", progress=False)
    ft = train_config("quick-objects", lr=1e-3, init_checkpoint=str(tmp_path / "base" / "generator.pt"),
                      generator_overrides={"output": "bounded", "prior": "sector", "prior_gain": 1.5,
                                           "prior_dmax": 0.3},
                      **small)
    card = train(ft, tmp_path / "ft", progress=False)
    assert card["heldout_eval"]["0.05"]["disp_max_mean"] < 0.05
    before = load_checkpoint(tmp_path / "base" / "generator.pt")
    after = load_checkpoint(tmp_path / "ft" / "generator.pt")
    assert after.config == before.config.with_(prior="sector", prior_gain=1.5, prior_dmax=0.3)
    assert set(after.model.state_dict()) - set(before.model.state_dict()) == {"prior_gain"}
    n_old = before.model.head[0].in_channels  # head input: [features (259), prior (8), budget]
    assert after.model.head[0].in_channels == n_old + PRIOR_CHANNELS
    assert after.model.sa[0].first.in_channels == 3 + PRIOR_CHANNELS
    # the prior's input weights started at zero and received gradients
    assert after.model.sa[0].first.weight[:, 3:].abs().max() > 0
    assert after.model.head[0].weight[:, 259:259 + PRIOR_CHANNELS].abs().max() > 0


def test_iterated_prior_training_uses_and_records_its_settings(tmp_path, monkeypatch):
    """prior="sector-iter": the training prior comes from the iterated attack with the config's
    ``sector_iter`` settings (missing ones at their defaults), which the card records in full;
    the quick-lidar preset trains through the 25-iteration surrogate on exact correspondences,
    and an unknown setting is refused."""
    import icpbench.learning.training as training
    from icpbench.core.errors import InputError
    from icpbench.core.iterated_sector import SectorIterSettings

    seen = []

    def recording(config, batch, budget_m, icp=None, settings=None):
        seen.append((len(batch), settings))
        return prior_channels(config, batch, budget_m, icp, settings)

    prior_channels = training.prior_channels
    monkeypatch.setattr(training, "prior_channels", recording)
    assert train_config("quick-lidar").sector_iter == {"icp_iterations": 25, "icp_nn_reuse": 0.0}
    assert train_config("quick-objects").sector_iter == {}
    settings = {"iterations": 1, "icp_iterations": 5, "icp_nn_reuse": 0.0}
    cfg = train_config("quick-objects", train_samples=2, eval_samples=1, batch_size=2,
                       pretrain_epochs=0, epochs=1, sector_iter=settings,
                       generator_overrides={"output": "ball", "prior": "sector-iter",
                                            "prior_gain": 1.0, "prior_dmax": 0.3},
                       dataset_params={"n_samples": 2})
    card = train(cfg, tmp_path / "iter", progress=False)
    assert card["sector_iter"] == SectorIterSettings(**settings).as_dict()
    assert card["sector_iter"]["step_size"] == 0.5  # a missing setting keeps its default
    # the 2 training scans (one prior each: one budget) and the held-out one, all with these settings
    assert [n for n, _ in seen] == [1, 1, 1]
    assert all(s == SectorIterSettings(**settings) for _, s in seen)
    ev = card["heldout_eval"]["0.05"]
    assert 0 < ev["disp_max_mean"] <= 0.05 + 1e-6
    bad = train_config("quick-objects", train_samples=2, eval_samples=1, batch_size=2,
                       pretrain_epochs=0, epochs=1, sector_iter={"icp_stride": 2},
                       generator_overrides=cfg.generator_overrides, dataset_params={"n_samples": 2})
    with pytest.raises(InputError, match="unknown setting.*'icp_stride'"):
        train(bad, tmp_path / "bad", progress=False)
