"""Matrix products of the generator's shared MLPs by numpy's BLAS, with and without autograd.

The generator's 1x1 convolutions are products ``W X + b`` of a small weight (O, I) with a very wide
activation (I, P) (P = S * K grouped rows: 320,000 for a 10,000-point scan's first level). On the
project's AMD EPYC core PyTorch's CPU GEMM (MKL) runs these skinny products 2-3x slower than the
OpenBLAS in numpy's wheels (docs/performance.md, sections 7 and 10; one thread each, I = 32,
P = 320,000: forward 43 / 80 ms against 13 / 26 ms for O = 32 / 64, backward products 57 against
39 ms). :func:`linear` computes the same function as ``torch.addmm`` through numpy, forward and
backward, so training gets the faster products too; :func:`blas_threads` keeps numpy's BLAS at
torch's thread count.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from threadpoolctl import ThreadpoolController

_BLAS: ThreadpoolController | None = None


def blas_threads():
    """Context manager limiting numpy's BLAS to torch's thread count (numpy's OpenBLAS would
    otherwise start one thread per core: measured 3x slower in CPU time on the shared 2 cores)."""
    global _BLAS
    if _BLAS is None:
        from threadpoolctl import ThreadpoolController

        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=torch.get_num_threads(), user_api="blas")


def mm(x: Tensor, w_t: Tensor, out: Tensor) -> Tensor:
    """``out = x @ w_t`` by numpy's BLAS: x (P, I), w_t (I, O), out (P, O) contiguous CPU tensors
    of one dtype, no autograd."""
    np.matmul(x.numpy(), w_t.numpy(), out=out.numpy())
    return out


class _Linear(torch.autograd.Function):
    """``W X + b`` for W (O, I), X (I, P), b (O,) -> (O, P), every product by numpy's BLAS."""

    @staticmethod
    def forward(ctx: Any, w: Tensor, x: Tensor, b: Tensor) -> Tensor:
        ctx.save_for_backward(w, x)
        out = torch.empty((w.shape[0], x.shape[1]), dtype=x.dtype)
        with blas_threads():
            np.matmul(w.detach().numpy(), x.detach().numpy(), out=out.numpy())
        return out.add_(b[:, None])

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        w, x = ctx.saved_tensors
        g_np = g.contiguous().numpy()
        gw = gx = gb = None
        with blas_threads():
            if ctx.needs_input_grad[0]:
                gw = torch.from_numpy(g_np @ x.detach().numpy().T)  # (O, I)
            if ctx.needs_input_grad[1]:
                gx = torch.from_numpy(w.detach().numpy().T @ g_np)  # (I, P)
        if ctx.needs_input_grad[2]:
            gb = g.sum(1)
        return gw, gx, gb


def linear(w: Tensor, x: Tensor, b: Tensor) -> Tensor:
    """``torch.addmm(b[:, None], w, x)`` by numpy's BLAS, differentiable in all three.

    Args:
        w: (O, I) weight; x: (I, P) contiguous activations; b: (O,) bias. CPU, float32 or
            float64, one dtype.

    Returns:
        (O, P) tensor of x's dtype; the same values as ``torch.addmm`` within float rounding.
    """
    return _Linear.apply(w, x, b)


def eligible(*tensors: Tensor) -> bool:
    """Whether :func:`linear` applies: CPU float32/float64 tensors of one dtype, x contiguous."""
    dt = tensors[0].dtype
    return all(t.device.type == "cpu" and t.dtype == dt for t in tensors) and dt in (
        torch.float32, torch.float64) and tensors[1].is_contiguous()
