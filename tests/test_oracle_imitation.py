"""Learning from the oracle: the PGD answer cache (icpbench/learning/oracle_cache.py) and the
imitation loss in training."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from icpbench.core.errors import InputError
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.learning.losses import imitation_loss
from icpbench.learning.oracle_cache import OracleCache, OracleSpec, assigned_budget
from icpbench.learning.training import train, train_config
from icpbench.targets.p2plane import PointToPlaneICP


def test_imitation_loss_is_zero_at_the_target_and_four_at_the_mirror():
    x = torch.randn(2, 50, 3, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(2, 50, 3, dtype=torch.float64), dim=-1) * 0.5
    lam = torch.tensor([0.5, 0.5], dtype=torch.float64)
    assert torch.allclose(imitation_loss(x, x + d, d, lam), torch.zeros(2, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(imitation_loss(x, x - d, d, lam), torch.full((2,), 4.0, dtype=torch.float64))
    assert torch.allclose(imitation_loss(x, x, d, lam), torch.ones(2, dtype=torch.float64))


def test_assigned_budget_is_stable_and_spread():
    budgets = [1.0, 2.0, 3.0, 4.0, 5.0]
    ids = [f"lidar-sim/pass3/{i:06d}" for i in range(200)]
    got = [assigned_budget(i, budgets) for i in ids]
    assert got == [assigned_budget(i, budgets) for i in ids]
    counts = np.unique(got, return_counts=True)[1]
    assert len(counts) == 5 and counts.min() >= 20


def test_cache_answers_beat_their_start_resume_and_refuse_other_settings(tmp_path):
    samples = [scene_sample(400, 4_000, seed=s, noise_m=0.02) for s in range(3)]
    icp = PointToPlaneICP()
    cache = OracleCache(tmp_path, OracleSpec(steps=3, init="sector"))
    disp = cache.ensure(samples, [0.3, 0.3, 0.5], icp)
    for d, lam, s in zip(disp, [0.3, 0.3, 0.5], samples, strict=True):
        assert d.shape == s.scan.shape and d.dtype == np.float32
        assert np.linalg.norm(d, axis=1).max() <= lam + 1e-6
        with np.load(cache.path(s.id, lam)) as f:  # the ascent never ends below its start
            assert float(f["objective"]) >= float(f["start_objective"]) - 1e-9
    stamps = [cache.path(s.id, b).stat().st_mtime_ns for s, b in zip(samples, [0.3, 0.3, 0.5],
                                                                      strict=True)]
    again = OracleCache(tmp_path, OracleSpec(steps=3, init="sector")).ensure(
        samples, [0.3, 0.3, 0.5], icp)
    assert all(np.array_equal(a, b) for a, b in zip(disp, again, strict=True))
    assert stamps == [cache.path(s.id, b).stat().st_mtime_ns
                      for s, b in zip(samples, [0.3, 0.3, 0.5], strict=True)]
    with pytest.raises(InputError, match="other settings"):
        OracleCache(tmp_path, OracleSpec(steps=5))
    with pytest.raises(InputError, match="no oracle answer"):
        cache.load(samples[0].id, 0.7)


def test_imitation_training_moves_the_generator_towards_the_oracle(tmp_path):
    """Imitation alone (alpha = 0): the loss (= the imitation loss; the bounded output keeps the
    reconstruction term at 0) falls over the epochs, and the card and the cache record it."""
    cfg = train_config("quick-objects", train_samples=4, eval_samples=1, batch_size=2,
                       pretrain_epochs=0, epochs=4, lr=3e-3, alpha=0.0, imitation=1.0,
                       oracle={"steps": 2, "init": "sector"}, generator_overrides={
                           "output": "bounded"}, dataset_params={"n_samples": 4})
    card = train(cfg, tmp_path, progress=False)
    assert card["imitation"]["weight"] == 1.0 and card["imitation"]["oracle"]["steps"] == 2
    files = sorted((tmp_path / "oracle").glob("*.npz"))
    assert len(files) == 4 and json.loads((tmp_path / "oracle" / "spec.json").read_text())["steps"] == 2
    hist = pd.read_csv(tmp_path / "history.csv")
    assert len(hist) == 4 and hist["loss"].iloc[-1] < hist["loss"].iloc[0]
    assert hist["l_adv"].eq(0).all()  # alpha = 0: no ICP ran in the training step
