"""The CEGC network: weighted SVD, gradients, equivariance, shapes, devices."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cegc_ros.model import CEGC, ModelConfig
from cegc_ros.model.losses import LossConfig, cegc_loss, overlap_labels
from cegc_ros.model.svd import weighted_kabsch


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def small_cfg(**kw) -> ModelConfig:
    return ModelConfig(agnn_dims=(16, 16, 32), feat_dim=32, attn_heads=2, attn_layers=1,
                       cams_dim=8, hoce_topk=4, chunk_rows=64, **kw)


def inputs(n: int, m: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(1, n, 3, generator=g) - 0.5
    tgt = torch.rand(1, m, 3, generator=g) - 0.5
    nrm_s = torch.nn.functional.normalize(torch.randn(1, n, 3, generator=g), dim=-1)
    nrm_t = torch.nn.functional.normalize(torch.randn(1, m, 3, generator=g), dim=-1)
    return src, tgt, nrm_s, nrm_t, torch.rand(1, n, 33, generator=g), torch.rand(1, m, 33, generator=g)


@pytest.mark.parametrize("seed", range(5))
def test_weighted_svd_recovers_random_rigid_transform_with_any_weights(seed):
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    t = rng.uniform(-2, 2, 3)
    src = rng.normal(size=(50, 3))
    tgt = src @ R.T + t
    w = rng.uniform(0.01, 1.0, 50)
    R_est, t_est, valid = weighted_kabsch(torch.tensor(src[None]), torch.tensor(tgt[None]), torch.tensor(w[None]))
    assert bool(valid[0])
    assert np.abs(R_est[0].double().numpy() - R).max() < 1e-4
    assert np.abs(t_est[0].double().numpy() - t).max() < 1e-4


def test_weighted_svd_returns_a_rotation_not_a_reflection():
    rng = np.random.default_rng(7)
    src = rng.normal(size=(40, 3))
    reflect = np.diag([1.0, 1.0, -1.0])
    tgt = src @ reflect.T                      # a mirror image: the best rotation is not det -1
    R, _, valid = weighted_kabsch(torch.tensor(src[None]), torch.tensor(tgt[None]), torch.ones(1, 40))
    assert bool(valid[0])
    assert torch.det(R[0]).item() == pytest.approx(1.0, abs=1e-5)
    assert torch.allclose(R[0] @ R[0].T, torch.eye(3), atol=1e-5)


def test_weighted_svd_degenerate_inputs_are_invalid_and_finite():
    rng = np.random.default_rng(3)
    src = torch.tensor(rng.normal(size=(1, 30, 3)))
    R, t, valid = weighted_kabsch(src, src + 1.0, torch.zeros(1, 30))
    assert not bool(valid[0]) and torch.isfinite(R).all() and torch.isfinite(t).all()
    line = torch.linspace(0, 1, 30).view(1, 30, 1) * torch.tensor([[[1.0, 2.0, 3.0]]])
    R, t, valid = weighted_kabsch(line, line + 0.5, torch.ones(1, 30))
    assert not bool(valid[0]) and torch.isfinite(R).all() and torch.isfinite(t).all()
    assert torch.allclose(R[0], torch.eye(3))


@pytest.mark.parametrize("variant", ["ri", "paper"])
@pytest.mark.parametrize("centre", ["own", "overlap"])
def test_gradients_flow_to_every_branch_and_stay_finite(variant, centre):
    torch.manual_seed(0)
    model = CEGC(small_cfg(variant=variant, cams_centre=centre)).train()
    src, tgt, ns, nt, ds, dt = inputs(96, 80)
    out = model(src, tgt, ns, nt, ds, dt)
    loss, parts = cegc_loss(out, src, tgt, torch.eye(3)[None], torch.zeros(1, 3), LossConfig(),
                            model.cfg.match_temperature)
    loss.backward()
    assert np.isfinite(parts["loss"])
    for name in ["agnn", "context", "hoce", "cams"]:
        grads = [p.grad for n, p in model.named_parameters() if n.startswith(name) and p.grad is not None]
        assert grads, f"no gradient reached {name}"
        assert all(torch.isfinite(g).all() for g in grads)
        assert any(g.abs().sum() > 0 for g in grads), f"all-zero gradient in {name}"


def test_overlap_scores_are_permutation_equivariant():
    torch.manual_seed(1)
    model = CEGC(small_cfg()).eval()
    src, tgt, ns, nt, ds, dt = inputs(128, 112, seed=2)
    perm_s, perm_t = torch.randperm(128), torch.randperm(112)
    with torch.no_grad():
        a = model(src, tgt, ns, nt, ds, dt)
        b = model(src[:, perm_s], tgt[:, perm_t], ns[:, perm_s], nt[:, perm_t], ds[:, perm_s], dt[:, perm_t])
    assert torch.allclose(a.src_overlap_logits[:, perm_s], b.src_overlap_logits, atol=1e-4)
    assert torch.allclose(a.tgt_overlap_logits[:, perm_t], b.tgt_overlap_logits, atol=1e-4)
    assert torch.allclose(a.R, b.R, atol=1e-3)


@pytest.mark.parametrize("n,m", [(64, 64), (64, 200), (300, 97), (1024, 1024), (4096, 4096)])
def test_forward_any_point_count(n, m):
    torch.manual_seed(0)
    model = CEGC(small_cfg()).eval()
    with torch.no_grad():
        out = model(*inputs(n, m))
    assert out.src_overlap_logits.shape == (1, n) and out.tgt_overlap_logits.shape == (1, m)
    n1, n2 = out.src_idx.shape[1], out.tgt_idx.shape[1]
    assert n1 == n // 2 and n2 == m // 2                    # top-N = floor(0.5 x points)
    assert out.scores.shape == (1, n1, n2)
    assert out.match.shape == (1, n1) and int(out.match.max()) < m
    assert torch.isfinite(out.R).all() and torch.isfinite(out.t).all()
    assert torch.allclose(out.R[0] @ out.R[0].T, torch.eye(3), atol=1e-4)


def test_cams_chunking_does_not_change_scores():
    torch.manual_seed(0)
    cfg = small_cfg()
    model = CEGC(cfg).eval()
    x = inputs(150, 130)
    with torch.no_grad():
        a = model(*x)
        model.cams.chunk_rows = 7
        b = model(*x)
    assert torch.allclose(a.scores, b.scores, atol=1e-5)
    assert torch.allclose(a.conf_logits, b.conf_logits, atol=1e-5)


def _double(module, *tensors):
    """A float64 copy of ``module`` and of ``tensors`` (new leaves that require grad)."""
    import copy
    return (copy.deepcopy(module).double(),
            *(t.detach().double().requires_grad_(True) for t in tensors))


def test_agnn_layer_attention_on_points_is_the_edge_wise_attention():
    """The AGNN layer applies the keys' and values' linear maps to the N points instead of the
    N*K edges (cegc_ros/model/features.py): the same function as the paper's edge-wise form,
    for the shipped weights and for random ones, gradients included."""
    from cegc_ros.engine import default_weights, load_checkpoint
    from cegc_ros.model.features import AGNNLayer

    def edge_wise(layer, edges):
        fb = layer.embed(edges)
        centre = fb.max(dim=2).values
        q = layer.q(centre).unsqueeze(2)
        a = torch.softmax((q * layer.k(fb)).sum(-1) * layer.scale, dim=-1)
        return layer.out((a.unsqueeze(-1) * layer.v(fb)).sum(2)) + centre

    torch.manual_seed(0)
    shipped, _ = load_checkpoint(default_weights(), "cpu")
    layers = list(shipped.agnn.layers) + [AGNNLayer(10, 24)]
    for layer in layers:
        c_in = layer.embed[0].in_features
        edges = torch.randn(1, 300, 12, c_in, requires_grad=True)
        ref = edge_wise(layer, edges)
        out = layer(edges)
        assert out.shape == ref.shape == (1, 300, layer.k.out_features)
        assert ref.abs().max() > 1.0                                   # not a trivially small output
        torch.testing.assert_close(out, ref, atol=2e-5, rtol=1e-5)
        # Gradients in float64 (_double): the max over the edges and the ReLUs have kinks where
        # float32 rounding alone can pick another side, and which it picks depends on the CPU.
        layer64, edges64 = _double(layer, edges)
        g_ref, = torch.autograd.grad(edge_wise(layer64, edges64).square().sum(), edges64)
        g_out, = torch.autograd.grad(layer64(edges64).square().sum(), edges64)
        assert g_ref.abs().max() > 1.0
        torch.testing.assert_close(g_out, g_ref, atol=1e-9, rtol=1e-9)
        wk = torch.autograd.grad(layer(edges).sum(), layer.k.weight)[0]
        assert wk.abs().sum() > 0                                       # the keys still learn


def test_agnn_split_first_linear_is_the_concatenated_edges_form():
    """AGNN.forward maps each layer's per-point input parts once per point (features.py): the
    same function as the paper's form on concatenated edges, for the shipped weights and random
    ones, gradients included; and gather() picks the rows x.gather did, at batch 1 and 2."""
    from cegc_ros.engine import default_weights, load_checkpoint
    from cegc_ros.model.features import AGNN, gather, knn

    def concatenated(agnn, edges, idx, point_feats):
        if agnn.c_point:
            edges = torch.cat([edges, point_feats.unsqueeze(2).expand(-1, -1, edges.shape[2], -1)], -1)
        f = agnn.layers[0](edges)
        outs = [f]
        for layer in agnn.layers[1:]:
            B, N, K = idx.shape
            nb = f.gather(1, idx.reshape(B, N * K, 1).expand(-1, -1, f.shape[-1])).reshape(B, N, K, -1)
            ctr = f.unsqueeze(2).expand_as(nb)
            f = layer(torch.cat([ctr, nb - ctr], dim=-1))
            outs.append(f)
        return agnn.head(torch.cat(outs, dim=-1))

    torch.manual_seed(0)
    shipped, _ = load_checkpoint(default_weights(), "cpu")
    for agnn, c_edge, c_point in ((shipped.agnn, 4, 33), (AGNN(6, 0, (8, 8, 16), 24), 6, 0),
                                  (AGNN(4, 5, (8, 16, 16), 24), 4, 5)):
        for B in (1, 2):
            xyz = torch.randn(B, 200, 3)
            idx = knn(xyz, 12)
            edges = torch.randn(B, 200, 12, c_edge, requires_grad=True)
            feats = torch.randn(B, 200, c_point, requires_grad=True) if c_point else None
            ref = concatenated(agnn, edges, idx, feats)
            out = agnn(edges, idx, feats)
            assert out.shape == ref.shape and ref.abs().max() > 0.5
            torch.testing.assert_close(out, ref, atol=3e-5, rtol=1e-5)
            # gradients in float64, as in the test above (a ReLU's kink: 8 of 28,800 float32
            # gradients of one random case differed by 3e-3 on an AVX2 EPYC, none elsewhere)
            agnn64, edges64, *feats64 = _double(agnn, edges, *([feats] if c_point else []))
            inputs = [edges64] + feats64
            f64 = feats64[0] if c_point else None
            g_ref = torch.autograd.grad(concatenated(agnn64, edges64, idx, f64).square().sum(), inputs)
            g_out = torch.autograd.grad(agnn64(edges64, idx, f64).square().sum(), inputs)
            for a, b in zip(g_out, g_ref):
                assert b.abs().max() > 0.5
                torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-9)
            x = torch.randn(B, 50, 7)
            picked = x.gather(1, idx[:, :, :5].reshape(B, -1, 1).clamp_max(49).expand(-1, -1, 7))
            assert torch.equal(gather(x, idx[:, :, :5].clamp_max(49)), picked.reshape(B, 200, 5, 7))


def test_overlap_labels_from_ground_truth():
    src = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [5.0, 5, 5]]])
    R = torch.eye(3)[None]
    t = torch.tensor([[0.0, 0.0, 1.0]])
    tgt = torch.tensor([[[0.0, 0, 1.0], [1.0, 0, 1.01], [-3.0, 0, 0]]])
    lx, ly = overlap_labels(src, tgt, R, t, torch.tensor([0.05]))
    assert lx.tolist() == [[1.0, 1.0, 0.0]]
    assert ly.tolist() == [[1.0, 1.0, 0.0]]


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="variant"):
        ModelConfig(variant="nope")
    with pytest.raises(ValueError, match="cams_centre"):
        ModelConfig(cams_centre="middle")
    with pytest.raises(ValueError, match="cams_centre_power"):
        ModelConfig(cams_centre_power=0.0)
    with pytest.raises(ValueError, match="overlap_ratio"):
        ModelConfig(overlap_ratio=0.0)
    with pytest.raises(ValueError, match="dilation"):
        ModelConfig(dilation=0)
    with pytest.raises(ValueError, match="geo_embedding"):
        ModelConfig(geo_embedding=1)
    with pytest.raises(ValueError, match="geo_sigma"):
        ModelConfig(geo_sigma=0.0)
    # checkpoints written before the field existed load with the paper's neighbourhood
    old = ModelConfig().to_dict()
    del old["dilation"], old["cams_centre"], old["cams_centre_power"], old["cams_centre_gradient"]
    del old["geo_embedding"], old["geo_sigma"]
    assert ModelConfig.from_dict(old).dilation == 1 and ModelConfig.from_dict(old).geo_embedding == 0
    assert ModelConfig.from_dict(old).cams_centre == "own"
    assert ModelConfig.from_dict(old).cams_centre_gradient is False
    assert ModelConfig.from_dict(ModelConfig().to_dict()) == ModelConfig()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cpu_and_cuda_agree():
    torch.manual_seed(0)
    model = CEGC(small_cfg()).eval()
    x = inputs(256, 256)
    with torch.no_grad():
        a = model(*x)
        b = model.cuda()(*(v.cuda() for v in x))
    assert torch.allclose(a.src_overlap_logits, b.src_overlap_logits.cpu(), atol=1e-3)
    assert torch.allclose(a.R, b.R.cpu(), atol=1e-3)


@pytest.mark.parametrize("variant,centre", [("ri", "own"), ("paper", "own"), ("ri", "overlap")])
def test_candidate_scores_are_the_all_pairs_scores_of_those_pairs_up_to_the_context(variant, centre):
    """score_candidates runs CAMS on N x k pairs: with every target point a candidate, the pair
    embedding equals forward()'s all-pairs one, so the scores agree exactly."""
    torch.manual_seed(0)
    cfg = small_cfg(variant=variant, overlap_ratio=1.0, cams_centre=centre)
    model = CEGC(cfg).eval()
    args = inputs(40, 40)
    with torch.no_grad():
        full = model(*args)
        allc = torch.arange(40).expand(1, 40, 40)
        cand = model.score_candidates(*args, k_learned=0, extra=allc)
        # forward() orders rows and columns by the top-N selection: undo it
        ix, iy = full.src_idx[0], full.tgt_idx[0]
        expect = torch.empty(40, 40)
        expect[ix[:, None], iy[None, :]] = full.scores[0]
    torch.testing.assert_close(cand.scores[0], expect, atol=1e-4, rtol=1e-4)
    assert cand.candidates.shape == (1, 40, 40)


def test_learned_candidates_are_the_nearest_in_feature_space_and_extra_ones_follow():
    torch.manual_seed(0)
    model = CEGC(small_cfg()).eval()
    args = inputs(50, 60)
    extra = torch.randint(0, 60, (1, 50, 2))
    with torch.no_grad():
        out = model.score_candidates(*args, k_learned=3, extra=extra)
    assert out.candidates.shape == out.scores.shape == (1, 50, 5) and out.conf_logits.shape == (1, 50)
    assert torch.equal(out.candidates[..., 3:], extra)
    sim = torch.nn.functional.normalize(out.src_features, dim=-1) @ \
        torch.nn.functional.normalize(out.tgt_features, dim=-1).transpose(1, 2)
    assert torch.equal(out.candidates[..., :3], sim.topk(3, dim=-1).indices)
    # the similarity it returns is that matrix, the one HOCE read (M_S): computed once
    assert out.similarity.shape == (1, 50, 60) and torch.allclose(out.similarity, sim, atol=1e-6)
    with torch.no_grad():
        fx, fy = model.features(*args)
        lx, ly = model.hoce(fx, fy)
    assert torch.allclose(lx, out.src_overlap_logits, atol=1e-5)
    assert torch.allclose(ly, out.tgt_overlap_logits, atol=1e-5)
    with pytest.raises(ValueError, match="needs k_learned > 0 or extra"):
        model.score_candidates(*args, k_learned=0)


@pytest.mark.parametrize("variant", ["ri", "paper"])
def test_both_clouds_as_one_batch_are_the_per_cloud_network(variant):
    """CEGC.features stacks equal-shaped clouds into one batch (faster); the outputs are the
    per-cloud path's, for a batch of two pairs too (each cross block sees its own partner)."""
    torch.manual_seed(0)
    cfg = small_cfg(variant=variant)
    cfg.attn_layers = 2
    model = CEGC(cfg).eval()
    one = inputs(96, 96, seed=3)
    two = [torch.cat([a, b]) for a, b in zip(one, inputs(96, 96, seed=4))]
    extra = torch.randint(0, 96, (2, 96, 2), generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        for args in (one, two):
            B = args[0].shape[0]
            a = model.score_candidates(*args, k_learned=3, extra=extra[:B], stack=True)
            b = model.score_candidates(*args, k_learned=3, extra=extra[:B], stack=False)
            assert torch.equal(a.candidates, b.candidates)
            for x, y in ((a.src_features, b.src_features), (a.tgt_features, b.tgt_features),
                         (a.scores, b.scores), (a.src_overlap_logits, b.src_overlap_logits)):
                assert torch.allclose(x, y, atol=1e-5)
        # the pairs of the batch do not mix: pair 1 alone gives what it gave in the batch
        alone = model.score_candidates(*[t[1:] for t in two], k_learned=3, extra=extra[1:])
        batch = model.score_candidates(*two, k_learned=3, extra=extra)
        assert torch.allclose(alone.scores[0], batch.scores[1], atol=1e-5)
        # unequal clouds take the per-cloud path
        out = model.score_candidates(*inputs(96, 80), k_learned=3)
        assert out.tgt_features.shape == (1, 80, 32)


@pytest.mark.parametrize("variant", ["ri", "paper"])
def test_dilated_agnn_gathers_every_dth_of_the_k_d_nearest_in_its_later_layers(variant):
    """dilation d: layer 1's edges are still the k nearest neighbours, layers 2 and 3 gather
    from every d-th of the k x d nearest (the nearest first); the same weights with d = 1 are
    the undilated network, and with d = 3 a different function of the same points."""
    from cegc_ros.model.features import knn, paper_edges, ppf_edges
    torch.manual_seed(0)
    src, _, nrm, _, desc, _ = inputs(120, 120, seed=7)
    plain = CEGC(small_cfg(variant=variant)).eval()
    wide = CEGC(small_cfg(variant=variant, dilation=3)).eval()
    wide.load_state_dict(plain.state_dict())
    k = plain.cfg.k
    idx, near36 = knn(src, k), knn(src, 3 * k)
    assert torch.equal(near36[..., :k], idx)
    far = near36[..., ::3]
    assert far.shape == idx.shape and torch.equal(far[..., 0], idx[..., 0])
    with torch.no_grad():
        if variant == "paper":
            edges, feats = paper_edges(src, idx), None
        else:
            edges, feats = ppf_edges(src, nrm, idx), desc
        by_hand = plain.agnn(edges, idx, feats, far)
        got = wide.encode(src, nrm, desc)
        assert torch.allclose(got, by_hand, atol=1e-6)
        assert torch.equal(plain.encode(src, nrm, desc), plain.agnn(edges, idx, feats))
        assert (got - plain.encode(src, nrm, desc)).abs().max() > 1e-3


def test_distance_knots_are_log_spaced_and_clamped():
    from cegc_ros.model.features import distance_knots
    xyz = torch.tensor([[[0.0, 0, 0], [0.04, 0, 0], [0, 1.5, 0], [0, 0, 3.0]]])
    t = distance_knots(xyz, 32, sigma=0.04, reach=1.5)
    assert t.shape == (1, 4, 4)
    assert torch.allclose(torch.diagonal(t[0]), torch.zeros(4))
    assert t[0, 0, 1].item() == pytest.approx(31 * np.log(2.0) / np.log1p(1.5 / 0.04), rel=1e-5)
    assert t[0, 0, 2].item() == pytest.approx(31.0, abs=1e-4)       # at reach: the last knot
    assert t[0, 0, 3].item() == 31.0                                 # beyond: clamped to it
    assert torch.equal(t, t.transpose(1, 2))


def test_distance_attention_is_geotransformers_form_on_hat_functions():
    """AttentionBlock with geo_dim G: logit_ij = q_i . (k_j + W_r r_ij) / sqrt(d) per head, with
    r_ij the pair's distance on G hat functions (weights 1 - w and w on the two knots around it),
    which the block computes with two gathers; checked against that form written out."""
    import torch.nn.functional as F
    from cegc_ros.model.features import AttentionBlock, distance_knots
    torch.manual_seed(0)
    B, N, C, h, G = 2, 40, 16, 2, 8
    blk = AttentionBlock(C, h, geo_dim=G).eval()
    with torch.no_grad():
        blk.geo.normal_(0, 1.0)
    x, xyz = torch.randn(B, N, C), torch.rand(B, N, 3) - 0.5
    t = distance_knots(xyz, G, sigma=0.04)
    hat = (1 - (t.unsqueeze(-1) - torch.arange(G)).abs()).clamp_min(0)      # (B, N, N, G)
    assert torch.allclose(hat.sum(-1), torch.ones(B, N, N), atol=1e-5)
    with torch.no_grad():
        q = blk.qkv_q(x).view(B, N, h, C // h).transpose(1, 2)
        k = blk.qkv_k(x).view(B, N, h, C // h).transpose(1, 2)
        v = blk.qkv_v(x).view(B, N, h, C // h).transpose(1, 2)
        r = torch.einsum("hcg,bnmg->bhnmc", blk.geo, hat)                   # W_r r_ij per head
        logits = (q.unsqueeze(3) * (k.unsqueeze(2) + r)).sum(-1) * (C // h) ** -0.5
        msg = torch.softmax(logits, -1) @ v
        want = x + blk.update(torch.cat([x, blk.merge(msg.transpose(1, 2).reshape(B, N, C))], -1))
        got = blk(x, x, t)
    assert torch.allclose(got, want, atol=1e-5)
    assert (got - blk(x, x, torch.zeros_like(t))).abs().max() > 1e-2       # the distances matter
    with pytest.raises(ValueError, match="pairs' distances"):
        blk(x, x)


def test_distance_attention_starts_as_the_network_without_it_and_stays_rigid_invariant():
    """geo_embedding with its maps at zero is the network without it (a warm start's step 0);
    with maps drawn at random it is another function, still of the clouds' shapes only (a moved
    source cloud gives the same candidates and scores), and one batch of both clouds is the
    per-cloud path."""
    torch.manual_seed(0)
    plain = CEGC(small_cfg(cams_centre="overlap")).eval()
    geo = CEGC(small_cfg(cams_centre="overlap", geo_embedding=16)).eval()
    assert geo.load_state_dict(plain.state_dict(), strict=False).missing_keys == ["context.self_blocks.0.geo"]
    src, tgt, ns, nt, ds, dt = inputs(120, 120, seed=5)
    with torch.no_grad():
        a = plain.score_candidates(src, tgt, ns, nt, ds, dt, k_learned=4)
        b = geo.score_candidates(src, tgt, ns, nt, ds, dt, k_learned=4)
        assert torch.equal(a.candidates, b.candidates) and torch.allclose(a.scores, b.scores, atol=1e-6)
        geo.context.self_blocks[0].geo.normal_(0, 2.0)
        c = geo.score_candidates(src, tgt, ns, nt, ds, dt, k_learned=4)
        assert (c.src_features - a.src_features).abs().max() > 1e-3     # float noise: ~1e-6
        R = torch.tensor(random_rotation(np.random.default_rng(4)), dtype=torch.float32)
        moved = src @ R.T + torch.tensor([0.3, -0.8, 0.5])
        d = geo.score_candidates(moved, tgt, ns @ R.T, nt, ds, dt, k_learned=4)
        assert torch.equal(c.candidates, d.candidates)
        torch.testing.assert_close(c.scores, d.scores, atol=1e-3, rtol=1e-3)
        e = geo.score_candidates(src, tgt, ns, nt, ds, dt, k_learned=4, stack=False)
        assert torch.equal(c.candidates, e.candidates)
        torch.testing.assert_close(c.scores, e.scores, atol=1e-5, rtol=1e-5)


def test_cams_overlap_centre_is_hoces_sharpened_centroid():
    """cams_centre "overlap": rho is each point's distance from the centroid weighted by
    sigmoid(HOCE logit) ** cams_centre_power; equal logits give the cloud's own centroid."""
    from cegc_ros.model.cams import CAMS
    g = torch.Generator().manual_seed(3)
    o = torch.rand(2, 40, 3, generator=g) * 4.0
    logits = torch.randn(2, 40, generator=g) * 2.0
    cams = CAMS(16, 8, "ri", 64, centre="overlap", centre_power=4.0)
    w = torch.sigmoid(logits.double()) ** 4
    c = (w[..., None] * o.double()).sum(1, keepdim=True) / w.sum(1)[:, None, None]
    expect = (o.double() - c).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(cams._radius(o, logits).double(), expect, atol=1e-5, rtol=1e-5)
    rx, ry = cams._spatial(o, o[:, :30], torch.zeros(2, 40), torch.zeros(2, 30))
    own = CAMS(16, 8, "ri", 64)._spatial(o, o[:, :30])
    torch.testing.assert_close(rx, own[0])
    torch.testing.assert_close(ry, own[1])
    # a confident point far from the rest pulls the centre to itself at a high power
    sharp = CAMS(16, 8, "ri", 64, centre="overlap", centre_power=64.0)
    peak = torch.full((2, 40), -4.0)
    peak[:, 7] = 6.0
    assert sharp._radius(o, peak)[:, 7].abs().max() < 1e-3
    # every logit far below zero: still the (equal-weight) centroid, finite
    torch.testing.assert_close(cams._radius(o, torch.full((2, 40), -200.0)), CAMS(16, 8, "ri", 64)._spatial(o, o)[0])
    # no gradient reaches HOCE's logits through the centre
    lg, og = logits.clone().requires_grad_(True), o.clone().requires_grad_(True)
    cams._radius(og, lg).sum().backward()
    assert lg.grad is None and og.grad is not None
    # ... unless centre_gradient: the same radii, and the logits get a gradient
    through = CAMS(16, 8, "ri", 64, centre="overlap", centre_power=4.0, centre_gradient=True)
    lg = logits.clone().requires_grad_(True)
    r = through._radius(o, lg)
    torch.testing.assert_close(r, cams._radius(o, logits))
    r.sum().backward()
    assert lg.grad is not None and lg.grad.abs().max() > 0
    with pytest.raises(ValueError, match="overlap logits"):
        cams._spatial(o, o)


def test_overlap_centre_network_is_invariant_to_each_clouds_pose():
    """The "ri" network with cams_centre "overlap" reads only rigid-invariant inputs: moving the
    source cloud (its normals turned with it) leaves every candidate and score as they were."""
    torch.manual_seed(0)
    model = CEGC(small_cfg(cams_centre="overlap")).eval()
    src, tgt, ns, nt, ds, dt = inputs(120, 100, seed=5)
    R = torch.tensor(random_rotation(np.random.default_rng(2)), dtype=torch.float32)
    moved = src @ R.T + torch.tensor([0.7, -1.2, 0.4])
    with torch.no_grad():
        a = model.score_candidates(src, tgt, ns, nt, ds, dt, k_learned=4)
        b = model.score_candidates(moved, tgt, ns @ R.T, nt, ds, dt, k_learned=4)
    assert torch.equal(a.candidates, b.candidates)
    torch.testing.assert_close(a.scores, b.scores, atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(a.src_overlap_logits, b.src_overlap_logits, atol=1e-3, rtol=1e-3)
