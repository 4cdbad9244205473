"""Queries answered by a target's exact replica: the attacks see the same answers, the runner's
rows stay the target's own, and a non-differentiable answerer is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from icpbench.attacks.ensemble import EnsembleAttack, column
from icpbench.core.errors import InputError
from icpbench.harness.results import load_results
from icpbench.harness.runner import RunConfig, config_differences, run
from icpbench.targets.kiss import KissICPTarget
from icpbench.targets.kiss_replica import KissICPReplica
from icpbench.targets.oracle import QueryOracle
from icpbench.targets.p2plane import PointToPlaneICP
from icpbench.targets.p2point import PointToPointICP
from icpbench.targets.point_forward import CompiledPointICP
from icpbench.targets.small_gicp import SmallGICPTarget

LAM = 0.3
MEMBERS = ("uniform", "sector-adaptive", "spoof", "valley")


def _ensemble_run(batch, oracle):
    ens = EnsembleAttack(members=",".join(MEMBERS), sector_iterations=2, spoof_queries=6,
                         valley_queries=4)
    return ens.run(batch, LAM, surrogate=None, generator=0, oracle=oracle)


def test_kiss_replica_answers_the_queries_exactly_as_kiss(scene_pair):
    """Every member's error, the chosen scans and the query counts are KISS's own when its
    replica answers; the final scans registered by KISS itself give the recorded worst case."""
    batch = scene_pair
    kiss = KissICPTarget("lidar")
    replica = kiss.exact_replica()
    assert isinstance(replica, CompiledPointICP) and isinstance(replica.of, KissICPReplica)
    by_kiss = QueryOracle.prepared(kiss, batch)
    answered = QueryOracle.prepared(kiss, batch, answer_with=replica)
    assert answered.name == "kiss-icp" and answered.target is kiss  # the cost model read is KISS's
    a, b = _ensemble_run(batch, by_kiss), _ensemble_run(batch, answered)
    for m in MEMBERS:
        np.testing.assert_allclose(b.extra[column(m)].numpy(), a.extra[column(m)].numpy(),
                                   rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.scans.numpy(), a.scans.numpy(), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(b.extra["queries"].numpy(), a.extra["queries"].numpy())
    np.testing.assert_array_equal(answered.queries, by_kiss.queries)
    worst = np.stack([b.extra[column(m)].numpy() for m in MEMBERS]).max(axis=0)
    np.testing.assert_allclose(QueryOracle.prepared(kiss, batch).errors(b.scans), worst,
                               rtol=0, atol=1e-6)


def test_only_measured_replicas_answer_and_they_must_take_the_batch_maps(scene_pair):
    p2point = PointToPointICP("lidar")
    assert isinstance(p2point.exact_replica(), CompiledPointICP)  # its compiled forward pass
    assert PointToPointICP("lidar", nn_reuse_m=0.05).exact_replica() is None  # approximate
    assert PointToPlaneICP("lidar").exact_replica() is None  # no compiled plane pass
    assert SmallGICPTarget("lidar").exact_replica() is None  # its replica differs by millimetres
    kiss = KissICPTarget("lidar")
    with pytest.raises(InputError, match="differentiable"):
        QueryOracle.prepared(kiss, scene_pair, answer_with=KissICPTarget("lidar"))


def test_who_answers_is_an_execution_setting_recorded_but_never_a_difference():
    on, off = RunConfig(), RunConfig(replica_queries=False)
    assert on.replica_queries is True
    stored = {**on.__dict__}
    assert config_differences(stored, {**off.__dict__}) == []
    with pytest.raises(InputError, match="--replica-queries must be true or false"):
        RunConfig(replica_queries="sometimes").validate()  # type: ignore[arg-type]


def test_a_run_gives_the_same_rows_whoever_answers_and_resumes_across_the_setting(tmp_path):
    """A KISS-ICP run of a query attack with and without its replica answering: equal rows (the
    runner registers the output with KISS itself); the setting is recorded, and a resume with
    the other one computes nothing new."""
    syn = dict(dataset="synthetic", targets=["kiss-icp"], surrogate="self", budgets=[LAM],
               samples=1, dataset_params={"n_samples": 1, "n_scan": 400, "n_map": 4000},
               attacks=["spoof"], attack_params={"spoof": {"queries": 4}})
    rows = {}
    for flag in (True, False):
        out = tmp_path / str(flag)
        run(RunConfig(**syn, replica_queries=flag), out, progress=False)
        rows[flag] = load_results(out)
    cols = ["sample_id", "attack", "trans_err_xy", "iterations", "status"]
    assert rows[True][cols].equals(rows[False][cols])
    assert json.loads((tmp_path / "True" / "manifest.json").read_text())["config"][
        "replica_queries"] is True
    run(RunConfig(**syn, replica_queries=False), tmp_path / "True", progress=False)
    assert load_results(tmp_path / "True")[cols].equals(rows[True][cols])
