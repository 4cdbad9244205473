"""Data-parallel training (icpbench.learning.distributed): sharding, torchrun's variables, and a real
``torchrun --nproc_per_node 2`` run of ``icpbench train`` in a CPU gloo process group.

The torchrun run trains with 2 ranks x batch 1 on samples {0, 1}; DDP averages the two gradients,
which is the gradient of the single-process loss on the batch {0, 1} (the losses are batch means and
the generator normalises per sample), so its weights must equal single-process training with batch
2, and differ from training on sample 0 alone.
"""

import json
import os
import subprocess
import sys

import pytest
import torch

from icpbench.core.errors import InputError
from icpbench.learning import distributed as ddp
from icpbench.learning.training import train, train_config

torch.set_num_threads(1)


def test_shards_are_disjoint_equal_and_cover_everything():
    for n, world in [(10, 2), (7, 3), (2, 2), (5, 8), (1, 4)]:
        shards = [ddp.shard_indices(n, ddp.DistContext(rank=r, world_size=world, enabled=True))
                  for r in range(world)]
        assert {len(s) for s in shards} == {-(-n // world)}  # same number of steps on every rank
        assert set().union(*shards) == set(range(n))
        if n % world == 0:
            assert sum(len(s) for s in shards) == n  # no padding when W divides n
    assert ddp.shard_indices(5, ddp.DistContext()) == [0, 1, 2, 3, 4]
    assert ddp.shard_indices(7, ddp.DistContext(rank=1, world_size=3, enabled=True)) == [1, 4, 0]


def test_torchrun_variables(monkeypatch):
    for v in ddp.TORCHRUN_VARS:
        monkeypatch.delenv(v, raising=False)
    assert ddp.env_context() == ddp.DistContext() and not ddp.DistContext().enabled
    ctx, dev = ddp.setup("cpu")  # no torchrun: nothing is created
    assert not ctx.enabled and dev == "cpu" and not torch.distributed.is_initialized()
    monkeypatch.setenv("RANK", "1")
    with pytest.raises(InputError, match="missing: WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT"):
        ddp.env_context()
    for k, v in dict(WORLD_SIZE="2", LOCAL_RANK="1", MASTER_ADDR="x", MASTER_PORT="1").items():
        monkeypatch.setenv(k, v)
    ctx = ddp.env_context()
    assert (ctx.rank, ctx.world_size, ctx.local_rank, ctx.enabled, ctx.is_main) == (1, 2, 1, True, False)
    monkeypatch.setenv("RANK", "2")
    with pytest.raises(InputError, match="inconsistent torchrun variables RANK=2, WORLD_SIZE=2"):
        ddp.env_context()
    monkeypatch.setenv("RANK", "one")
    with pytest.raises(InputError, match="RANK='one' must be an integer"):
        ddp.env_context()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error of a CPU-only PyTorch")
def test_cuda_on_a_cpu_build_is_a_clear_error():
    with pytest.raises(InputError, match="sees no CUDA GPU .*use --device cpu"):
        ddp.resolve_device("cuda", ddp.DistContext())
    with pytest.raises(InputError, match="unknown device 'gpu7'"):
        ddp.resolve_device("gpu7", ddp.DistContext())


def _config(**kw):
    base = dict(train_samples=2, eval_samples=1, batch_size=2, pretrain_epochs=1, epochs=1,
                dataset_params={"n_samples": 4})
    return train_config("quick-objects", **{**base, **kw})


def _weights(out) -> dict[str, torch.Tensor]:
    return torch.load(out / "generator.pt", weights_only=True)


@pytest.mark.slow
def test_torchrun_two_gloo_ranks_equal_single_process_training(tmp_path):
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "icpbench.cli", "train", "--preset", "quick-objects", "--train-samples", "2",
           "--eval-samples", "1", "--batch-size", "1", "--pretrain-epochs", "1", "--epochs", "1",
           "--dataset-param", "n_samples=4", "--threads", "1", "--out", str(out), "--quiet"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert res.stdout.count("checkpoint: ") == 2  # both ranks finished (and got the card)

    meta = json.loads((out / "generator.json").read_text())
    card = meta["card"]
    assert card["distributed"] == {"world_size": 2, "backend": "gloo", "batch_size_per_rank": 1,
                                   "effective_batch_size": 2}
    assert card["data"]["samples"] == 2 and card["epochs_done"] == 2
    assert card["heldout_eval"]["0.05"]["samples"] == 1
    history = (out / "history.csv").read_text().strip().splitlines()
    assert [ln.split(",")[:2] for ln in history[1:]] == [["1", "pretrain"], ["2", "attack"]]
    assert not [p.name for p in out.iterdir() if "tmp" in p.name]  # rank 0 wrote each file once

    # single process, batch 2 on the same two samples: the same weights
    single = tmp_path / "single"
    train(_config(), single, progress=False)
    w_ddp, w_one = _weights(out), _weights(single)
    assert w_ddp.keys() == w_one.keys()
    for k in w_one:
        torch.testing.assert_close(w_ddp[k], w_one[k], rtol=1e-5, atol=1e-6, msg=k)
    # and the test has teeth: sample 0 alone (what rank 0 would train on without gradient
    # averaging) gives other weights
    alone = tmp_path / "alone"
    train(_config(train_samples=1, batch_size=1), alone, progress=False)
    w_alone = _weights(alone)
    assert max(float((w_alone[k] - w_one[k]).abs().max()) for k in w_one) > 1e-5
