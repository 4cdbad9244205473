"""Data-parallel generator training with PyTorch's DistributedDataParallel, launched by ``torchrun``.

Usage (one machine, 4 GPUs; every process trains on its own shard of the training subset and DDP
averages the gradients, so the effective batch is ``4 x batch_size``)::

    torchrun --standalone --nproc_per_node 4 -m icpbench.cli train --preset paper-lidar \\
        --device cuda --out runs/gen

``torchrun`` starts the processes and sets ``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``
and ``MASTER_PORT``; :func:`setup` reads them, joins the process group (NCCL on CUDA, gloo on CPU)
and gives process ``LOCAL_RANK`` the GPU ``cuda:LOCAL_RANK``. Without those variables (a plain
``icpbench train``) nothing here does anything and training is exactly the single-process loop.

Division of labour: every rank builds the same model from the same seed (DDP also broadcasts rank
0's weights when it wraps the model), loads only its shard (:func:`shard_indices`), and runs the
differentiable ICP of its own samples; DDP all-reduces the gradients during ``backward``. Only rank
0 writes files (checkpoint, optimiser state, history, model card) and runs the held-out evaluation;
the others wait at a barrier, so a resumed run finds one consistent checkpoint. The output folder
must be visible to every rank (always true on one machine; use a shared filesystem across nodes).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from icpbench.core.errors import InputError

#: Environment variables torchrun sets in every process it starts.
TORCHRUN_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


@dataclass(frozen=True)
class DistContext:
    """Where this process sits in the job.

    Attributes:
        rank: global rank (0 .. world_size - 1); rank 0 writes files.
        world_size: number of processes.
        local_rank: rank on this machine (selects the GPU).
        enabled: launched by torchrun (a process group exists and the model is wrapped in DDP).
        backend: ``"nccl"`` or ``"gloo"`` when enabled.
        owns_group: this module created the process group (and :func:`cleanup` destroys it).
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    enabled: bool = False
    backend: str | None = None
    owns_group: bool = False

    @property
    def is_main(self) -> bool:
        """Whether this process writes files and logs (rank 0)."""
        return self.rank == 0


def _env_int(name: str) -> int:
    raw = os.environ.get(name, "")
    try:
        return int(raw)
    except ValueError:
        raise InputError(f"environment variable {name}={raw!r} must be an integer (it is set by "
                         "torchrun; launch with `torchrun --nproc_per_node N ...`)") from None


def env_context() -> DistContext:
    """Read torchrun's variables (no process group is created).

    Raises:
        InputError: some but not all of torchrun's variables are set, or they are inconsistent.
    """
    present = [v for v in TORCHRUN_VARS if v in os.environ]
    if "RANK" not in os.environ and "WORLD_SIZE" not in os.environ:
        return DistContext()
    missing = [v for v in TORCHRUN_VARS if v not in present]
    if missing:
        raise InputError(f"distributed training needs {', '.join(TORCHRUN_VARS)} (torchrun sets them "
                         f"all); missing: {', '.join(missing)}")
    rank, world, local = _env_int("RANK"), _env_int("WORLD_SIZE"), _env_int("LOCAL_RANK")
    if world < 1 or not 0 <= rank < world or local < 0:
        raise InputError(f"inconsistent torchrun variables RANK={rank}, WORLD_SIZE={world}, "
                         f"LOCAL_RANK={local}")
    return DistContext(rank=rank, world_size=world, local_rank=local, enabled=True)


def resolve_device(device: str, ctx: DistContext) -> str:
    """The device this process trains on: ``device`` itself when not distributed, else
    ``cuda:LOCAL_RANK`` for CUDA (one GPU per process).

    Raises:
        InputError: the device is not ``cpu``/``cuda[:i]``, CUDA is not available, or there are
            fewer GPUs than processes on this machine.
    """
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"unknown device {device!r}; use cpu or cuda") from exc
    if dev.type == "cpu":
        return device
    if dev.type != "cuda":
        raise InputError(f"device {device!r} is not supported; use cpu or cuda")
    if not torch.cuda.is_available():
        raise InputError(f"device {device!r} requested but this PyTorch build sees no CUDA GPU "
                         "(install a CUDA build of torch, or use --device cpu)")
    if not ctx.enabled:
        return device
    n = torch.cuda.device_count()
    if ctx.local_rank >= n:
        raise InputError(f"process LOCAL_RANK={ctx.local_rank} has no GPU: this machine has {n}; "
                         f"start at most {n} processes per node (--nproc_per_node {n})")
    return f"cuda:{ctx.local_rank}"


def setup(device: str) -> tuple[DistContext, str]:
    """Join torchrun's process group if launched by torchrun; return the context and the device.

    Without torchrun this returns ``(DistContext(), device)`` after checking that the device
    exists, and creates nothing.
    """
    ctx = env_context()
    dev = resolve_device(device, ctx)
    if not ctx.enabled:
        return ctx, dev
    backend = "nccl" if dev.startswith("cuda") else "gloo"
    owns = False
    if not dist.is_initialized():
        if dev.startswith("cuda"):
            torch.cuda.set_device(dev)
        dist.init_process_group(backend=backend)
        owns = True
    else:
        backend = dist.get_backend()
    return DistContext(rank=ctx.rank, world_size=ctx.world_size, local_rank=ctx.local_rank,
                       enabled=True, backend=backend, owns_group=owns), dev


def wrap_model(model: torch.nn.Module, ctx: DistContext, device: str) -> torch.nn.Module:
    """``model`` itself, or ``DistributedDataParallel(model)`` when distributed (gradients are
    averaged over ranks in ``backward``). The optimiser keeps using ``model.parameters()``."""
    if not ctx.enabled:
        return model
    from torch.nn.parallel import DistributedDataParallel

    if device.startswith("cuda"):
        idx = torch.device(device).index
        return DistributedDataParallel(model, device_ids=[idx], output_device=idx)
    return DistributedDataParallel(model)


def shard_indices(n: int, ctx: DistContext) -> list[int]:
    """This rank's share of ``range(n)``: ``rank, rank + W, rank + 2W, ...`` (W = world size).

    Every rank gets ``ceil(n / W)`` indices (DDP needs the same number of steps on every rank):
    when ``W`` does not divide ``n``, the last round wraps around to the first samples, as
    ``torch.utils.data.DistributedSampler`` pads. With one process this is ``range(n)``.
    """
    if n < 0:
        raise InputError(f"cannot shard {n} samples")
    if not ctx.enabled or ctx.world_size == 1:
        return list(range(n))
    if n == 0:
        return []
    per_rank = -(-n // ctx.world_size)
    return [(ctx.rank + k * ctx.world_size) % n for k in range(per_rank)]


def all_reduce_sums(values: Mapping[str, float], ctx: DistContext) -> dict[str, float]:
    """Sum scalars over ranks (for epoch statistics); identity when not distributed."""
    if not ctx.enabled:
        return dict(values)
    keys = sorted(values)
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64)
    if ctx.backend == "nccl":
        t = t.cuda()
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return {k: float(v) for k, v in zip(keys, t.cpu().tolist(), strict=True)}


def broadcast(obj: Any, ctx: DistContext) -> Any:
    """Rank 0's ``obj`` on every rank (a stop decision, the model card); identity when not
    distributed. ``obj`` must be picklable."""
    if not ctx.enabled:
        return obj
    box = [obj if ctx.is_main else None]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def all_gather(obj: Any, ctx: DistContext) -> list[Any]:
    """Every rank's ``obj``, in rank order (``[obj]`` when not distributed)."""
    if not ctx.enabled:
        return [obj]
    out: list[Any] = [None] * ctx.world_size
    dist.all_gather_object(out, obj)
    return out


def barrier(ctx: DistContext) -> None:
    """Wait for every rank (e.g. until rank 0 has written the checkpoint)."""
    if ctx.enabled:
        if ctx.backend == "nccl":
            dist.barrier(device_ids=[torch.cuda.current_device()])
        else:
            dist.barrier()


def cleanup(ctx: DistContext) -> None:
    """Destroy the process group if :func:`setup` created it."""
    if ctx.enabled and ctx.owns_group and dist.is_initialized():
        dist.destroy_process_group()


def describe(ctx: DistContext, batch_size: int) -> dict[str, Any]:
    """What the model card records about a distributed run."""
    return {"world_size": ctx.world_size, "backend": ctx.backend,
            "batch_size_per_rank": batch_size, "effective_batch_size": batch_size * ctx.world_size}
