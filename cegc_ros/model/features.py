"""Feature extraction and enhancement (paper section "Feature Extraction and Enhancement").

AGNN: kNN (k=12) edge encodings, three attention-aggregation layers, max-pool over the
neighbourhood per layer, concatenation, MLP to C2 = 256. Then interleaved self- and
cross-attention between the two clouds.

Choices where the paper is vague (recorded here, where the code is):
- Query of the neighbourhood attention: the paper attends from f_{x_i} to f_{x_j}; the centre
  point's query is the max over its edge embeddings (so it exists at layer 1, where only edge
  encodings exist), keys/values are the edge embeddings.
- Layer l+1's edges are ``[f_i, f_j - f_i]`` gathered from layer l's point features (the
  paper says only that layer l's output feeds layer l+1).
- LayerNorm instead of BatchNorm after each linear layer: batch size 1 on a CPU, and BatchNorm's
  running statistics shift between synthetic training and real sensor data.
- ``nn.Linear`` instead of 1x1 convolutions (same maths; 1.5-3x faster on this CPU).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def mlp(dims: list[int], last_act: bool = True) -> nn.Sequential:
    """Linear (+ LayerNorm + ReLU) stack over the last dimension."""
    layers: list[nn.Module] = []
    for i in range(len(dims) - 1):
        layers.append(nn.Linear(dims[i], dims[i + 1]))
        if i < len(dims) - 2 or last_act:
            layers.append(nn.LayerNorm(dims[i + 1]))
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


def knn(xyz: Tensor, k: int, exact: bool = False) -> Tensor:
    """Indices (B, N, k) of each point's k nearest neighbours, the point itself excluded, the
    nearest first. ``exact``: squared distances summed coordinate by coordinate, which torch and
    ONNX Runtime round alike (a dilated neighbourhood picks by rank at every d-th boundary, where
    ``torch.cdist``'s matrix form and its ONNX export rounded differently: overlap logits 0.1
    apart; 1e-5 this way), at ~7% more of ONNX Runtime's network time, so only where needed."""
    k_eff = min(k + 1, xyz.shape[1])
    d = (xyz.unsqueeze(2) - xyz.unsqueeze(1)).square().sum(-1) if exact else torch.cdist(xyz, xyz)   # (B, N, N)
    idx = d.topk(k_eff, dim=-1, largest=False).indices                   # (B, N, k+1)
    idx = idx[..., 1:]
    if idx.shape[-1] < k:   # tiny clouds: repeat the farthest neighbour
        pad = idx[..., -1:].expand(*idx.shape[:-1], k - idx.shape[-1])
        idx = torch.cat([idx, pad], dim=-1)
    return idx


def gather(x: Tensor, idx: Tensor) -> Tensor:
    """x (B, M, C), idx (B, N, K) indices into M -> (B, N, K, C): x's rows picked.

    A row gather (ONNX ``Gather``) rather than ``x.gather`` over an index expanded to C
    channels (``Expand`` + ``GatherElements``, 13% of the network's time under ONNX Runtime on
    a 1.5k-point crop, docs/performance.md); the same values."""
    B, M, C = x.shape
    if B == 1:
        return x[0][idx[0]].unsqueeze(0)
    base = torch.arange(B, device=idx.device).view(B, 1, 1) * M
    return x.reshape(B * M, C)[idx + base]


def paper_edges(xyz: Tensor, idx: Tensor) -> Tensor:
    """The paper's H_{x_i} = [x_i, x_i - x_j]: (B, N, K, 6). Rotation-variant."""
    nb = gather(xyz, idx)                                                # (B, N, K, 3)
    ctr = xyz.unsqueeze(2).expand_as(nb)
    return torch.cat([ctr, ctr - nb], dim=-1)


def ppf_edges(xyz: Tensor, normals: Tensor, idx: Tensor) -> Tensor:
    """Point-pair features [|d|, n_i.d^, n_j.d^, n_i.n_j] per edge: (B, N, K, 4). Rotation-invariant.

    ``|d|`` is divided by the mean neighbour distance of the cloud so that the encoding does
    not depend on point density.
    """
    nb = gather(xyz, idx)                                                # (B, N, K, 3)
    nn_ = gather(normals, idx)                                           # (B, N, K, 3)
    d = nb - xyz.unsqueeze(2)
    dist = d.norm(dim=-1, keepdim=True)                                  # (B, N, K, 1)
    dn = d / dist.clamp_min(1e-8)
    ni = normals.unsqueeze(2).expand_as(nn_)
    scale = dist.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-8)
    return torch.cat([
        dist / scale,
        (ni * dn).sum(-1, keepdim=True),
        (nn_ * dn).sum(-1, keepdim=True),
        (ni * nn_).sum(-1, keepdim=True),
    ], dim=-1)


class AGNNLayer(nn.Module):
    """One attention-aggregation layer over kNN edges: (B, N, K, C_in) -> (B, N, C_out)."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.embed = mlp([c_in, c_out, c_out])          # f_b = MLP(f_a)
        self.q = nn.Linear(c_out, c_out, bias=False)
        self.k = nn.Linear(c_out, c_out, bias=False)
        self.v = nn.Linear(c_out, c_out, bias=False)
        self.out = mlp([c_out, c_out])                   # f_{C1}
        self.scale = c_out ** -0.5

    def forward(self, edges: Tensor) -> Tensor:
        """Attention of the centre's query over its K edge embeddings: a_j = softmax_j(q . W_k
        fb_j / sqrt(C)), then out(sum_j a_j W_v fb_j) + centre. Computed with the keys' and
        values' linear maps moved onto the N points (q . W_k fb_j = (W_k^T q) . fb_j and
        sum_j a_j W_v fb_j = W_v sum_j a_j fb_j, both bias-free): the same function, two
        (N*K, C) x (C, C) products fewer, 17-25% of the AGNN's time on a 2-core Xeon
        (docs/performance.md); equal to the edge-wise form to float rounding (test_model)."""
        return self.attend(self.embed(edges))

    def attend(self, fb: Tensor) -> Tensor:
        """The attention over the edge embeddings fb (B, N, K, C) -> (B, N, C)."""
        centre = fb.max(dim=2).values                                    # (B, N, C)  zeta: max-pool
        qk = (self.q(centre) @ self.k.weight).unsqueeze(2)               # (B, N, 1, C): W_k^T q
        a = torch.softmax((qk * fb).sum(-1) * self.scale, dim=-1)        # (B, N, K)
        agg = self.v((a.unsqueeze(-1) * fb).sum(2))                      # (B, N, C)
        return self.out(agg) + centre

    def from_first_linear(self, pre: Tensor) -> Tensor:
        """forward() given its first linear map's output pre = embed[0](edges) (B, N, K, C)."""
        return self.attend(self.embed[1:](pre))


class AGNN(nn.Module):
    """Three AGNN layers, per-layer outputs concatenated, MLP to C2."""

    def __init__(self, c_edge: int, c_point: int, dims: tuple[int, ...], c_out: int) -> None:
        super().__init__()
        self.c_point = c_point
        self.layers = nn.ModuleList()
        c_prev = None
        for i, d in enumerate(dims):
            c_in = c_edge + c_point if i == 0 else 2 * c_prev
            self.layers.append(AGNNLayer(c_in, d))
            c_prev = d
        self.head = mlp([sum(dims), c_out, c_out], last_act=False)

    def forward(self, edges: Tensor, idx: Tensor, point_feats: Tensor | None,
                idx_far: Tensor | None = None) -> Tensor:
        """edges (B, N, K, c_edge), idx (B, N, K), point_feats (B, N, c_point) or None -> (B, N, C2).
        ``idx_far`` (B, N, K): the neighbours layers 2 and 3 gather from (a dilated
        neighbourhood, ``ModelConfig.dilation``); None: ``idx``, as layer 1's edges."""
        # Each layer's first linear map is split by its input's parts, so the parts that are the
        # same along a point's K edges are mapped once per point, not per edge: layer 1's input
        # [edge, point_feat] gives W_e edge + (W_p point_feat + b); layer l's [f_i, f_j - f_i]
        # gives W_2 f_j + ((W_1 - W_2) f_i + b), W_2 f gathered to the edges. The same function
        # as mapping the concatenated edges (to float rounding; test_model), without the (N, K)
        # copies of point features and with a K-th of those products.
        lin = self.layers[0].embed[0]
        if self.c_point:
            ce = edges.shape[-1]
            pre = (F.linear(edges, lin.weight[:, :ce])
                   + F.linear(point_feats, lin.weight[:, ce:], lin.bias).unsqueeze(2))
        else:
            pre = lin(edges)
        f = self.layers[0].from_first_linear(pre)                        # (B, N, C1)
        outs = [f]
        idx = idx if idx_far is None else idx_far
        for layer in self.layers[1:]:
            lin, c = layer.embed[0], f.shape[-1]
            w_ctr, w_nb = lin.weight[:, :c], lin.weight[:, c:]
            pre = gather(F.linear(f, w_nb), idx) + F.linear(f, w_ctr - w_nb, lin.bias).unsqueeze(2)
            f = layer.from_first_linear(pre)
            outs.append(f)
        return self.head(torch.cat(outs, dim=-1))


def distance_knots(xyz: Tensor, knots: int, sigma: float, reach: float = 1.5) -> Tensor:
    """Each pair's distance within one cloud as a position on ``knots`` knots: (B, N, N) floats
    in [0, knots - 1], log-spaced, ``log(1 + d / sigma) / log(1 + reach / sigma) * (knots - 1)``
    (so the knots are dense near a point and sparse far away; pairs beyond ``reach``, in
    normalised units where a cloud's rms radius is at most 0.5, sit on the last). Rigid-invariant."""
    d = torch.cdist(xyz, xyz)
    return (torch.log1p(d / sigma) * ((knots - 1) / math.log1p(reach / sigma))).clamp(max=knots - 1)


class AttentionBlock(nn.Module):
    """f <- f + f_C2([f, sum_j e_ij v_j]) with multi-head attention (self or cross).

    ``geo_dim`` > 0 (self-attention only, ``ModelConfig.geo_embedding``): the attention logits
    also read each pair's distance, GeoTransformer's form ``q_i . (k_j + W_r r_ij) / sqrt(d)``
    (Qin et al., CVPR 2022, its geometric structure embedding's distance part) with r_ij the
    pair's distance embedded on ``geo_dim`` piecewise-linear hat functions
    (:func:`distance_knots`) instead of GeoTransformer's sinusoids: ``(W_r^T q_i) . r_ij`` per
    head is then each query's own piecewise-linear function of distance, read at two knots a pair
    (two gathers of (B, N, N) a head) where the sinusoids' (B, N, N, geo_dim) embedding and its
    product cost the network ~60% more time on 2 cores (42 -> 68 ms a pair, torch, 512 points,
    32 sinusoids). The gathers run head by head with the (B, N, M) knot indices shared: one
    gather over (B, h, N, M) needs the indices expanded to every head, which in ONNX Runtime is
    an int64 Expand and costs a 512-point cloud 4.2-4.9 ms against 2.8-3.2 (the same bias within
    5e-7; docs/performance.md, "The weights of arm 22"). Added to the logits as SDPA's float
    mask. ``geo`` starts at zero, so a network warm-started from weights without it begins as
    that network (training/_load_weights)."""

    def __init__(self, dim: int, heads: int, geo_dim: int = 0) -> None:
        super().__init__()
        self.heads = heads
        self.qkv_q = nn.Linear(dim, dim)
        self.qkv_k = nn.Linear(dim, dim)
        self.qkv_v = nn.Linear(dim, dim)
        self.merge = nn.Linear(dim, dim)
        self.update = mlp([2 * dim, dim, dim], last_act=False)
        self.geo = None
        if geo_dim:
            self.geo = nn.Parameter(torch.zeros(heads, dim // heads, geo_dim))   # W_r per head

    def forward(self, x: Tensor, src: Tensor, knots: Tensor | None = None) -> Tensor:
        """x (B, N, C) attends to src (B, M, C) -> (B, N, C); ``knots`` (B, N, M): the pairs'
        :func:`distance_knots` (blocks with geo_dim > 0 only)."""
        B, N, C = x.shape
        h = self.heads
        q = self.qkv_q(x).view(B, N, h, C // h).transpose(1, 2)         # (B, h, N, C/h)
        k = self.qkv_k(src).view(B, -1, h, C // h).transpose(1, 2)
        v = self.qkv_v(src).view(B, -1, h, C // h).transpose(1, 2)
        bias = None
        if self.geo is not None:
            if knots is None:
                raise ValueError("this attention block reads the pairs' distances; none were given")
            u = torch.einsum("bhnc,hcg->bhng", q, self.geo) * (C // h) ** -0.5   # (B, h, N, G)
            slope = u[..., 1:] - u[..., :-1]                               # (B, h, N, G - 1)
            lo = knots.floor().clamp(max=self.geo.shape[-1] - 2)           # (B, N, M)
            w, i = knots - lo, lo.long()                                   # (B, N, M) each
            bias = torch.stack([torch.addcmul(u[:, j].gather(-1, i), slope[:, j].gather(-1, i), w)
                                for j in range(h)], dim=1)                 # (B, h, N, M)
        msg = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)     # (B, h, N, C/h)
        msg = self.merge(msg.transpose(1, 2).reshape(B, N, C))
        return x + self.update(torch.cat([x, msg], dim=-1))


class ContextEnhancer(nn.Module):
    """Interleaved self- then cross-attention blocks, shared between the two clouds. With
    ``geo_dim`` > 0 the self-attention blocks read each cloud's pairwise distances
    (:class:`AttentionBlock`); the cross blocks never do (the clouds' frames differ)."""

    def __init__(self, dim: int, heads: int, layers: int, geo_dim: int = 0, geo_sigma: float = 0.04) -> None:
        super().__init__()
        self.geo_dim, self.geo_sigma = geo_dim, geo_sigma
        self.self_blocks = nn.ModuleList(AttentionBlock(dim, heads, geo_dim) for _ in range(layers))
        self.cross_blocks = nn.ModuleList(AttentionBlock(dim, heads) for _ in range(layers))

    def _knots(self, xyz: Tensor | None) -> Tensor | None:
        if not self.geo_dim:
            return None
        if xyz is None:
            raise ValueError("the context blocks read pairwise distances: pass the clouds' points")
        return distance_knots(xyz, self.geo_dim, self.geo_sigma)

    def forward(self, fx: Tensor, fy: Tensor, x: Tensor | None = None, y: Tensor | None = None
                ) -> tuple[Tensor, Tensor]:
        """fx (B, N, C), fy (B, M, C); x (B, N, 3), y (B, M, 3): the clouds' points (read only
        with geo_dim > 0)."""
        ex, ey = self._knots(x), self._knots(y)
        for sa, ca in zip(self.self_blocks, self.cross_blocks):
            fx, fy = sa(fx, fx, ex), sa(fy, fy, ey)
            fx, fy = ca(fx, fy), ca(fy, fx)
        return fx, fy

    def stacked(self, f: Tensor, b: int, xyz: Tensor | None = None) -> Tensor:
        """The same blocks on both clouds stacked as one batch: f (2b, N, C), the source clouds
        first -> (2b, N, C); xyz (2b, N, 3) as f. Each cross block attends from every cloud to
        its partner (the other half of the batch)."""
        e = self._knots(xyz)
        for sa, ca in zip(self.self_blocks, self.cross_blocks):
            f = sa(f, f, e)
            f = ca(f, torch.cat([f[b:], f[:b]]))
        return f
