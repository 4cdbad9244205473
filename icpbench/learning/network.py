"""The PointNet++ generator G of the learned attack (Zhang et al., ICRA 2025, §III-B, Fig. 2).

Architecture (PointNet++ set abstraction, Qi et al. NeurIPS 2017; layout of LG-GAN's generator,
Zhou et al. CVPR 2020, without its label inputs):

* encoder: four set-abstraction (SA) levels, each a shared MLP (1x1 convolutions) on grouped
  ``[relative xyz, features]`` of K neighbours, then a max over the K neighbours:
  F1 (N x 64, MLP [32, 32, 64], all N points in their own order, input = relative xyz only),
  F2 (N/a x 128, [64, 64, 128]), F3 (N/b x 256, [128, 128, 256]), F4 (N/c x 512, [256, 256, 512]);
* decoder: F2, F3, F4 interpolated to the N scan points with the precomputed inverse-distance
  3-NN weights, each mapped to 64 channels by a 1x1 convolution (+ norm + ReLU); concatenated with
  F1 and the (scaled) coordinates X: 64 * 4 + 3 = 259 channels; head of four 1-D convolutions
  259 -> 256 -> 128 -> 64 -> 3 (ReLU between, linear output).

All sampling/grouping indices come from :mod:`icpbench.learning.geometry` (computed once from the
clean scan), so a forward pass is gathers and matrix products only.

Design choices (the paper does not state them; see also docs/methods.md, "Generator design"):

* **Residual output** (default, ``output="residual"``): ``X_adv = X + offset_scale_m * h`` with the
  last convolution initialised to zero, so an untrained generator returns the clean scan exactly.
  The paper (and LG-GAN) output absolute coordinates and therefore pretrain 50 epochs on
  reconstruction (alpha = 0, beta = 1) because "without pretraining, the generator generates scans
  that are too different from the maps". With the residual, that pretraining is trivial (the loss
  is already 0 and its gradient too, as SoftShrink is flat inside the lambda-ball) and can be
  skipped; gradients still reach every layer after the first step because the zero layer's own
  gradient (features x upstream gradient) is non-zero. ``output="absolute"`` reproduces the paper
  (``X_adv = scale_m * h``, default initialisation), for which pretraining is meaningful.
* **Bounded output** (``output="bounded"``, beyond the paper): ``X_adv = X + lambda * u`` with
  ``u = h tanh(|h|) / |h|`` per point, so every displacement is strictly shorter than the budget
  lambda by construction and the model needs lambda at run time. The paper's bound is soft (the
  SoftShrink loss of eq. 4 only penalises excess); on lidar-sim our soft-bound models moved points
  3-4 m at lambda = 1 m (see the lidar model cards), which makes their errors incomparable with
  budget-respecting baselines. The radial tanh is the identity near zero (zero-initialised last
  layer: an untrained model returns the clean scan) and saturates smoothly, so gradients never
  vanish abruptly as they would behind a hard projection. With ``lambda`` a scale of the output,
  one model serves every budget; ``conditioned=True`` additionally lets the directions depend on it.
* **GroupNorm** (default ``norm="group"``, 8 groups) after every SA/FP convolution, none in the
  head (as LG-GAN's head). BatchNorm couples the samples of a batch (an attack's result would
  depend on what else is in the batch), behaves differently in train and eval mode, and its running
  statistics are unreliable with B = 1-8 heterogeneous lidar scans; GroupNorm normalises each
  sample on its own (statistics over channels-in-group x points x neighbours), is identical in
  train and eval, and keeps relative magnitudes across points (a per-point LayerNorm would erase
  the neighbour-distance scale of the first layer).
* **Input scaling**: coordinates are divided by ``scale_m`` inside the network (1 for objects
  normalised to the unit circle, 20 m for lidar) and the offset is multiplied by
  ``offset_scale_m`` (the expected displacement size: 0.1 for objects, 1 m for lidar), so one
  architecture serves both. kNN grouping (not a metric ball) makes the groups scale-free.
* **Budget conditioning** (``conditioned=True``): ``budget / budget_scale_m`` is appended as a
  constant channel to the input of each of the four head convolutions (LG-GAN injects its label at
  several head layers), so one model can serve lambda = 1..5 m. The encoder stays budget-free: F1..F4
  can be computed once and decoded for several budgets (:meth:`Generator.encode`/``decode``).
Two exact rewrites save time without changing the function: the first convolution of an SA level
is applied per source point before gathering (``W [p_j - p_c; f_j] + b = (W_p p_j + W_f f_j + b) -
W_p p_c``), and each FP 1x1 convolution is applied before interpolating (the weights of a scan
point sum to 1, so the affine map commutes with the weighted sum).
"""

from __future__ import annotations

import json
import math
import typing
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from icpbench.core.errors import InputError
from icpbench.learning import blas, fast
from icpbench.learning.geometry import Geometry, GeometryConfig, compute_geometry_batch
from icpbench.learning.prior import PRIOR_CHANNELS

Output = Literal["residual", "absolute", "bounded", "ball"]
Prior = Literal["none", "sector", "sector-iter"]

#: Shared-MLP widths of the four SA levels and of the head (paper Fig. 2 / LG-GAN).
SA_WIDTHS: tuple[tuple[int, ...], ...] = ((32, 32, 64), (64, 64, 128), (128, 128, 256), (256, 256, 512))
FP_WIDTH = 64
HEAD_WIDTHS: tuple[int, ...] = (256, 128, 64)


@dataclass(frozen=True)
class GeneratorConfig:
    """Hyper-parameters of :class:`Generator` (JSON-serialisable; stored beside checkpoints).

    Attributes:
        a, b, c, k, k_interp, idw_power: index precompute, see
            :class:`~icpbench.learning.geometry.GeometryConfig`.
        scale_m: coordinates are divided by this inside the network (metres; 1 for unit objects).
        offset_scale_m: residual output unit (metres): ``X_adv = X + offset_scale_m * h``.
        output: ``"residual"`` (zero-initialised offset), ``"absolute"`` (paper/LG-GAN) or
            ``"bounded"`` (``X + lambda * u``, ``|u| < 1``; needs the budget at run time).
        norm_groups: groups of the GroupNorm after SA and FP convolutions (must divide 32).
        conditioned: take a per-sample budget lambda (metres) as an extra head input channel.
        budget_scale_m: the budget channel is ``lambda / budget_scale_m``.
        prior: ``"sector"``: the model also takes the analytic per-point channels of
            :mod:`icpbench.learning.prior` (B, N, 8) as input features of the first SA level and
            of the head, and adds ``prior_gain`` times the sector attack's direction to its output
            before the bounded squashing (needs ``output="bounded"``); ``"none"``: coordinates only.
        prior_gain: initial value of the learnable gain of the prior direction (dimensionless).
        prior_dmax: association gate of the prior channels (the ICP's d_max: 5 m for lidar, 0.3
            for unit-scale objects).
            ``prior="sector-iter"`` (beyond the paper): the direction channels come from the
            iterated analytic attack instead (:func:`icpbench.learning.prior.iterated_prior_batch`,
            per budget; the model then needs the surrogate ICP at run time, and the attack's
            settings are the generator attack's ``sector_iter``, not the model's).
    """

    a: float = 2.0
    b: float = 4.0
    c: float = 8.0
    k: int = 32
    k_interp: int = 3
    idw_power: float = 2.0
    scale_m: float = 1.0
    offset_scale_m: float = 0.1
    output: Output = "residual"
    norm_groups: int = 8
    conditioned: bool = False
    budget_scale_m: float = 1.0
    prior: Prior = "none"
    prior_gain: float = 2.0
    prior_dmax: float = 5.0

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(GeneratorConfig)
        for f in fields(self):
            v, hint = getattr(self, f.name), hints[f.name]
            if typing.get_origin(hint) is Literal:
                if v not in typing.get_args(hint):
                    raise InputError(f"{f.name} must be one of {typing.get_args(hint)}, got {v!r}")
            elif hint is bool:
                if not isinstance(v, bool):
                    raise InputError(f"{f.name} must be true or false, got {v!r}")
            elif hint is int:
                if isinstance(v, bool) or not isinstance(v, int):
                    raise InputError(f"{f.name} must be an integer, got {v!r}")
            elif hint is float and (isinstance(v, bool) or not isinstance(v, int | float)):
                raise InputError(f"{f.name} must be a number, got {v!r}")
            if hint is float:
                object.__setattr__(self, f.name, float(v))  # 2 and 2.0 serialise alike
        for name in ("scale_m", "offset_scale_m", "budget_scale_m", "prior_dmax"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise InputError(f"{name} must be a finite number > 0, got {getattr(self, name)}")
        if self.prior != "none" and self.output not in ("bounded", "ball"):
            raise InputError(f"prior={self.prior!r} needs output='bounded' or 'ball', got "
                             f"{self.output!r}")
        if self.norm_groups < 1 or any(w % self.norm_groups for w in (32, FP_WIDTH)):
            raise InputError(f"norm_groups must divide 32, got {self.norm_groups}")
        _ = self.geometry  # validates a, b, c, k, k_interp, idw_power

    @property
    def geometry(self) -> GeometryConfig:
        """The index-precompute parameters."""
        return GeometryConfig(a=self.a, b=self.b, c=self.c, k=self.k, k_interp=self.k_interp,
                              idw_power=self.idw_power)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> GeneratorConfig:
        """Strict inverse of :meth:`to_dict`: every field must be present, no unknown keys.

        Fields added after checkpoints were first shipped (``_ADDED_LATER``) take their old
        behaviour when absent, and fields since removed (``_REMOVED``) are dropped when they hold
        the one behaviour that remains (or were run-time settings of the prior's attack, which the
        generator attack now owns), so older checkpoint JSONs still load.

        Raises:
            InputError: not a dict, missing or unknown keys, or invalid values.
        """
        if not isinstance(data, dict):
            raise InputError(f"generator config must be a JSON object, got {type(data).__name__}")
        names = [f.name for f in fields(cls)]
        data = {**{k: v for k, v in _ADDED_LATER.items() if k not in data}, **data}
        for k, kept in _REMOVED.items():
            if k in data:
                if kept is not _ANY and data[k] != kept:
                    raise InputError(f"generator config {k}={data[k]!r} is no longer supported "
                                     f"(only {kept!r})")
                del data[k]
        missing = [n for n in names if n not in data]
        unknown = sorted(set(data) - set(names))
        if missing:
            raise InputError(f"generator config lacks key(s) {missing}")
        if unknown:
            raise InputError(f"generator config has unknown key(s) {unknown}")
        return cls(**{n: data[n] for n in names})

    def with_(self, **kw: Any) -> GeneratorConfig:
        return replace(self, **kw)


#: Config fields introduced after the first shipped checkpoints, with the value that reproduces
#: the behaviour of configs written before them.
_ADDED_LATER: dict[str, Any] = {"prior": "none", "prior_gain": 2.0, "prior_dmax": 5.0}
_ANY = object()
#: Config fields removed, with the one value that remains supported (``_ANY``: run-time settings
#: of the prior's iterated attack, now the generator attack's ``sector_iter``; ignored).
_REMOVED: dict[str, Any] = {"global_feature": False, "norm": "group", "fps": "exact",
                            **{k: _ANY for k in ("prior_iterations", "prior_step", "prior_icp_iterations",
                                                 "prior_icp_stride", "prior_icp_nn_reuse")}}


#: Paper settings: objects (ShapeNet, N = 2,048, unit circle) and lidar (Boreas-like, N = 10,000).
PRESETS: dict[str, GeneratorConfig] = {
    "objects": GeneratorConfig(a=2, b=4, c=8, scale_m=1.0, offset_scale_m=0.1, budget_scale_m=0.1),
    "lidar": GeneratorConfig(a=3, b=12, c=48, scale_m=20.0, offset_scale_m=1.0, budget_scale_m=5.0),
}


def add_prior(model: Generator, kind: str = "sector", gain: float = 2.0,
              dmax: float = 5.0) -> Generator:
    """A copy of a coordinate-only bounded ``model`` that also takes the analytic prior channels.

    The new input weights (first SA level and first head layer) are zero, so the copy's network
    output ``h`` equals the original's; the output becomes ``squash(h + gain * d_prior)``, i.e.
    fine-tuning starts from the trained model pulled towards the sector attack's directions.

    Raises:
        InputError: the model already has a prior, or its output is not ``"bounded"``.
    """
    if model.needs_prior:
        raise InputError("this generator already takes prior channels")
    p = next(model.parameters())
    wide = Generator(model.config.with_(prior=kind, prior_gain=float(gain),
                                        prior_dmax=float(dmax))).to(device=p.device, dtype=p.dtype)
    state = wide.state_dict()
    for k, v in model.state_dict().items():
        tgt = state[k]
        if tgt.shape == v.shape:
            state[k] = v
        else:  # widened input: old columns first, then the prior's (zero)
            new = torch.zeros_like(tgt)
            if k == "sa.0.first.weight":  # input [xyz (3), prior (8)]
                new[:, :v.shape[1]] = v
            else:  # head.0.weight: input [features (259), prior (8), budget (0/1)]
                n_old = FP_WIDTH * 3 + SA_WIDTHS[0][-1] + 3
                new[:, :n_old] = v[:, :n_old]
                new[:, n_old + PRIOR_CHANNELS:] = v[:, n_old:]
            state[k] = new
    wide.load_state_dict(state)
    wide.chunk_size = model.chunk_size
    return wide.train(model.training)


def generator_config(preset: str | GeneratorConfig = "lidar", **overrides: Any) -> GeneratorConfig:
    """Resolve a preset name (``objects``, ``lidar``) plus overrides."""
    if isinstance(preset, GeneratorConfig):
        base = preset
    else:
        if preset not in PRESETS:
            raise InputError(f"unknown generator preset {preset!r}; valid: {', '.join(PRESETS)}")
        base = PRESETS[preset]
    return base.with_(**overrides) if overrides else base


def _norm(channels: int, groups: int) -> nn.Module:
    return nn.GroupNorm(groups, channels)


def gather(feat: Tensor, idx: Tensor) -> Tensor:
    """Gather columns: feat (B, C, n), idx (B, *S) int64 in [0, n) -> (B, C, *S)."""
    B, C = feat.shape[:2]
    if B == 1:
        out = feat[0].index_select(1, idx[0].reshape(-1))[None]
    else:
        out = torch.stack([feat[i].index_select(1, idx[i].reshape(-1)) for i in range(B)])
    return out.reshape(B, C, *idx.shape[1:])


def pointwise(conv: nn.Conv1d | nn.Conv2d, x: Tensor) -> Tensor:
    """The 1x1 convolution ``conv`` of x (B, C, *S) as one matrix product -> (B, O, *S).

    Same function as ``conv(x)``; on the CPU PyTorch runs 1x1 convolutions through its generic
    ``slow_conv2d`` kernels (the largest item of a training step's profile), while ``addmm`` and
    its backward are plain GEMMs: 25% less time forward + backward (docs/performance.md)."""
    B, C = x.shape[:2]
    w = conv.weight.reshape(conv.weight.shape[0], C)
    bias = conv.bias if conv.bias is not None else w.new_zeros(w.shape[0])
    if B == 1:  # (the CPU runs samples one by one: Generator.chunk_size)
        xm = x.reshape(C, -1)
        if blas.eligible(w, xm, bias):  # numpy's BLAS: 2-3x faster skinny products on the CPU
            out = blas.linear(w, xm, bias)[None]
        else:
            out = torch.addmm(bias[:, None], w, xm)[None]
    else:  # (torch.matmul would copy x into another layout first)
        out = torch.baddbmm(bias[None, :, None], w.expand(B, -1, -1), x.reshape(B, C, -1))
    return out.reshape(B, -1, *x.shape[2:])


class SetAbstraction(nn.Module):
    """One SA level: shared MLP on grouped [relative xyz, features], max over the K neighbours."""

    def __init__(self, in_features: int, widths: tuple[int, ...], groups: int) -> None:
        super().__init__()
        self.first = nn.Conv1d(3 + in_features, widths[0], 1)
        self.norms = nn.ModuleList([_norm(w, groups) for w in widths])
        self.convs = nn.ModuleList([nn.Conv2d(i, o, 1) for i, o in zip(widths[:-1], widths[1:], strict=True)])

    def forward(self, xyz: Tensor, feat: Tensor | None, centers: Tensor, group: Tensor) -> Tensor:
        """xyz (B, 3, n) source points, feat (B, C, n) or None, centers (B, 3, S), group (B, S, K)
        indices into the n sources -> (B, widths[-1], S)."""
        src = xyz if feat is None else torch.cat([xyz, feat], 1)
        pre = pointwise(self.first, src)  # (B, w0, n): W_p p_j + W_f f_j + b
        w_xyz = self.first.weight[:, :3, 0]  # (w0, 3)
        h = gather(pre, group).sub_(torch.einsum("oc,bcs->bos", w_xyz, centers)[..., None])
        h = F.relu(self.norms[0](h), inplace=True)
        for conv, norm in zip(self.convs, self.norms[1:], strict=True):
            h = F.relu(norm(pointwise(conv, h)), inplace=True)
        return h.max(dim=3).values


class Generator(nn.Module):
    """PointNet++ generator: clean scans (B, N, 3) -> adversarial scans (B, N, 3), same frame/units.

    Usage::

        cfg = generator_config("lidar")
        G = Generator(cfg)
        geo = G.precompute(x)              # once per clean scan, no gradient
        x_adv = G(x, geo)                  # (B, N, 3); conditioned models: G(x, geo, budget_m)
    """

    def __init__(self, config: GeneratorConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or GeneratorConfig()
        g = cfg.norm_groups
        n_prior = PRIOR_CHANNELS if cfg.prior != "none" else 0
        in_feats = (n_prior, *(w[-1] for w in SA_WIDTHS[:-1]))
        self.sa = nn.ModuleList([SetAbstraction(i, w, g)
                                 for i, w in zip(in_feats, SA_WIDTHS, strict=True)])
        self.fp = nn.ModuleList([nn.Conv1d(w[-1], FP_WIDTH, 1) for w in SA_WIDTHS[1:]])
        self.fp_norms = nn.ModuleList([_norm(FP_WIDTH, g) for _ in SA_WIDTHS[1:]])
        extra = 1 if cfg.conditioned else 0
        dims = (FP_WIDTH * 3 + SA_WIDTHS[0][-1] + 3 + n_prior, *HEAD_WIDTHS, 3)
        self.head = nn.ModuleList([nn.Conv1d(i + extra, o, 1)
                                   for i, o in zip(dims[:-1], dims[1:], strict=True)])
        if cfg.output in ("residual", "bounded", "ball"):
            nn.init.zeros_(self.head[-1].weight)
            nn.init.zeros_(self.head[-1].bias)
        #: learnable gain of the prior direction in the output (prior models only)
        self.prior_gain: nn.Parameter | None = None
        if cfg.prior != "none":
            self.prior_gain = nn.Parameter(torch.tensor(float(cfg.prior_gain)))
        #: Samples per chunk in :meth:`forward` (None: 1 on CPU, where per-sample passes keep the
        #: working set in cache and were 1.6x faster for B=8, N=2,048 forward+backward; the whole
        #: batch on GPU). Not part of the config: it never changes the result.
        self.chunk_size: int | None = None

    # -- inputs -------------------------------------------------------------------------------
    def precompute(self, scans: Tensor | Any) -> Geometry:
        """Index precompute for clean scans (B, N, 3) with this model's geometry parameters."""
        return compute_geometry_batch(scans, self.config.geometry)

    def _check_inputs(self, x: Tensor, geo: Geometry) -> None:
        if not isinstance(x, Tensor) or x.ndim != 3 or x.shape[-1] != 3 or not x.is_floating_point():
            raise InputError(f"x must be a float tensor of shape (B, N, 3), got "
                             f"{getattr(x, 'shape', type(x))}")
        B, N = x.shape[:2]
        if geo.config != self.config.geometry:
            raise InputError(f"geometry was computed with {geo.config}, the model needs "
                             f"{self.config.geometry}; use Generator.precompute")
        if geo.fps_idx.device != x.device:
            raise InputError(f"geometry is on {geo.fps_idx.device}, x on {x.device}: use geo.to(device)")
        if geo.batch_size != B or geo.sizes[0] != N:
            raise InputError(f"geometry is for {geo.batch_size} scans of {geo.sizes[0]} points, "
                             f"x has {B} scans of {N} points")

    @property
    def needs_budget(self) -> bool:
        """Whether :meth:`forward` takes the budget (conditioned or bounded models)."""
        return self.config.conditioned or self.config.output in ("bounded", "ball")

    def _check_budget(self, budget: Tensor | None, B: int) -> None:
        if self.needs_budget:
            if budget is None:
                raise InputError("this generator is budget-conditioned or bounded: pass budget_m "
                                 "(B,) in metres")
            if not isinstance(budget, Tensor) or budget.shape != (B,):
                raise InputError(f"budget must be a tensor of shape ({B},), got "
                                 f"{getattr(budget, 'shape', type(budget).__name__)}")
            if not bool(torch.isfinite(budget).all() and (budget >= 0).all()):
                raise InputError("budget must be finite and >= 0 (metres)")
        elif budget is not None:
            raise InputError("this generator takes no budget (conditioned=False and output is not "
                             "'bounded'); pass budget=None")

    @property
    def needs_prior(self) -> bool:
        """Whether :meth:`forward` takes the analytic prior channels (``prior != "none"``)."""
        return self.config.prior != "none"

    def _check_prior(self, prior: Tensor | None, x: Tensor) -> None:
        if self.needs_prior:
            if not isinstance(prior, Tensor) or prior.shape != (*x.shape[:2], PRIOR_CHANNELS):
                raise InputError(f"this generator needs prior channels of shape "
                                 f"{(*x.shape[:2], PRIOR_CHANNELS)} (icpbench.learning.prior), got "
                                 f"{getattr(prior, 'shape', type(prior).__name__)}")
        elif prior is not None:
            raise InputError("this generator takes no prior channels (prior='none'); pass prior=None")

    # -- network ------------------------------------------------------------------------------
    def encode(self, x: Tensor, geo: Geometry, prior: Tensor | None = None
               ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Encoder features of the clean scans x (B, N, 3): F1 (B, 64, N), F2 (B, 128, n2),
        F3 (B, 256, n3), F4 (B, 512, n4) (channels first; level-k columns follow
        ``geo.fps_idx[:, :n_k]``). Budget-free, so one encoding can be decoded for several budgets.
        ``prior`` (B, N, 8): the analytic channels of prior models (features of the first level)."""
        self._check_inputs(x, geo)
        self._check_prior(prior, x)
        _, n2, n3, n4 = geo.sizes
        p = self.parameters().__next__()
        xs = (x.to(p.dtype) / self.config.scale_m).transpose(1, 2)  # (B, 3, N), scaled
        xyz2 = gather(xs, geo.fps_idx)
        pts = (xs, xs, xyz2, xyz2[..., :n3], xyz2[..., :n4])  # sources of level 1, centres 1..4
        f0 = None if prior is None else prior.to(p.dtype).transpose(1, 2)  # (B, 8, N)
        f1 = self.sa[0](pts[0], f0, pts[1], geo.groups[0])
        f2 = self.sa[1](pts[1], f1, pts[2], geo.groups[1])
        f3 = self.sa[2](pts[2], f2, pts[3], geo.groups[2])
        f4 = self.sa[3](pts[3], f3, pts[4], geo.groups[3])
        return f1, f2, f3, f4

    def decode(self, x: Tensor, geo: Geometry, feats: tuple[Tensor, Tensor, Tensor, Tensor],
               budget: Tensor | None = None, *, prior: Tensor | None = None,
               trace: dict[str, Tensor] | None = None) -> Tensor:
        """Head: encoder features -> adversarial scans (B, N, 3) in ``x``'s dtype.

        ``budget`` (B,) in metres for conditioned models, ``prior`` (B, N, 8) for prior models.
        If ``trace`` is a dict, the up-sampled features (``up2..up4``, (B, 64, N)) and the inputs
        of the four head convolutions
        (``head0..head3``: (B, 259 / 256 / 128 / 64, N), before the budget channel) are put in it.
        """
        self._check_inputs(x, geo)
        self._check_budget(budget, x.shape[0])
        self._check_prior(prior, x)
        p = self.parameters().__next__()
        xs = (x.to(p.dtype) / self.config.scale_m).transpose(1, 2)
        ups = []
        for j, (conv, norm) in enumerate(zip(self.fp, self.fp_norms, strict=True)):
            pre = gather(pointwise(conv, feats[j + 1]), geo.interp_idx[j])  # (B, 64, N, k)
            up = F.relu(norm((pre * geo.interp_w[j].to(p.dtype)[:, None]).sum(-1)), inplace=True)
            ups.append(up)
            if trace is not None:
                trace[f"up{j + 2}"] = up
        parts = [ups[2], ups[1], ups[0], feats[0], xs]
        if prior is not None:
            parts.append(prior.to(p.dtype).transpose(1, 2))
        h = torch.cat(parts, 1)  # (B, 259 (+8), N)
        cond = None
        if self.config.conditioned:
            assert budget is not None
            b = budget.to(device=h.device, dtype=p.dtype) / self.config.budget_scale_m
            cond = b[:, None, None].expand(-1, 1, h.shape[2])
        for i, conv in enumerate(self.head):
            if trace is not None:
                trace[f"head{i}"] = h
            h = pointwise(conv, h if cond is None else torch.cat([h, cond], 1))
            if i < len(self.head) - 1:
                h = F.relu(h, inplace=True)
        return self._output(x, h.transpose(1, 2), budget, prior)

    def _output(self, x: Tensor, out: Tensor, budget: Tensor | None, prior: Tensor | None
                ) -> Tensor:
        """Adversarial scans (B, N, 3) in ``x``'s dtype from the head's output ``out`` (B, N, 3)."""
        if prior is not None:
            assert self.prior_gain is not None
            out = out + self.prior_gain * prior[..., 0:3].to(out.dtype)
        if self.config.output == "residual":
            return x + (self.config.offset_scale_m * out).to(x.dtype)
        if self.config.output == "bounded":
            assert budget is not None
            r = torch.sqrt((out * out).sum(-1, keepdim=True) + 1e-12)
            u = out * (torch.tanh(r) / r)  # |u| < 1, ~ out near 0
            lam = budget.to(device=out.device, dtype=out.dtype)[:, None, None]
            return x + (lam * u).to(x.dtype)
        if self.config.output == "ball":
            assert budget is not None
            # hard projection onto the unit ball: inside it the output is used as is, so a prior
            # model with gain 1 and a zero head returns its prior's displacement exactly
            r = torch.sqrt((out * out).sum(-1, keepdim=True) + 1e-12)
            lam = budget.to(device=out.device, dtype=out.dtype)[:, None, None]
            return x + (lam * (out / torch.clamp(r, min=1.0))).to(x.dtype)
        return (self.config.scale_m * out).to(x.dtype)

    def forward(self, x: Tensor, geo: Geometry, budget: Tensor | None = None,
                prior: Tensor | None = None) -> Tensor:
        """x (B, N, 3) clean scans (sensor frame, metres), geo from :meth:`precompute` on the same
        scans, budget (B,) metres (conditioned models only), prior (B, N, 8) channels of
        :func:`icpbench.learning.prior.sector_prior_batch` (prior models only) -> adversarial
        scans (B, N, 3).

        The batch is run in chunks of :attr:`chunk_size` samples inside one autograd graph; with
        per-sample normalisation (GroupNorm) this gives the same result as one pass."""
        self._check_inputs(x, geo)
        B = x.shape[0]
        self._check_budget(budget, B)
        self._check_prior(prior, x)
        if fast.eligible(self, x):  # no autograd: the same function, channels-last (fast.py)
            return self._output(x, fast.forward(self, x, geo, budget, prior), budget, prior)
        step = self._chunk(x)
        if step >= B:
            return self.decode(x, geo, self.encode(x, geo, prior), budget, prior=prior)
        outs = []
        for s in range(0, B, step):
            part, g = x[s:s + step], geo.select(range(s, min(s + step, B)))
            pr = None if prior is None else prior[s:s + step]
            outs.append(self.decode(part, g, self.encode(part, g, pr),
                                    None if budget is None else budget[s:s + step], prior=pr))
        return torch.cat(outs)

    def _chunk(self, x: Tensor) -> int:
        if self.chunk_size is not None:
            return max(1, int(self.chunk_size))
        return 1 if x.device.type == "cpu" else x.shape[0]

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
