"""Inference pass of the PointNet++ generator without autograd: channels-last and allocation-free.

The same function as :meth:`Generator.encode` + :meth:`Generator.decode` (equal within float32
rounding; tests/test_generator_fast.py compares the two), rearranged for a CPU without a graph
(profiles in docs/performance.md):

* **channels-last** ``(points, channels)`` rows, so every shared-MLP layer is one matrix product
  and the max over the K neighbours reduces over a middle axis (measured 5-10x faster than
  ``max(dim=3)`` on ``(B, C, S, K)``);
* **matrix products by numpy's BLAS** (OpenBLAS in numpy's wheels) into preallocated buffers, with
  as many BLAS threads as torch has (``threadpoolctl``): on the project's AMD EPYC core the
  shared-MLP products of a 10,000-point scan took 152 ms against 207 ms for ``torch.addmm``
  (PyTorch's MKL), 2.3x faster for the skinny 32-channel products of level 1;
* **no fresh large buffers**: the (S * K, C) activations (up to 80 MB at N = 10,000) live in a
  workspace kept on the model and reused call after call. A new buffer of that size costs page
  faults on every call (measured: a 41 MB ``clone`` took 20 ms, a copy into an existing buffer
  4 ms);
* **GroupNorm as a per-channel affine map** ``a_c x + b_c`` from channel sums and norms (mean and
  biased variance of each group of channels, ``eps`` as the module); the convolution's bias only
  shifts the channel means, so it is folded into ``b`` instead of being added to every row;
* **normalisation and ReLU folded into the next layer**: ``relu(a x + b) = a clamp(x, t) + b``
  with ``t = -b / a`` (a lower bound for ``a > 0``, an upper bound for ``a < 0``), so a hidden
  layer costs one in-place ``clamp`` and the next product uses ``W diag(a)`` and the bias
  ``bias + W b`` (``a = 0``: the constant ``relu(b)``);
* **the last layer of a set abstraction is reduced before it is normalised**:
  ``max_k relu(a x_k + b) = relu(a max_k x_k + b)`` for ``a >= 0`` and ``relu(a min_k x_k + b)``
  for ``a < 0``, so the largest tensor of each level is only read once more;
* **interpolation as k weighted row gathers** (``index_select`` + ``addcmul``) instead of a
  batched (1 x k) x (k x C) product: 0.5 against 5.8 ms per level;
* **constant head inputs folded into the bias**: the budget channel of conditioned models enters
  every point equally, so ``W [h; c] + b = W_h h + (b + c W_c)``.

Used by :meth:`Generator.forward` when autograd is off and the device is the CPU
(:func:`eligible`); training keeps the autograd path.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from icpbench.learning.blas import blas_threads, mm

if TYPE_CHECKING:
    from icpbench.learning.geometry import Geometry
    from icpbench.learning.network import Generator, SetAbstraction

#: Rows per block of the normalisation statistics (4,096 x 64 float32 = 1 MB: stays in cache;
#: 16,384 rows measured the same, 65,536 slower).
_BLOCK_ROWS = 4096
#: Bytes of the widest layer's rows per block of a set-abstraction pass (whole groups of K rows).
_BLOCK_BYTES = 2**21

class Workspace:
    """Named flat buffers reused across calls (grown when a larger shape is asked for)."""

    def __init__(self) -> None:
        self._buf: dict[str, Tensor] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
        """A contiguous tensor of ``shape`` backed by the buffer ``name`` (contents undefined)."""
        n = 1
        for s in shape:
            n *= int(s)
        buf = self._buf.get(name)
        if buf is None or buf.numel() < n or buf.dtype != dtype:
            buf = torch.empty(n, dtype=dtype)
            self._buf[name] = buf
        return buf[:n].view(shape)


def eligible(model: Generator, x: Tensor) -> bool:
    """Whether :func:`forward` applies: no autograd, CPU tensors."""
    return not torch.is_grad_enabled() and x.device.type == "cpu"


class _Stats:
    """Running channel sums of rows y (P, C) for a GroupNorm: ``sum(y)`` and the shifted
    ``sum((y - s)^2)`` accumulated in float64 block by block, with s the mean of the first rows
    seen (no cancellation in the variance); a block that was just written is still in cache when
    it is added, so the statistics cost no extra pass over memory."""

    def __init__(self, channels: int, ws: Workspace) -> None:
        self.ws = ws
        self.rows = 0
        self.shift: Tensor | None = None
        self.s1 = torch.zeros(channels, dtype=torch.float64)
        self.s2 = torch.zeros(channels, dtype=torch.float64)

    def add(self, y: Tensor) -> None:
        """Add rows y (P, C) (a block of the layer's output)."""
        if self.shift is None:
            self.shift = y[:256].mean(0)
        step = max(_BLOCK_ROWS, _BLOCK_BYTES // (y.shape[1] * y.element_size()))
        for i in range(0, y.shape[0], step):
            blk = y[i:i + step]
            self.s1 += blk.sum(0)  # sum(y); the shift is taken off in affine()
            # (y - s)^2 in one elementwise pass (measured 30% faster than sub + square)
            self.s2 += F.mse_loss(blk, self.shift.expand_as(blk), reduction="none").sum(0)
        self.rows += int(y.shape[0])

    def affine(self, norm: nn.Module, bias: Tensor) -> tuple[Tensor, Tensor]:
        """Per-channel (a, b) (C,) float64 such that ``norm(y + bias) = a * y + b`` over all rows
        added (``bias`` (C,): the convolution's bias, not added to y). The bias moves every row of
        a channel alike, so the sums about ``s`` are those of ``y + bias`` about ``s + bias``."""
        bias = bias.double()
        C = self.s1.shape[0]
        assert self.shift is not None
        G, P = norm.num_groups, self.rows
        cnt = P * (C // G)
        sh = self.shift.double() + bias
        s1 = self.s1 - P * self.shift.double()  # sum(y - s)
        m1 = (s1 + P * sh).view(G, -1).sum(1) / cnt  # group mean of y + bias
        # group variance: mean over the group of E[(y - s)^2] minus (mean - s)^2 per channel shift
        d = sh.view(G, -1) - m1[:, None]
        e2 = (self.s2.view(G, -1) + 2 * d * s1.view(G, -1) + P * d * d).sum(1) / cnt
        rstd = torch.rsqrt(e2.clamp_min(0.0) + norm.eps).repeat_interleave(C // G)
        a = norm.weight.detach().double() * rstd
        b = norm.bias.detach().double() - m1.repeat_interleave(C // G) * a
        return a, b + a * bias


def _affine(y: Tensor, norm: nn.Module, bias: Tensor, ws: Workspace) -> tuple[Tensor, Tensor]:
    """:meth:`_Stats.affine` of all rows y (P, C) at once."""
    st = _Stats(y.shape[1], ws)
    st.add(y)
    return st.affine(norm, bias)


class _Relu:
    """``relu(a y + b)`` of rows y (P, C) as the in-place ``clamp(y, lo, hi)`` followed by the
    affine map ``scale * y + offset`` that the next layer absorbs (see the module docstring)."""

    def __init__(self, a: Tensor, b: Tensor, dtype: torch.dtype) -> None:
        pos, neg, zero = a > 0, a < 0, a == 0
        t = -b / torch.where(zero, torch.ones_like(a), a)
        inf = torch.full_like(a, float("inf"))
        self.lo = torch.where(pos, t, torch.where(zero, 0.0, -inf)).to(dtype)
        self.hi = torch.where(neg, t, torch.where(zero, 0.0, inf)).to(dtype)
        self.scale = torch.where(zero, 0.0, a)  # float64 (C,)
        self.offset = torch.where(zero, b.clamp_min(0.0), b)  # float64 (C,)

    def apply_(self, y: Tensor, out: Tensor | None = None) -> Tensor:
        """Clamp y (P, C) in place, or into ``out`` (one pass)."""
        if out is None:
            return y.clamp_(min=self.lo, max=self.hi)
        return torch.clamp(y, min=self.lo, max=self.hi, out=out)

    def fold(self, weight: Tensor, bias: Tensor | None) -> tuple[Tensor, Tensor]:
        """The next layer ``weight`` (O, C) and ``bias`` (O,) acting on the clamped rows:
        (transposed, scaled weight (C, O) in weight's dtype, bias (O,) float64)."""
        w = weight.detach().double()
        b = w @ self.offset
        if bias is not None:
            b = b + bias.detach().double()
        return (w * self.scale).T.contiguous().to(weight.dtype), b


def _set_abstraction(sa: SetAbstraction, ws: Workspace, src: Tensor, centers: Tensor,
                     group: Tensor) -> Tensor:
    """One SA level: src (n, 3 + C) rows ``[xyz, features]``, centers (S, 3), group (S, K)
    indices into the n rows -> (S, widths[-1]).

    Every pass over the (S * K, C) rows runs in blocks of whole groups that stay in cache: the
    grouped first layer is gathered twice (once for its statistics, once as the input of the next
    product) instead of being stored; a hidden layer's output is stored once and read once
    (clamped into a cache block); the last layer's blocks are reduced over K at once and never
    stored. Measured at N = 10,000: level 1 in 55-60 instead of 100 ms."""
    S, K = group.shape
    dtype = src.dtype
    W0 = sa.first.weight.detach()[:, :, 0]  # (w0, 3 + C)
    pre = mm(src, W0.T.contiguous(), ws.get("pre", (src.shape[0], W0.shape[0]), dtype))
    cterm = centers @ W0[:, :3].T  # (S, w0)
    widest = max(W0.shape[0], *(int(c.weight.shape[0]) for c in sa.convs))
    g = max(1, _BLOCK_BYTES // (K * widest * src.element_size()))  # groups per block
    blocks = [(s0, min(s0 + g, S)) for s0 in range(0, S, g)]

    def grouped(s0: int, s1: int) -> Tensor:
        """Rows of groups s0..s1 of the first layer (before its norm; the bias is in the norm):
        W_p p_j + W_f f_j - W_p p_c, in a cache block."""
        hb = ws.get("in", ((s1 - s0) * K, W0.shape[0]), dtype)
        torch.index_select(pre, 0, group[s0:s1].reshape(-1), out=hb)
        hb.view(s1 - s0, K, -1).sub_(cterm[s0:s1, None, :])
        return hb

    st = _Stats(W0.shape[0], ws)
    for s0, s1 in blocks:
        st.add(grouped(s0, s1))
    a, b = st.affine(sa.norms[0], sa.first.bias.detach())
    h: Tensor | None = None  # the stored output of the previous hidden layer
    for i, (conv, norm) in enumerate(zip(sa.convs, sa.norms[1:], strict=True)):
        relu = _Relu(a, b, dtype)
        w_t, bias = relu.fold(conv.weight[:, :, 0, 0], conv.bias)
        C = w_t.shape[1]
        last = i == len(sa.convs) - 1
        st = _Stats(C, ws)
        if last:
            neg = bool((norm.weight < 0).any()) if isinstance(norm, nn.GroupNorm) else False
            top = torch.empty(S, C, dtype=dtype)
            bot = torch.empty(S, C, dtype=dtype) if neg else None
        else:
            out = ws.get("a" if i % 2 == 0 else "b", (S * K, C), dtype)
        for s0, s1 in blocks:
            rows = slice(s0 * K, s1 * K)
            if h is None:
                hb = relu.apply_(grouped(s0, s1))
            else:
                hb = relu.apply_(h[rows], out=ws.get("in", (h[rows].shape), dtype))
            ob = ws.get("blk", ((s1 - s0) * K, C), dtype) if last else out[rows]
            mm(hb, w_t, ob)
            st.add(ob)
            if last:  # amax and amin apart: faster than aminmax
                torch.amax(ob.view(s1 - s0, K, C), 1, out=top[s0:s1])
                if bot is not None:
                    torch.amin(ob.view(s1 - s0, K, C), 1, out=bot[s0:s1])
        a, b = st.affine(norm, bias)
        if not last:
            h = out
    a, b = a.to(dtype), b.to(dtype)  # sign(a) = sign(norm weight)
    if bot is not None:
        top = torch.where(a >= 0, top, bot)
    return top.mul_(a).add_(b).relu_()


def _interpolate(conv: nn.Conv1d, norm: nn.Module, ws: Workspace, name: str, feat: Tensor,
                 idx: Tensor, w: Tensor) -> Tensor:
    """FP: 1x1 conv of level features feat (n_k, C), inverse-distance interpolation to the N scan
    points (idx, w (N, k)), norm, ReLU -> (N, 64) in the workspace buffer ``name``. The weights of
    a scan point sum to 1, so the convolution's bias passes through the interpolation and is
    folded into the norm."""
    W = conv.weight.detach()[:, :, 0]  # (64, C)
    pre = mm(feat, W.T.contiguous(), ws.get("fp_pre", (feat.shape[0], W.shape[0]), feat.dtype))
    N, k = idx.shape
    idx_t, w_t = idx.T.contiguous(), w.to(pre.dtype).T.contiguous()[:, :, None]  # (k, N), (k, N, 1)
    up = ws.get(name, (N, pre.shape[1]), pre.dtype)
    tmp = ws.get("interp", (N, pre.shape[1]), pre.dtype)
    torch.index_select(pre, 0, idx_t[0], out=up)
    up.mul_(w_t[0])
    for j in range(1, k):
        torch.index_select(pre, 0, idx_t[j], out=tmp)
        up.addcmul_(tmp, w_t[j])
    a, b = _affine(up, norm, conv.bias.detach(), ws)
    return up.mul_(a.to(up.dtype)).add_(b.to(up.dtype)).relu_()


def _sample(model: Generator, ws: Workspace, x: Tensor, geo: Geometry, b: int,
            budget: Tensor | None, prior: Tensor | None) -> Tensor:
    """Head output h (N, 3) of sample b (before the output map) of clean scans x (B, N, 3)."""
    cfg = model.config
    dtype = next(model.parameters()).dtype
    _, n2, n3, n4 = geo.sizes
    xs = x[b].to(dtype) / cfg.scale_m  # (N, 3)
    xyz2 = xs.index_select(0, geo.fps_idx[b])  # (n2, 3)
    src1 = xs if prior is None else torch.cat([xs, prior[b].to(dtype)], 1)
    f1 = _set_abstraction(model.sa[0], ws, src1, xs, geo.groups[0][b])
    f2 = _set_abstraction(model.sa[1], ws, torch.cat([xs, f1], 1), xyz2, geo.groups[1][b])
    f3 = _set_abstraction(model.sa[2], ws, torch.cat([xyz2, f2], 1), xyz2[:n3], geo.groups[2][b])
    f4 = _set_abstraction(model.sa[3], ws, torch.cat([xyz2[:n3], f3], 1), xyz2[:n4],
                          geo.groups[3][b])
    feats = (f2, f3, f4)
    ups = [_interpolate(conv, norm, ws, f"up{j}", feats[j], geo.interp_idx[j][b],
                        geo.interp_w[j][b])
           for j, (conv, norm) in enumerate(zip(model.fp, model.fp_norms, strict=True))]
    parts = [ups[2], ups[1], ups[0], f1, xs]
    if prior is not None:
        parts.append(prior[b].to(dtype))
    h = ws.get("head_in", (xs.shape[0], sum(t.shape[1] for t in parts)), dtype)
    torch.cat(parts, 1, out=h)  # (N, 259 (+8))
    relu: _Relu | None = None
    for i, conv in enumerate(model.head):
        W, bias = conv.weight.detach()[:, :, 0], conv.bias.detach().double()
        if cfg.conditioned:
            assert budget is not None
            c = budget[b].double() / cfg.budget_scale_m
            W, bias = W[:, :-1], bias + c * W[:, -1].double()
        if relu is None:
            w_t = W.T.contiguous()
        else:  # the previous layer's ReLU (and its bias) folded into this one
            w_t, b_prev = relu.fold(W, None)
            bias = bias + b_prev
        out = mm(h, w_t, ws.get(f"head{i}", (h.shape[0], w_t.shape[1]), dtype))
        if i < len(model.head) - 1:
            relu = _Relu(torch.ones_like(bias), bias, dtype)  # relu(out + bias)
            h = relu.apply_(out)
        else:  # (the last output is returned: a tensor of its own)
            h = out + bias.to(dtype)
    return h


def forward(model: Generator, x: Tensor, geo: Geometry, budget: Tensor | None,
            prior: Tensor | None) -> Tensor:
    """Head outputs (B, N, 3) of clean scans x (B, N, 3) (inputs already checked by the model)."""
    ws = model.__dict__.setdefault("_workspace", Workspace())
    with blas_threads():
        return torch.stack([_sample(model, ws, x, geo, b, budget, prior)
                            for b in range(x.shape[0])])
