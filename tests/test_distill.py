"""The distilled generator (icpbench.learning.distill): targets, the start point, training."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.iterated_sector import SectorIterSettings, iterated_sector
from icpbench.core.types import Batch
from icpbench.learning.distill import (
    QUANT,
    DistillConfig,
    TargetSpec,
    distilled_model,
    load_targets,
    make_targets,
    quantise,
    train_distilled,
    unit_displacement,
)
from icpbench.learning.geometry import compute_geometry
from icpbench.targets.p2plane import PointToPlaneICP

PARAMS = {"n_samples": 3, "n_scan": 600, "n_map": 6000}
SPEC = TargetSpec(dataset="synthetic", dataset_params=PARAMS, samples=3, budgets=(1.0, 2.0),
                  cheap={"iterations": 0}, target={"iterations": 2}, chunk=2)


@pytest.fixture(scope="module")
def targets(tmp_path_factory):
    out = tmp_path_factory.mktemp("targets")
    written = make_targets(SPEC, out)
    return out, written


def test_targets_hold_both_attacks_per_scan_and_budget_and_resume(targets):
    out, written = targets
    assert [p.name for p in written] == ["chunk_00000.npz", "chunk_00002.npz"]
    d = load_targets(out)
    assert d.scan.shape == (3, 600, 3) and d.cheap.shape == d.target.shape == (3, 2, 600, 3)
    assert d.cheap.dtype == np.int8 and d.fps.shape[0] == 3
    # the stored cheap displacement is the iterated attack's own (to the int8 step)
    ds = registry.datasets.get("synthetic").create(seed=0, split="train", **PARAMS)
    b = Batch.from_samples([ds[2]])
    r = iterated_sector(b, 2.0, PointToPlaneICP("lidar"), SectorIterSettings(iterations=0))
    want = (r.scans[0] - b.scans[0].numpy()) / 2.0
    assert np.abs(d.cheap[2, 1] / QUANT - want).max() <= 0.5 / QUANT + 1e-9
    assert np.linalg.norm(d.target / QUANT, axis=-1).max() <= 1 + np.sqrt(3) * 0.5 / QUANT
    assert make_targets(SPEC, out) == []  # resumed: nothing left to do
    with pytest.raises(InputError, match="another spec"):
        make_targets(TargetSpec(**{**SPEC.as_dict(), "samples": 2}), out)


def test_quantise_round_trip_is_within_half_a_step():
    u = np.random.default_rng(0).uniform(-1, 1, (1000, 3))
    assert np.abs(quantise(u) / QUANT - u).max() <= 0.5 / QUANT + 1e-12


def test_given_fps_gives_the_geometry_computed_here(targets):
    d = load_targets(targets[0])
    cfg = distilled_model().config.geometry
    a, b = compute_geometry(d.scan[1], cfg), compute_geometry(d.scan[1], cfg, fps=d.fps[1])
    assert all(torch.equal(x, y) for x, y in zip(a.groups, b.groups, strict=True))
    assert all(torch.equal(x, y) for x, y in zip(a.interp_idx, b.interp_idx, strict=True))
    with pytest.raises(InputError, match="fps must be"):
        compute_geometry(d.scan[1], cfg, fps=d.fps[1][:-1])


def test_untrained_model_returns_the_cheap_attack_exactly(targets):
    d = load_targets(targets[0])
    m = distilled_model().eval()
    x = torch.as_tensor(d.scan[:2])
    geo = m.precompute(x)
    cheap = torch.as_tensor(d.cheap[:2, 1]).float() / QUANT
    prior = torch.cat([cheap, torch.as_tensor(d.stat[:2].astype(np.float32))], -1)
    with torch.no_grad():
        u = unit_displacement(m, x, geo, torch.full((2,), 2.0), prior)
    # the ball output keeps it as is (the int8 rounding's few points just outside: projected)
    want = cheap / torch.linalg.norm(cheap, dim=-1, keepdim=True).clamp(min=1.0)
    assert torch.allclose(u, want, atol=1e-5)


@pytest.mark.parametrize("loss", ["mse", "align"])
def test_training_fits_the_target_and_writes_a_loadable_generator(targets, tmp_path, loss):
    from icpbench.attacks.generator import GeneratorAttack

    out = tmp_path / "gen"
    card = train_distilled(targets[0], out, DistillConfig(epochs=6, batch_size=2, lr=3e-3,
                                                          val_scans=0, loss=loss))
    hist = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    assert hist["train_loss"][-1] < hist["train_loss"][0]  # it learns the training targets
    assert card["epochs_done"] == 6 and card["distill_target"]["iterations"] == 2
    meta = json.loads((out / "generator.json").read_text())
    assert meta["config"]["prior"] == "sector-iter" and meta["config"]["output"] == "ball"
    ds = registry.datasets.get("synthetic").create(seed=0, split="test", **PARAMS)
    b = Batch.from_samples([ds[0], ds[1]])
    att = GeneratorAttack(checkpoint=str(out / "generator.pt"),
                          sector_iter={"iterations": 0})
    res = att.run(b, 1.0, surrogate=PointToPlaneICP("lidar"))
    assert float(res.stats["frac_over_budget"].max()) == 0.0
    assert float(torch.linalg.norm(res.scans - b.scans, dim=-1).max()) > 0.5  # it moved points


def test_bad_settings_are_refused(targets, tmp_path):
    with pytest.raises(InputError, match="loss must be"):
        train_distilled(targets[0], tmp_path / "x", DistillConfig(loss="l1"))
    with pytest.raises(InputError, match="none for training"):
        train_distilled(targets[0], tmp_path / "x", DistillConfig(val_scans=3))
    with pytest.raises(InputError, match="no target shards"):
        train_distilled(tmp_path, tmp_path / "x", DistillConfig())
    with pytest.raises(InputError, match="iterations"):
        TargetSpec(target={"iterations": -1}).check()
