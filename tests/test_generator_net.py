"""Generator network, index precompute and checkpoint I/O (icpbench.learning)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from icpbench.core.errors import CheckpointError, InputError
from icpbench.learning.checkpoint import (
    CONFIG_HASH_KEY,
    config_hash,
    load_checkpoint,
    read_checkpoint_meta,
    save_checkpoint,
)
from icpbench.learning.geometry import (
    Geometry,
    GeometryConfig,
    compute_geometry,
    compute_geometry_batch,
    farthest_point_indices,
    fps_start_index,
)
from icpbench.learning.network import Generator, GeneratorConfig, generator_config

torch.set_num_threads(1)

N = 256  # small scans: levels of 256 / 128 / 64 / 32 points with a, b, c = 2, 4, 8


def cloud(seed: int, n: int = N) -> np.ndarray:
    """A generic (no ties) random cloud with some structure: a noisy box surface, unit scale."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, (n, 3))
    face = rng.integers(0, 3, n)
    p[np.arange(n), face] = np.sign(p[np.arange(n), face]) * 0.5
    return (p + rng.normal(0, 0.01, p.shape)).astype(np.float32)


def randomised(cfg: GeneratorConfig, seed: int = 0) -> Generator:
    """A generator whose zero-initialised last layer is made non-zero (so outputs differ from x)."""
    torch.manual_seed(seed)
    G = Generator(cfg)
    torch.nn.init.normal_(G.head[-1].weight, std=0.05)
    torch.nn.init.normal_(G.head[-1].bias, std=0.05)
    return G


def naive_fps(x: np.ndarray, n: int, start: int) -> np.ndarray:
    d = np.full(len(x), np.inf)
    out = [start]
    for _ in range(n - 1):
        d = np.minimum(d, ((x - x[out[-1]]) ** 2).sum(1))
        out.append(int(np.argmax(d)))
    return np.array(out)


# -- geometry --------------------------------------------------------------------------------------

def test_geometry_sizes_and_indices_match_brute_force():
    x = cloud(0).astype(np.float64)
    geo = compute_geometry(x)
    assert geo.sizes == (256, 128, 64, 32)
    assert [tuple(g.shape) for g in geo.groups] == [(1, 256, 32), (1, 128, 32), (1, 64, 32), (1, 32, 32)]
    assert all(g.dtype == torch.int64 for g in (geo.fps_idx, *geo.groups, *geo.interp_idx))
    # levels 2-4 are the first 128 / 64 / 32 picks of exact vanilla FPS from the
    # farthest-from-centroid point (as sets; the start first), and prefixes of fps_idx
    fps = geo.fps_idx[0].numpy()
    assert fps[0] == np.argmax(((x - x.mean(0)) ** 2).sum(1))
    ref = naive_fps(x, 128, int(fps[0]))
    for n in (128, 64, 32):
        np.testing.assert_array_equal(np.sort(fps[:n]), np.sort(ref[:n]))
    # the same sets as fpsample's float32 FPS sequence (what the shipped models were trained with)
    np.testing.assert_array_equal(np.sort(farthest_point_indices(x, 128)[:64]), np.sort(ref[:64]))
    # kNN groups: the K nearest source points of each centre (as sets)
    lvl = [x, x[fps], x[fps[:64]], x[fps[:32]]]
    for k, (src, ctr) in enumerate([(lvl[0], lvl[0]), (lvl[0], lvl[1]), (lvl[1], lvl[2]), (lvl[2], lvl[3])]):
        d = ((ctr[:, None] - src[None]) ** 2).sum(-1)
        ref = np.sort(np.argsort(d, axis=1)[:, :32], axis=1)
        np.testing.assert_array_equal(np.sort(geo.groups[k][0].numpy(), axis=1), ref)
    # interpolation: 3 nearest level points, weights proportional to 1 / d^2 (1 / d on request),
    # summing to 1; a scan point that is itself a level point takes that point's feature
    w1 = compute_geometry(x, GeometryConfig(idw_power=1.0)).interp_w
    for j in range(3):
        d = np.sqrt(((x[:, None] - lvl[j + 1][None]) ** 2).sum(-1))
        idx = geo.interp_idx[j][0].numpy()
        np.testing.assert_array_equal(np.sort(idx, 1), np.sort(np.argsort(d, 1)[:, :3], 1))
        dd = np.take_along_axis(d, idx, 1)
        on = dd[:, 0] == 0
        assert on.sum() == geo.sizes[j + 1]
        for p, w in ((2, geo.interp_w[j][0].numpy()), (1, w1[j][0].numpy())):
            np.testing.assert_allclose(w[on, 0], 1.0, rtol=1e-6)
            w_ref = dd[~on] ** -p / (dd[~on] ** -p).sum(1, keepdims=True)
            np.testing.assert_allclose(w[~on], w_ref, rtol=1e-5)


def test_geometry_is_deterministic_batched_and_cacheable():
    xs = np.stack([cloud(1), cloud(2)])
    a, b = compute_geometry_batch(xs), compute_geometry_batch(torch.as_tensor(xs))
    for ta, tb in zip(a.to_arrays().values(), b.to_arrays().values(), strict=True):
        np.testing.assert_array_equal(ta, tb)
    single = compute_geometry(xs[1])
    np.testing.assert_array_equal(a.select([1]).groups[2].numpy(), single.groups[2].numpy())
    back = Geometry.from_arrays(a.to_arrays(), a.config)
    assert torch.equal(back.interp_w[1], a.interp_w[1]) and torch.equal(back.fps_idx, a.fps_idx)
    with pytest.raises(InputError, match="recompute"):
        Geometry.from_arrays(a.to_arrays(), GeometryConfig(k=16))
    with pytest.raises(InputError, match="different scan sizes"):
        Geometry.stack([single, compute_geometry(cloud(3, n=300))])


def test_geometry_rejects_bad_scans_and_configs():
    with pytest.raises(InputError, match="at least 128 points"):
        compute_geometry(cloud(0, n=100))
    bad = cloud(0)
    bad[5, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        compute_geometry(bad)
    with pytest.raises(InputError, match="a <= b <= c"):
        GeometryConfig(a=4, b=2, c=8)
    assert GeometryConfig(a=3, b=12, c=48).level_sizes(10_000) == (10_000, 3333, 833, 208)
    g1 = compute_geometry(cloud(0), GeometryConfig(k=1, k_interp=1))
    assert g1.groups[3].shape == (1, 32, 1) and torch.equal(g1.interp_w[2], torch.ones(1, N, 1))
    assert GeometryConfig(a=2) == GeometryConfig(a=2.0) and isinstance(GeometryConfig(a=2).a, float)


def test_fps_start_is_permutation_invariant():
    x = cloud(4).astype(np.float64)
    perm = np.random.default_rng(0).permutation(N)
    assert perm[fps_start_index(x[perm])] == fps_start_index(x)


# -- network ---------------------------------------------------------------------------------------

def test_every_layer_has_the_paper_shape():
    cfg = generator_config("objects")
    G = randomised(cfg)
    x = torch.as_tensor(np.stack([cloud(5), cloud(6)]))
    geo = G.precompute(x)
    f1, f2, f3, f4 = G.encode(x, geo)
    assert [tuple(f.shape) for f in (f1, f2, f3, f4)] == [
        (2, 64, 256), (2, 128, 128), (2, 256, 64), (2, 512, 32)]
    trace: dict[str, torch.Tensor] = {}
    out = G.decode(x, geo, (f1, f2, f3, f4), trace=trace)
    assert {k: tuple(v.shape[1:]) for k, v in trace.items()} == {
        "up2": (64, 256), "up3": (64, 256), "up4": (64, 256),
        "head0": (259, 256), "head1": (256, 256), "head2": (128, 256), "head3": (64, 256)}
    assert out.shape == (2, 256, 3) and out.dtype == x.dtype
    # SA 3-32-32-64 / 67-64-64-128 / 131-128-128-256 / 259-256-256-512, FP 128/256/512->64,
    # head 259-256-128-64-3, with biases and GroupNorm affine parameters
    assert G.num_parameters() == 520_163
    # forward (one sample at a time, numpy's BLAS) = decode(encode) of the batch (torch's GEMM)
    torch.testing.assert_close(G(x, geo), out)


def _naive_encode_decode(G: Generator, x: torch.Tensor, geo: Geometry):
    """Reference forward without the two rewrites: groups [relative xyz, features] explicitly and
    interpolates before the FP convolution."""
    xs = (x / G.config.scale_m).transpose(1, 2)
    b = torch.arange(x.shape[0])[:, None, None]
    _, n2, n3, n4 = geo.sizes
    xyz2 = xs[torch.arange(x.shape[0])[:, None], :, geo.fps_idx].transpose(1, 2)
    pts = (xs, xs, xyz2, xyz2[..., :n3], xyz2[..., :n4])
    feats, f = [], None
    for lvl, sa in enumerate(G.sa):
        src, ctr, grp = pts[lvl], pts[lvl + 1], geo.groups[lvl]
        rel = src.transpose(1, 2)[b, grp] - ctr.transpose(1, 2)[:, :, None]  # (B, S, K, 3)
        g = rel if f is None else torch.cat([rel, f.transpose(1, 2)[b, grp]], -1)
        h = g.permute(0, 3, 1, 2)
        h = F.relu(sa.norms[0](F.conv2d(h, sa.first.weight[..., None], sa.first.bias)))
        for conv, norm in zip(sa.convs, sa.norms[1:], strict=True):
            h = F.relu(norm(conv(h)))
        f = h.amax(3)
        feats.append(f)
    ups = []
    for j in range(3):
        fk = feats[j + 1].transpose(1, 2)[b, geo.interp_idx[j]]  # (B, N, 3, C)
        interp = (fk * geo.interp_w[j][..., None].to(fk.dtype)).sum(2).transpose(1, 2)
        ups.append(F.relu(G.fp_norms[j](G.fp[j](interp))))
    h = torch.cat([ups[2], ups[1], ups[0], feats[0], xs], 1)
    for i, conv in enumerate(G.head):
        h = conv(h) if i == len(G.head) - 1 else F.relu(conv(h))
    return feats, x + G.config.offset_scale_m * h.transpose(1, 2)


def test_fast_layers_equal_the_textbook_computation():
    G = randomised(generator_config("objects")).double()  # float64: compare without rounding noise
    x = torch.as_tensor(np.stack([cloud(7), cloud(8)]), dtype=torch.float64)
    geo = G.precompute(x)
    with torch.no_grad():
        feats, ref = _naive_encode_decode(G, x, geo)
        for f, r in zip(G.encode(x, geo), feats, strict=True):
            torch.testing.assert_close(f, r, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(G(x, geo), ref, rtol=1e-9, atol=1e-10)


def test_permuting_the_points_permutes_the_output():
    G = randomised(generator_config("objects"), seed=1)
    x = torch.as_tensor(cloud(9))[None]
    perm = torch.as_tensor(np.random.default_rng(3).permutation(N))
    xp = x[:, perm]
    geo, geop = G.precompute(x), G.precompute(xp)
    # the same physical level sets (the start first); groups are the same sets of physical points
    for n in geo.sizes[1:]:
        assert torch.equal(perm[geop.fps_idx[0, :n]].sort().values, geo.fps_idx[0, :n].sort().values)
    assert perm[geop.fps_idx[0, 0]] == geo.fps_idx[0, 0]
    with torch.no_grad():
        y, yp = G(x, geo), G(xp, geop)
        fs, fps_ = G.encode(x, geo), G.encode(xp, geop)
    assert (y - x).abs().max() > 1e-3  # the test is not trivially about the identity
    torch.testing.assert_close(yp, y[:, perm], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fps_[0], fs[0][:, :, perm], rtol=1e-5, atol=1e-5)
    # coarse levels: the same features for the same physical points (stored in scan-index order
    # inside each level's part, so matched through the physical point ids)
    ids, ids_p = geo.fps_idx[0], perm[geop.fps_idx[0]]
    for a, b in zip(fs[1:], fps_[1:], strict=True):
        n = a.shape[-1]
        order, order_p = ids[:n].argsort(), ids_p[:n].argsort()
        torch.testing.assert_close(a[..., order], b[..., order_p], rtol=1e-5, atol=1e-5)


def test_samples_are_independent_of_the_batch():
    G = randomised(generator_config("objects"))
    x = torch.as_tensor(np.stack([cloud(10), cloud(11), cloud(12)]))
    geo = G.precompute(x)
    with torch.no_grad():
        G.chunk_size = 3  # one pass over the whole batch
        full = G(x, geo)
        G.chunk_size = 2  # chunks of 2 and 1
        chunked = G(x, geo)
        one = G(x[1:2], geo.select([1]))
    torch.testing.assert_close(full[1:2], one, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(full, chunked, rtol=1e-5, atol=1e-6)
    assert G._chunk(x) == 2
    G.chunk_size = None  # the CPU default: one sample at a time
    assert G._chunk(x) == 1


def test_residual_starts_at_identity_and_scales_are_applied():
    x = torch.as_tensor(cloud(13) * 20.0, dtype=torch.float64)[None]  # metre-scale, float64 in
    G = Generator(generator_config("lidar", a=2, b=4, c=8))
    geo = G.precompute(x)
    y = G(x, geo)
    assert y.dtype == torch.float64 and torch.equal(y, x)
    # offset = offset_scale_m * head output: doubling offset_scale_m doubles the displacement
    G1 = randomised(generator_config("lidar", a=2, b=4, c=8, offset_scale_m=1.0))
    G2 = randomised(generator_config("lidar", a=2, b=4, c=8, offset_scale_m=2.0))
    with torch.no_grad():
        torch.testing.assert_close(G2(x, geo) - x, 2 * (G1(x, geo) - x))
    Ga = Generator(generator_config("objects", output="absolute"))
    with torch.no_grad():
        assert (Ga(x, geo) - x).abs().max() > 1.0  # absolute coordinates need pretraining


def test_budget_conditioning():
    cfg = generator_config("objects", conditioned=True)
    G = randomised(cfg)
    x = torch.as_tensor(np.stack([cloud(14), cloud(14)]))
    geo = G.precompute(x)
    with torch.no_grad():
        y = G(x, geo, torch.tensor([0.05, 0.1]))
    assert (y[0] - y[1]).abs().max() > 1e-4  # same scan, different budgets
    assert G.head[0].in_channels == 260 and G.head[-1].in_channels == 65
    with pytest.raises(InputError, match="budget-conditioned"):
        G(x, geo)
    with pytest.raises(InputError, match="finite and >= 0"):
        G(x, geo, torch.tensor([0.1, -1.0]))
    with pytest.raises(InputError, match="takes no budget"):
        randomised(generator_config("objects"))(x, geo, torch.ones(2))
    with pytest.raises(InputError, match="use Generator.precompute"):
        Generator(generator_config("lidar"))(x, geo)


def test_bounded_output_respects_the_budget_and_scales_with_it():
    G = randomised(generator_config("objects", output="bounded"))
    with torch.no_grad():  # large random head weights: saturate the radial tanh
        G.head[-1].weight.normal_(0, 5.0)
    x = torch.as_tensor(np.stack([cloud(18), cloud(18)]))
    geo = G.precompute(x)
    lam = torch.tensor([0.05, 0.2], dtype=torch.float64)
    with torch.no_grad():
        y = G(x, geo, lam)
    d = torch.linalg.norm(y - x, dim=-1)
    assert (d[0] < 0.05).all() and (d[1] < 0.2).all()
    assert d[0].max() > 0.045  # saturated points come close to the bound
    torch.testing.assert_close(y[1] - x[1], 4 * (y[0] - x[0]))  # lambda is a pure scale
    with pytest.raises(InputError, match="bounded"):
        G(x, geo)
    G0 = Generator(generator_config("objects", output="bounded"))  # zero-initialised last layer
    with torch.no_grad():
        assert torch.equal(G0(x, geo, lam), x)


def test_backward_is_finite_through_every_layer():
    """GroupNorm (the one normalisation) with in-place ReLUs: autograd gives finite gradients to
    every parameter."""
    G = randomised(generator_config("objects"))
    x = torch.as_tensor(np.stack([cloud(15), cloud(16)]))
    y = G(x, G.precompute(x))
    assert y.shape == x.shape and torch.isfinite(y).all()
    norms = [m for m in G.modules() if "norm" in type(m).__name__.lower()]
    assert len(norms) == 15 and all(isinstance(m, torch.nn.GroupNorm) and m.num_groups == 8
                                    for m in norms)  # 4 SA levels x 3 + 3 FP levels
    y.square().sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in G.parameters())


def test_config_json_round_trip_and_validation():
    cfg = generator_config("lidar", conditioned=True)
    assert GeneratorConfig.from_dict(json.loads(cfg.to_json())) == cfg
    assert cfg.geometry.level_sizes(10_000) == (10_000, 3333, 833, 208)
    with pytest.raises(InputError, match="lacks key"):
        GeneratorConfig.from_dict({"a": 2})
    # JSONs written before the prior existed: no prior, as then
    pre_prior = {k: v for k, v in cfg.to_dict().items() if not k.startswith("prior")}
    assert GeneratorConfig.from_dict(pre_prior) == cfg and cfg.prior == "none"
    # JSONs written while the removed options existed load when they hold the behaviour that
    # remains (no global feature, GroupNorm, exact FPS); the prior's old run-time settings are
    # ignored (the generator attack's sector_iter settings replace them)
    old = {**cfg.to_dict(), "global_feature": False, "norm": "group", "fps": "exact",
           "prior_iterations": 8, "prior_step": 0.5, "prior_icp_iterations": 25,
           "prior_icp_stride": 1, "prior_icp_nn_reuse": 0.05}
    assert GeneratorConfig.from_dict(old) == cfg
    for key, value in (("norm", "batch"), ("norm", "none"), ("global_feature", True),
                       ("fps", "bucket")):
        with pytest.raises(InputError, match=f"{key}={value!r} is no longer supported"):
            GeneratorConfig.from_dict({**old, key: value})
    with pytest.raises(InputError, match="unknown key"):
        GeneratorConfig.from_dict({**cfg.to_dict(), "depth": 5})
    with pytest.raises(InputError, match="output must be one of"):
        generator_config("objects", output="sphere")
    with pytest.raises(InputError, match="conditioned must be true or false"):
        generator_config("objects", conditioned=1)
    with pytest.raises(InputError, match="scale_m must be a finite number > 0"):
        generator_config("objects", scale_m=float("inf"))


def test_a_few_steps_increase_the_icp_pose_error():
    """Gradient ascent on the p2plane ICP translation error through the generator works."""
    from icpbench.core.se3 import pose_error_components
    from icpbench.core.types import Batch, Sample
    from icpbench.datasets.synthetic_scene import scene_sample
    from icpbench.targets.p2plane import PointToPlaneICP

    s = scene_sample(n_scan=N, n_map=6000, seed=0)
    f = 1 / 40  # the 80 m synthetic scene shrunk to object scale for the objects preset
    T_gt = s.T_gt.copy()
    T_gt[:3, 3] *= f
    s = Sample(id="box", scan=s.scan * f, map=s.map * f, map_normals=s.map_normals, T_gt=T_gt)
    batch = Batch.from_samples([s], dtype=torch.float32)
    target = PointToPlaneICP("objects-train", max_iterations=15)
    torch.manual_seed(0)
    G = Generator(generator_config("objects", offset_scale_m=0.05))
    geo = G.precompute(batch.scans)
    opt = torch.optim.Adam(G.parameters(), lr=1e-3)
    errs = []
    for _ in range(6):
        reg = target.register(G(batch.scans, geo).double(), batch.maps, batch.T_init)
        err = pose_error_components(reg.T, batch.T_gt)["trans_err_xy"]
        opt.zero_grad()
        (-err.sum()).backward()
        opt.step()
        errs.append(float(err.detach()))
    assert errs[0] < 2e-3  # clean scan: ICP recovers the pose
    assert errs[-1] > 3 * errs[0] and errs[-1] > 4e-3
    assert all(b > a for a, b in zip(errs, errs[1:], strict=False))


# -- checkpoints -----------------------------------------------------------------------------------

def test_checkpoint_round_trip(tmp_path):
    G = randomised(generator_config("objects", conditioned=True))
    card = {"data": "unit test", "budget_m": [0.05, 0.1], "epochs": 0}
    path = save_checkpoint(G, tmp_path / "sub" / "gen.pt", card=card)
    assert path.is_file() and (tmp_path / "sub" / "gen.json").is_file()
    loaded = load_checkpoint(path)
    assert loaded.config == G.config and loaded.card == card and not loaded.model.training
    x = torch.as_tensor(cloud(17))[None]
    geo = G.precompute(x)
    budget = torch.tensor([0.07])
    with torch.no_grad():
        assert torch.equal(loaded.model(x, geo, budget), G.eval()(x, geo, budget))
    cfg, meta = read_checkpoint_meta(path)
    assert cfg == G.config and meta["num_parameters"] == G.num_parameters()
    with pytest.raises(InputError, match="JSON-serialisable"):
        save_checkpoint(G, tmp_path / "bad.pt", card={"x": object()})


class _NotATensor:
    """A custom class: a pickle containing it is refused by torch.load(weights_only=True)."""

    def __init__(self) -> None:
        self.payload = "would run arbitrary code on unpickling"


def test_checkpoint_errors(tmp_path):
    G = Generator(generator_config("objects"))
    path = save_checkpoint(G, tmp_path / "gen.pt")
    raw, meta = path.read_bytes(), json.loads(path.with_suffix(".json").read_text())

    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")

    def variant(name: str, weights: bytes | None = raw, js: dict | str | None = None):
        p = tmp_path / f"{name}.pt"
        if weights is not None:
            p.write_bytes(weights)
        js = meta if js is None else js
        if js != "absent":
            p.with_suffix(".json").write_text(js if isinstance(js, str) else json.dumps(js))
        return p

    with pytest.raises(CheckpointError, match="config file .* is missing"):
        load_checkpoint(variant("nojson", js="absent"))
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_checkpoint(variant("badjson", js="{not json"))
    with pytest.raises(CheckpointError, match="invalid generator config.*lacks key"):
        load_checkpoint(variant("cfgkey", js={**meta, "config": {"a": 2}}))
    with pytest.raises(CheckpointError, match="invalid generator config.*output must be one of"):
        load_checkpoint(variant("cfgval", js={**meta, "config": {**meta["config"], "output": "sphere"}}))
    with pytest.raises(CheckpointError, match="invalid generator config.*norm='batch' is no longer"):
        load_checkpoint(variant("cfgnorm", js={**meta, "config": {**meta["config"], "norm": "batch"}}))
    # a checkpoint saved while the removed options existed (its weights carry the hash of its own
    # JSON), holding the remaining behaviour, loads as today's config
    old_cfg = {**meta["config"], "global_feature": False, "norm": "group", "fps": "exact",
               "prior_icp_iterations": 25}
    old_pt = tmp_path / "old-weights.pt"
    torch.save({**G.state_dict(), CONFIG_HASH_KEY: config_hash(old_cfg)}, old_pt)
    loaded = load_checkpoint(variant("oldjson", weights=old_pt.read_bytes(),
                                     js={**meta, "config": old_cfg}))
    assert loaded.config == G.config
    for (k, a), b in zip(loaded.model.state_dict().items(), G.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    with pytest.raises(CheckpointError, match="not an icpbench generator config"):
        load_checkpoint(variant("fmt", js={**meta, "format": "other"}))
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_checkpoint(variant("trunc", weights=raw[: len(raw) // 2]))
    with pytest.raises(CheckpointError, match="is corrupt or not a file written by torch.save"):
        load_checkpoint(variant("garbage", weights=b"definitely not a checkpoint" * 40))

    # a state dict from another architecture / config, with the JSON of this one
    other = tmp_path / "other.pt"
    save_checkpoint(Generator(generator_config("objects", conditioned=True)), other)
    shape_msg = r"'head\.0\.weight' has shape \(256, 260, 1\).*needs \(256, 259, 1\)"
    with pytest.raises(CheckpointError, match=shape_msg):
        load_checkpoint(variant("shape", weights=other.read_bytes()))
    # weights without the 30 GroupNorm parameters (4 SA levels x 3 + 3 FP levels, weight and bias)
    torch.save({k: v for k, v in G.state_dict().items() if "norms" not in k}, other)
    with pytest.raises(CheckpointError, match=r"lacks 30 parameter\(s\).*first 'sa\.0\.norms\.0\.weight'"):
        load_checkpoint(variant("missing", weights=other.read_bytes()))
    extra = tmp_path / "extra.pt"
    torch.save({**G.state_dict(), "decoder.extra": torch.zeros(3)}, extra)
    with pytest.raises(CheckpointError, match="unexpected key.*'decoder.extra'"):
        load_checkpoint(variant("extra", weights=extra.read_bytes()))
    torch.save([torch.zeros(3)], extra)
    with pytest.raises(CheckpointError, match="does not contain a state dict"):
        load_checkpoint(variant("list", weights=extra.read_bytes()))

    # a pickle with a custom class: refused by weights_only loading, never unpickled
    evil = tmp_path / "evil.pt"
    torch.save({**G.state_dict(), "x": _NotATensor()}, evil)
    with pytest.raises(CheckpointError, match="safe loading .*refuses.*_NotATensor"):
        load_checkpoint(variant("evil", weights=evil.read_bytes()))
