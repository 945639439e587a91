"""SDM-UniPS (Ikehata, CVPR 2023) written from the facts in ``shared/reference/sdm_unips/SPEC.md``.

Pipeline for one object with N images of side H (square, H a multiple of the canonical resolution G):

1. ``encode``: every image ``[I*M, M]`` (4 channels) is encoded by a ConvNeXt backbone with light-axis attention
   ("comm" blocks, across the N images, per pixel, per scale) and a UPerNet fusion head, once for the whole image
   resized to GxG and once for each of the s^2 polyphase sub-images ``x[a::s, b::s]`` (s = H/G). The sub-image
   features are interleaved back to H/4 and the resized-pass features (upsampled to H/4) are added. The features are
   then smoothed with a depthwise Gaussian. Result: ``(B, N, C, H/4, W/4)``.
2. ``decode``: for each requested pixel, the raw RGB of the N images (at the decoder resolution) and the features
   (bilinear ``grid_sample``) go through ``glc_upsample`` (attention across the images), ``glc_aggregation``
   (attention across the images + PMA pooling to one vector per pixel) and the ``regressor`` (attention across the
   pixels of one sample set, then MLP heads).

Submodule names are chosen so that the ``paper`` preset's ``state_dict`` keys equal the published checkpoints' keys
(without the ``module.`` prefix of their DataParallel wrapper), in the same order.
"""
from __future__ import annotations

import contextlib
import math

import torch
import torch.nn.functional as F
from torch import nn

from networks.config import SDMUniPSConfig

OUTPUT_KEYS = {"normal": ("normal",), "brdf": ("normal", "base_color", "roughness", "metallic")}

# ------------------------------------------------------------------------------------------ reference switch
_REFERENCE = False


@contextlib.contextmanager
def reference_ops():
    """Run the straightforward implementation (docs/speed.md) inside this block: explicit
    attention with separate K/V projections, the PMA's K/V projected per image, the 2-D convolution Gaussian
    smoothing and the UPerNet head in contiguous (NCHW) memory. Same function, other rounding; the equality tests
    compare the two (``tests/test_networks_speed_equality.py``). Not thread-safe (a module-level switch)."""
    global _REFERENCE
    was = _REFERENCE
    _REFERENCE = True
    try:
        yield
    finally:
        _REFERENCE = was


# ----------------------------------------------------------------------------------------------------- attention
#: Key sequences up to this length use an explicit softmax(QK^T)V: for the short light-axis sequences (a handful of
#: images per pixel, but thousands of pixels) it is ~3x faster on CPU than PyTorch's fused kernel in bfloat16 and
#: ~1.4x in float32 (fwd+bwd, `(1536, 8, 4, 12)`); long sequences (the regressor's pixel sets) keep the fused kernel.
SHORT_SEQUENCE = 64


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, scale: float, dropout: float = 0.0,
              training: bool = False) -> torch.Tensor:
    """Softmax attention. q: (B, h, Lq, d); k, v: (B, h, Lk, d) -> (B, h, Lq, d)."""
    if k.shape[-2] > SHORT_SEQUENCE:
        return F.scaled_dot_product_attention(q, k, v, dropout_p=dropout if training else 0.0, scale=scale)
    w = torch.softmax((q @ k.transpose(-1, -2)) * scale, dim=-1)
    if training and dropout > 0:
        w = F.dropout(w, dropout)
    return w @ v


def _fused_linear_gelu_works() -> bool:
    """Whether oneDNN's fused linear + exact GELU (``torch.ops.mkldnn._linear_pointwise``) runs here and agrees
    with ``gelu(linear(.))`` (a private op: checked once, the plain ops are used otherwise)."""
    try:
        g = torch.Generator().manual_seed(0)
        x, w = torch.randn(8, 5, generator=g), torch.randn(6, 5, generator=g)
        with torch.inference_mode():
            y = torch.ops.mkldnn._linear_pointwise(x, w, None, "gelu", [], "none")
        return bool(torch.allclose(y, F.gelu(F.linear(x, w)), atol=1e-6))
    except Exception:  # noqa: BLE001 - any failure: not available
        return False


_FUSED_GELU: bool | None = None


def _linear_gelu(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``gelu(x @ weight.T)`` (exact erf GELU). x: (M, in) -> (M, out). One fused oneDNN call for float32 CPU
    tensors outside autocast and autograd, else the two plain ops."""
    global _FUSED_GELU
    if (x.device.type == "cpu" and x.dtype == torch.float32 and weight.dtype == torch.float32
            and not torch.is_autocast_enabled("cpu") and not (torch.is_grad_enabled() and weight.requires_grad)):
        if _FUSED_GELU is None:
            _FUSED_GELU = _fused_linear_gelu_works()
        if _FUSED_GELU:
            return torch.ops.mkldnn._linear_pointwise(x.contiguous(), weight, None, "gelu", [], "none")
    return F.gelu(F.linear(x, weight))


class MAB(nn.Module):
    """Multi-head attention block as published (all linears without bias).

    ``Q = fc_q(ln0(x))``, ``K = fc_k(y)``, ``V = fc_v(y)`` (K and V from the *un-normalised* input); per-head softmax
    attention ``A``; ``O = Q + A``; ``O = O + fc_o2(gelu(fc_o1(ln1(O))))``. ``scale`` is the softmax scale (the
    published network uses 1/sqrt(dim_out) in most places and 1/sqrt(dim_out/heads) in the regressor).
    """

    def __init__(self, dim_q: int, dim_k: int, dim_out: int, heads: int, ff: int, *, ln: bool, scale: float,
                 dropout: float, ln_eps: float = 1e-5):
        super().__init__()
        if dim_out % heads:
            raise ValueError(f"attention width {dim_out} not divisible by {heads} heads")
        self.dim_out = dim_out
        self.heads = heads
        self.scale = float(scale)
        self.dropout = float(dropout)
        self.fc_q = nn.Linear(dim_q, dim_out, bias=False)
        self.fc_k = nn.Linear(dim_k, dim_out, bias=False)
        self.fc_v = nn.Linear(dim_k, dim_out, bias=False)
        if ln:
            self.ln0 = nn.LayerNorm(dim_q, eps=ln_eps)
            self.ln1 = nn.LayerNorm(dim_out, eps=ln_eps)
        else:
            self.ln0 = None
            self.ln1 = None
        self.fc_o1 = nn.Linear(dim_out, ff, bias=False)
        self.fc_o2 = nn.Linear(ff, dim_out, bias=False)

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """x: (B, Lq, dim_q) queries; y: (B, Lk, dim_k) keys/values. Returns (B, Lq, dim_out)."""
        if _REFERENCE or self.training:
            return self._forward_reference(x, y)
        xq = self.ln0(x) if self.ln0 is not None else x
        q = self.fc_q(xq)
        d, h = self.dim_out, self.heads
        if y is x:
            # One GEMM for K and V (the input is read once); same products, summed in the same order.
            k, v = F.linear(y, torch.cat([self.fc_k.weight, self.fc_v.weight])).split(d, dim=-1)
        else:
            k, v = self.fc_k(y), self.fc_v(y)
        # Strided head views straight into the fused kernel (no copies): (B, L, d) -> (B, h, L, d/h).
        a = F.scaled_dot_product_attention(q.unflatten(-1, (h, d // h)).transpose(1, 2),
                                           k.unflatten(-1, (h, d // h)).transpose(1, 2),
                                           v.unflatten(-1, (h, d // h)).transpose(1, 2), scale=self.scale)
        o = q + a.transpose(1, 2).reshape(q.shape)
        return self._feed_forward(o, 0.0)

    def _feed_forward(self, o: torch.Tensor, p: float) -> torch.Tensor:
        o_ = self.ln1(o) if self.ln1 is not None else o
        if not (_REFERENCE or self.training):
            # GELU fused into the first GEMM (oneDNN post-op, exact erf) and the residual into the second (addmm).
            hidden = _linear_gelu(o_.reshape(-1, o_.shape[-1]), self.fc_o1.weight)
            out = torch.addmm(o.reshape(-1, o.shape[-1]), hidden, self.fc_o2.weight.t())
            return out.view(o.shape)
        hidden = F.dropout(F.gelu(self.fc_o1(o_)), p, self.training)
        return o + F.dropout(self.fc_o2(hidden), p, self.training)

    def _forward_reference(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The straightforward forward pass (training uses it: its short-sequence attention is faster fwd+bwd)."""
        p = self.dropout if self.training else 0.0
        xq = self.ln0(x) if self.ln0 is not None else x
        q = self.fc_q(xq)
        k = self.fc_k(y)
        v = self.fc_v(y)
        b, lq, d = q.shape
        lk = k.shape[1]
        h = self.heads
        qh = q.view(b, lq, h, d // h).transpose(1, 2)
        kh = k.view(b, lk, h, d // h).transpose(1, 2)
        vh = v.view(b, lk, h, d // h).transpose(1, 2)
        a = attention(qh, kh, vh, self.scale, p, self.training)
        o = q + a.transpose(1, 2).reshape(b, lq, d)
        return self._feed_forward(o, p)


class SAB(nn.Module):
    """Self-attention block: ``mab(x, x)``."""

    def __init__(self, dim_in: int, dim_out: int, heads: int, ff: int, *, scale: float, dropout: float,
                 ln_eps: float = 1e-5):
        super().__init__()
        self.mab = MAB(dim_in, dim_in, dim_out, heads, ff, ln=True, scale=scale, dropout=dropout, ln_eps=ln_eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, L, dim_in) -> (B, L, dim_out)."""
        return self.mab(x, x)


class PMA(nn.Module):
    """Pooling by multi-head attention: a learned seed ``S (1, 1, dim)`` attends to the set (no LayerNorms)."""

    def __init__(self, dim: int, heads: int, ff: int, *, scale: float, dropout: float):
        super().__init__()
        self.S = nn.Parameter(torch.empty(1, 1, dim))
        nn.init.xavier_uniform_(self.S)
        self.mab = MAB(dim, dim, dim, heads, ff, ln=False, scale=scale, dropout=dropout)

    #: Set by SDMUniPS from its ``fp32_under_autocast``: pool in float32 at inference under autocast.
    fp32_under_autocast = False

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, L, dim) -> (B, 1, dim)."""
        if _REFERENCE or self.training:
            return self.mab(self.S.expand(x.shape[0], -1, -1).to(x.dtype), x)
        dev = x.device.type
        if self.fp32_under_autocast and dev in ("cpu", "cuda") and torch.is_autocast_enabled(dev):
            with torch.autocast(device_type=dev, enabled=False):
                return self._pool(x.float())
        return self._pool(x)

    def _pool(self, x: torch.Tensor) -> torch.Tensor:
        """Inference form of ``mab(S, x)``: the query is one constant vector, so its scores against the keys are
        ``x @ (W_k,h^T q_h)`` per head and the values are projected after pooling, ``W_v,h (sum_j a_j x_j)``: the
        K and V projections of all L elements (2 L d^2 per set) become ``L d h + h d^2``. Same sums, reassociated."""
        mab = self.mab
        b, length, dim_in = x.shape
        d, h = mab.dim_out, mab.heads
        dh = d // h
        q = mab.fc_q(self.S.reshape(1, -1).to(x.dtype))                                   # (1, d)
        wk = mab.fc_k.weight.to(x.dtype).reshape(h, dh, dim_in)
        u = torch.einsum("he,hec->ch", q.reshape(h, dh), wk) * mab.scale                 # (dim_in, h)
        w = torch.softmax((x @ u).transpose(1, 2), dim=-1)                               # (B, h, L)
        pooled = torch.bmm(w, x)                                                          # (B, h, dim_in)
        wv = mab.fc_v.weight.to(x.dtype).reshape(h, dh, dim_in)
        a = torch.bmm(pooled.transpose(0, 1), wv.transpose(1, 2)).transpose(0, 1)         # (B, h, dh)
        o = q.reshape(1, 1, d) + a.reshape(b, 1, d)
        return mab._feed_forward(o, 0.0)


class CommunicationBlock(nn.Module):
    """``blocks`` self-attention blocks along the sequence axis; the first maps dim_in -> dim_hidden."""

    def __init__(self, dim_in: int, dim_hidden: int, blocks: int, heads: int, ff: int, *, per_head_scale: bool,
                 dropout: float, ln_eps: float = 1e-5):
        super().__init__()
        scale = 1.0 / math.sqrt(dim_hidden // heads if per_head_scale else dim_hidden)
        layers = [SAB(dim_in if i == 0 else dim_hidden, dim_hidden, heads, ff, scale=scale, dropout=dropout,
                      ln_eps=ln_eps) for i in range(blocks)]
        self.enc = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, L, dim_in) -> (B, L, dim_hidden)."""
        return self.enc(x)


class AggregationBlock(nn.Module):
    """Self-attention blocks across the images of a pixel, then PMA pooling to one vector."""

    def __init__(self, dim_in: int, dim: int, blocks: int, heads: int, ff: int, pma_ff: int, *, dropout: float,
                 ln_eps: float = 1e-5):
        super().__init__()
        scale = 1.0 / math.sqrt(dim)
        self.enc = nn.Sequential(*[SAB(dim_in if i == 0 else dim, dim, heads, ff, scale=scale, dropout=dropout,
                                       ln_eps=ln_eps) for i in range(blocks)])
        self.dec = nn.Sequential(PMA(dim, heads, pma_ff, scale=scale, dropout=dropout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, N, dim_in) -> (B, dim)."""
        return self.dec(self.enc(x)).squeeze(1)


# ------------------------------------------------------------------------------------------------------ ConvNeXt
class LayerNorm2d(nn.Module):
    """LayerNorm over the channel axis of (B, C, H, W) tensors ("channels first")."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, C, H, W) -> (B, C, H, W)."""
        y = F.layer_norm(x.permute(0, 2, 3, 1), x.shape[1:2], self.weight, self.bias, self.eps)
        return y.permute(0, 3, 1, 2)


class ConvNeXtBlock(nn.Module):
    """dwconv7 -> LayerNorm -> Linear(4x) -> GELU -> Linear -> gamma * (.) + residual."""

    def __init__(self, dim: int, eps: float = 1e-6, layer_scale_init: float = 1e-6):
        super().__init__()
        self.dwconv = nn.Conv2d(dim, dim, 7, padding=3, groups=dim)
        self.norm = nn.LayerNorm(dim, eps=eps)
        self.pwconv1 = nn.Linear(dim, 4 * dim)
        self.pwconv2 = nn.Linear(4 * dim, dim)
        self.gamma = nn.Parameter(torch.full((dim,), float(layer_scale_init)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, C, H, W) -> (B, C, H, W)."""
        y = self.dwconv(x).permute(0, 2, 3, 1)
        y = self.pwconv2(F.gelu(self.pwconv1(self.norm(y))))
        return x + (self.gamma * y).permute(0, 3, 1, 2)


class ConvNeXt(nn.Module):
    """ConvNeXt with a LayerNorm (``norm0..``) on every stage output; returns the list of stage features."""

    def __init__(self, in_channels: int, depths: tuple[int, ...], dims: tuple[int, ...], eps: float = 1e-6,
                 layer_scale_init: float = 1e-6):
        super().__init__()
        self.downsample_layers = nn.ModuleList()
        self.downsample_layers.append(nn.Sequential(nn.Conv2d(in_channels, dims[0], 4, stride=4),
                                                    LayerNorm2d(dims[0], eps)))
        for i in range(1, len(dims)):
            self.downsample_layers.append(nn.Sequential(LayerNorm2d(dims[i - 1], eps),
                                                        nn.Conv2d(dims[i - 1], dims[i], 2, stride=2)))
        self.stages = nn.ModuleList(
            nn.Sequential(*[ConvNeXtBlock(d, eps, layer_scale_init) for _ in range(n)]) for n, d in zip(depths, dims)
        )
        for i, d in enumerate(dims):
            self.add_module(f"norm{i}", LayerNorm2d(d, eps))
        self.num_stages = len(dims)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x: (B, in_channels, G, G) -> [(B, dims[i], G/2^(i+2), G/2^(i+2)) for each stage i]."""
        # channels_last memory: the per-pixel LayerNorm/Linear permutes become free views and the depthwise convs
        # take oneDNN's fast NHWC path (same values; about 2x faster on CPU).
        x = x.contiguous(memory_format=torch.channels_last)
        outs = []
        for i in range(self.num_stages):
            x = self.stages[i](self.downsample_layers[i](x))
            outs.append(getattr(self, f"norm{i}")(x))
        return outs


class Backbone(nn.Module):
    """Holder so that parameter names read ``backbone.backbone.0.*`` as published."""

    def __init__(self, cfg: SDMUniPSConfig):
        super().__init__()
        self.backbone = nn.ModuleList([ConvNeXt(cfg.in_channels, cfg.backbone_depths, cfg.backbone_dims,
                                                cfg.backbone_ln_eps, cfg.backbone_layer_scale_init)])

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """x: (B, in_channels, G, G) -> list of stage features."""
        return self.backbone[0](x)


# ------------------------------------------------------------------------------------------------------- UPerNet
def _conv_relu(cin: int, cout: int, k: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, padding=k // 2), nn.ReLU(inplace=True))


class UPerHead(nn.Module):
    """UPerNet head (PPM on the last stage + FPN), every conv with bias and ReLU, no normalisation."""

    def __init__(self, in_channels: tuple[int, ...], channels: int, pool_scales: tuple[int, ...]):
        super().__init__()
        self.psp_modules = nn.ModuleList(
            nn.Sequential(nn.AdaptiveAvgPool2d(s), nn.Conv2d(in_channels[-1], channels, 1), nn.ReLU(inplace=True))
            for s in pool_scales
        )
        self.bottleneck = _conv_relu(in_channels[-1] + len(pool_scales) * channels, channels, 3)
        self.lateral_convs = nn.ModuleList(_conv_relu(c, channels, 1) for c in in_channels[:-1])
        self.fpn_convs = nn.ModuleList(_conv_relu(channels, channels, 3) for _ in in_channels[:-1])
        self.fpn_bottleneck = _conv_relu(len(in_channels) * channels, channels, 3)

    @staticmethod
    def _resize(x: torch.Tensor, size) -> torch.Tensor:
        if tuple(x.shape[-2:]) == tuple(size):
            return x
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        """feats: per-stage (B, in_channels[i], h_i, w_i) -> (B, channels, h_0, w_0)."""
        if not _REFERENCE:
            # channels-last convolutions: oneDNN's fast path, no layout conversions between the convs.
            feats = [f.contiguous(memory_format=torch.channels_last) for f in feats]
        top = feats[-1]
        psp = [top] + [self._resize(m(top), top.shape[-2:]) for m in self.psp_modules]
        laterals = [conv(feats[i]) for i, conv in enumerate(self.lateral_convs)]
        laterals.append(self.bottleneck(torch.cat(psp, dim=1)))
        for i in range(len(laterals) - 1, 0, -1):
            laterals[i - 1] = laterals[i - 1] + self._resize(laterals[i], laterals[i - 1].shape[-2:])
        outs = [conv(laterals[i]) for i, conv in enumerate(self.fpn_convs)]
        outs.append(laterals[-1])
        size = outs[0].shape[-2:]
        outs = [outs[0]] + [self._resize(o, size) for o in outs[1:]]
        return self.fpn_bottleneck(torch.cat(outs, dim=1))


class Fusion(nn.Module):
    """Light-axis attention on the backbone features (stages 2..), then the UPerNet head."""

    def __init__(self, cfg: SDMUniPSConfig):
        super().__init__()
        self.fusion = UPerHead(cfg.backbone_dims, cfg.fusion_channels, cfg.pool_scales)
        self.comm = nn.ModuleList(
            CommunicationBlock(d, d, n, cfg.heads, d, per_head_scale=False, dropout=cfg.dropout,
                               ln_eps=cfg.attention_ln_eps)
            for d, n in zip(cfg.backbone_dims[1:], cfg.light_attention_blocks[1:])
        )

    def forward(self, feats: list[torch.Tensor], num_images: int) -> torch.Tensor:
        """feats: per-stage (G*N, C_i, h_i, w_i), G groups of ``num_images`` consecutive images (attention runs
        across the images of one group, per pixel) -> (G*N, channels, h_0, w_0)."""
        out = [feats[0]]
        for f, comm in zip(feats[1:], self.comm):
            bn, c, h, w = f.shape
            g = bn // num_images
            x = f.reshape(g, num_images, c, h * w).permute(0, 3, 1, 2).reshape(g * h * w, num_images, c)
            x = comm(x)
            out.append(x.reshape(g, h * w, num_images, c).permute(0, 2, 3, 1).reshape(bn, c, h, w))
        return self.fusion(out)


class ImageEncoder(nn.Module):
    """Scale-invariant spatial-light image encoder (resized pass + polyphase split-and-merge)."""

    def __init__(self, cfg: SDMUniPSConfig):
        super().__init__()
        self.canonical_resolution = cfg.canonical_resolution
        self.backbone = Backbone(cfg)
        self.fusion = Fusion(cfg)

    def encode_canonical(self, x: torch.Tensor, num_images: int) -> torch.Tensor:
        """x: (G*N, in_channels, Gc, Gc) -> features (G*N, C, Gc/4, Gc/4)."""
        return self.fusion(self.backbone(x), num_images)

    def forward(self, x: torch.Tensor, num_images: int) -> torch.Tensor:
        """x: (B*N, in_channels, H, W) with H = W = s*Gc -> features (B*N, C, H/4, W/4)."""
        g = self.canonical_resolution
        bn, _, h, w = x.shape
        s = h // g
        resized = F.interpolate(x, size=(g, g), mode="bilinear", align_corners=True) if s != 1 else x
        f_resized = self.encode_canonical(resized, num_images)
        if s == 1:
            # The polyphase split of a canonical-size input is the input itself: both passes see the same data.
            return f_resized + f_resized
        out = None
        for a in range(s):
            for b in range(s):
                f = self.encode_canonical(x[:, :, a::s, b::s], num_images)
                if out is None:
                    out = f.new_zeros(bn, f.shape[1], f.shape[2] * s, f.shape[3] * s)
                out[:, :, a::s, b::s] = f
        return out + F.interpolate(f_resized, size=out.shape[-2:], mode="bilinear", align_corners=True)


# ------------------------------------------------------------------------------------------------------ decoder
class GLCUpsample(nn.Module):
    """Attention across the N images of a pixel on [raw RGB, encoder feature]."""

    def __init__(self, cfg: SDMUniPSConfig):
        super().__init__()
        self.comm = CommunicationBlock(3 + cfg.fusion_channels, cfg.glc_upsample_dim, cfg.glc_upsample_blocks,
                                       cfg.heads, cfg.glc_upsample_ff, per_head_scale=False, dropout=cfg.dropout,
                                       ln_eps=cfg.attention_ln_eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (P, N, 3 + C) -> (P, N, glc_upsample_dim)."""
        return self.comm(x)


class GLCAggregation(nn.Module):
    """Attention across the N images of a pixel + PMA pooling to one vector per pixel."""

    def __init__(self, cfg: SDMUniPSConfig):
        super().__init__()
        self.aggregation = AggregationBlock(3 + cfg.glc_upsample_dim, cfg.glc_aggregation_dim,
                                            cfg.glc_aggregation_blocks, cfg.heads, cfg.glc_aggregation_ff,
                                            cfg.pma_ff, dropout=cfg.dropout, ln_eps=cfg.attention_ln_eps)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (P, N, 3 + glc_upsample_dim) -> (P, glc_aggregation_dim)."""
        return self.aggregation(x)


class PredictionHead(nn.Module):
    """Linear -> ReLU -> Linear."""

    def __init__(self, dim: int, hidden: int, out: int):
        super().__init__()
        self.regression = nn.Sequential(nn.Linear(dim, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (..., dim) -> (..., out)."""
        return self.regression(x)


class Regressor(nn.Module):
    """Attention across the pixels of one sample set (no position encoding), then the prediction heads."""

    def __init__(self, cfg: SDMUniPSConfig):
        super().__init__()
        d = cfg.glc_aggregation_dim
        self.target = cfg.target
        self.comm = CommunicationBlock(d, d, cfg.regressor_blocks, cfg.heads, cfg.regressor_ff, per_head_scale=True,
                                       dropout=cfg.dropout, ln_eps=cfg.attention_ln_eps)
        self.prediction_normal = PredictionHead(d, cfg.head_width, 3)
        if cfg.target == "brdf":
            self.prediction_base = PredictionHead(d, cfg.head_width, 3)
            self.prediction_rough = PredictionHead(d, cfg.head_width, 1)
            self.prediction_metal = PredictionHead(d, cfg.head_width, 1)

    def forward(self, x: torch.Tensor, clamp: bool = True) -> dict[str, torch.Tensor]:
        """x: (B, m, dim) (each row one sample set) -> dict of (B, m, k) float32 maps (normal unit length).

        ``clamp=False`` returns the BRDF heads' linear outputs instead of their ReLU (the published network's
        output): a training loss on them keeps a gradient where the ReLU is zero."""
        x = self.comm(x)
        out = {"normal": F.normalize(self.prediction_normal(x).float(), p=2, dim=-1)}
        if self.target == "brdf":
            act = torch.relu if clamp else (lambda t: t)
            out["base_color"] = act(self.prediction_base(x).float())
            out["roughness"] = act(self.prediction_rough(x).float())
            out["metallic"] = act(self.prediction_metal(x).float())
        return out


def _no_autocast(device: torch.device):
    """Disable autocast for a region (no-op on devices autocast does not know, e.g. meta)."""
    if device.type in ("cpu", "cuda", "xpu", "mps"):
        return torch.autocast(device_type=device.type, enabled=False)
    return contextlib.nullcontext()


# ---------------------------------------------------------------------------------------------------- smoothing
def gaussian_kernel_1d(size: int, sigma: float, dtype=torch.float64) -> torch.Tensor:
    """Normalised 1-D Gaussian of ``size`` taps centred at (size-1)/2. The published 2-D kernel (normalised product
    of two such Gaussians) equals the outer product of this kernel with itself."""
    t = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    return (k / k.sum()).to(dtype)


def gaussian_smooth(x: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """Depthwise Gaussian smoothing with zero padding of size//2. x: (B, C, h, w) -> (B, C, h, w).

    Separable (mathematically identical to the published 2-D kernel). Each 1-D pass is a product with a banded
    (Toeplitz) matrix that holds the zero padding: two batched GEMMs, ~100x faster on CPU than a one-channel
    convolution over B*C maps. In channels-last memory the result is channels-last too.
    """
    if size <= 1:
        return x
    if _REFERENCE:
        return _gaussian_smooth_conv(x, size, sigma)
    b, c, h, w = x.shape
    k = gaussian_kernel_1d(size, sigma)

    def band(n: int) -> torch.Tensor:
        # T[i, j] = k[j - i + size//2]: row i of T @ v is the zero-padded 1-D convolution of v at i.
        i = torch.arange(n)
        off = i[None, :] - i[:, None] + size // 2
        t = torch.where((off >= 0) & (off < size), k[off.clamp(0, size - 1)], torch.zeros((), dtype=k.dtype))
        return t.to(device=x.device, dtype=x.dtype)

    th, tw = band(h), band(w)
    if x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous():
        y = x.permute(0, 2, 3, 1)                                                   # (B, h, w, C) contiguous
        y = torch.matmul(th, y.reshape(b, h, w * c)).reshape(b * h, w, c)           # along rows
        y = torch.matmul(tw, y).reshape(b, h, w, c)                                 # along columns
        return y.permute(0, 3, 1, 2)
    y = x.reshape(b * c * h, w) @ tw.t()                                            # along columns
    return torch.matmul(th, y.reshape(b * c, h, w)).reshape(b, c, h, w)            # along rows


def _gaussian_smooth_conv(x: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """Reference form of :func:`gaussian_smooth`: two one-channel 1-D convolutions over the B*C maps."""
    k = gaussian_kernel_1d(size, sigma).to(device=x.device, dtype=x.dtype)
    b, c, h, w = x.shape
    y = x.reshape(b * c, 1, h, w)
    y = F.conv2d(y, k.view(1, 1, size, 1), padding=(size // 2, 0))
    y = F.conv2d(y, k.view(1, 1, 1, size), padding=(0, size // 2))
    return y.reshape(b, c, h, w)


# -------------------------------------------------------------------------------------------------------- model
class SDMUniPS(nn.Module):
    """The SDM-UniPS network. See the module docstring for the data flow.

    Inputs everywhere: ``images (B, N, 3, H, W)`` float, linear, already normalised; ``mask (B, 1, H, W)`` in {0, 1};
    H = W, a multiple of ``config.canonical_resolution``.
    """

    def __init__(self, config: SDMUniPSConfig):
        super().__init__()
        config.validate()
        self.config = config
        self.image_encoder = ImageEncoder(config)
        self.glc_upsample = GLCUpsample(config)
        self.glc_aggregation = GLCAggregation(config)
        self.regressor = Regressor(config)
        #: Decoder parts that run in float32 at inference under autocast (bf16): the config's
        #: ``resolved_bf16_fp32_stages()`` (measurements in its docstring).
        #: Names: "glc_upsample", "glc_aggregation.pma", "regressor".
        self.fp32_under_autocast: tuple[str, ...] = config.resolved_bf16_fp32_stages()
        self.glc_aggregation.aggregation.dec[0].fp32_under_autocast = "glc_aggregation.pma" in self.fp32_under_autocast
        self._init_weights()

    # -------------------------------------------------------------------- init
    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    @property
    def output_keys(self) -> tuple[str, ...]:
        return OUTPUT_KEYS[self.config.target]

    # ------------------------------------------------------------------- checks
    def _check_inputs(self, images: torch.Tensor, mask: torch.Tensor) -> None:
        g = self.config.canonical_resolution
        if images.dim() != 5 or images.shape[2] != 3:
            raise ValueError(f"images must have shape (B, N, 3, H, W), got {tuple(images.shape)}")
        b, n, _, h, w = images.shape
        if h != w or h % g or h == 0:
            raise ValueError(
                f"images must be square with a side that is a multiple of {g}, got {tuple(images.shape)}")
        if n < 1 or b < 1:
            raise ValueError(f"images need at least one object and one image, got {tuple(images.shape)}")
        if mask.dim() != 4 or tuple(mask.shape) != (b, 1, h, w):
            raise ValueError(f"mask must have shape {(b, 1, h, w)} to match images, got {tuple(mask.shape)}")
        if not images.is_floating_point():
            raise ValueError(f"images must be a floating point tensor, got {images.dtype}")

    def _decoder_resolution(self, h: int, decoder_resolution: int | None) -> int:
        d = h if decoder_resolution is None else int(decoder_resolution)
        if d < 1:
            raise ValueError(f"decoder_resolution must be positive, got {d}")
        return d

    def smoothing_kernel_size(self, decoder_resolution: int) -> int:
        """Gaussian kernel size used for a decoder resolution: factor * (decoder_res // G) + 1."""
        return self.config.gaussian_kernel_factor * (decoder_resolution // self.config.canonical_resolution) + 1

    # ------------------------------------------------------------------ encode
    def encode(self, images: torch.Tensor, mask: torch.Tensor, decoder_resolution: int | None = None
               ) -> torch.Tensor:
        """Encode the images of B objects.

        images: (B, N, 3, H, W); mask: (B, 1, H, W); decoder_resolution: side of the decoder grid (default H; it
        only sets the Gaussian kernel size).
        Returns smoothed features ``(B, N, C, H/4, W/4)`` with C = ``config.fusion_channels`` (the decoder samples
        them with normalised coordinates, so they serve any decoder resolution).
        """
        self._check_inputs(images, mask)
        b, n, _, h, w = images.shape
        dres = self._decoder_resolution(h, decoder_resolution)
        m = mask.to(images.dtype).unsqueeze(1).expand(b, n, 1, h, w)
        x = torch.cat([images * m, m], dim=2).reshape(b * n, 4, h, w)
        f = self.image_encoder(x, n)
        f = gaussian_smooth(f, self.smoothing_kernel_size(dres), self.config.gaussian_sigma)
        return f.reshape(b, n, f.shape[1], f.shape[2], f.shape[3])

    # ------------------------------------------------------------------ decode
    def decode(self, images: torch.Tensor, mask: torch.Tensor, features: torch.Tensor, pixel_index: torch.Tensor,
               decoder_resolution: int | None = None, clamp: bool = True) -> dict[str, torch.Tensor]:
        """Predict the maps at ``m`` pixels per object; the m pixels of a row form one sample set.

        images: (B, N, 3, H, W) (raw, un-masked; resized to the decoder resolution D if D != H);
        mask: (B, 1, H, W) (shape-checked only: ``pixel_index`` selects the pixels);
        features: (B, N, C, h, w) from :meth:`encode`;
        pixel_index: (B, m) long, flat indices ``row * D + col`` into the D x D decoder grid (D = H by default).
        Returns ``{"normal": (B, m, 3) unit}`` plus, for target "brdf", ``"base_color" (B, m, 3)``,
        ``"roughness" (B, m, 1)``, ``"metallic" (B, m, 1)`` (all float32; ``clamp=False``: the BRDF maps before
        the output ReLU, for training).
        """
        self._check_inputs(images, mask)
        b, n, _, h, w = images.shape
        cfg = self.config
        if features.dim() != 5 or tuple(features.shape[:3]) != (b, n, cfg.fusion_channels):
            raise ValueError(
                f"features must have shape ({b}, {n}, {cfg.fusion_channels}, h, w), got {tuple(features.shape)}")
        if pixel_index.dim() != 2 or pixel_index.shape[0] != b or pixel_index.shape[1] < 1:
            raise ValueError(f"pixel_index must have shape ({b}, m) with m >= 1, got {tuple(pixel_index.shape)}")
        if pixel_index.dtype not in (torch.int64, torch.int32):
            raise ValueError(f"pixel_index must be an integer tensor, got {pixel_index.dtype}")
        d = self._decoder_resolution(h, decoder_resolution)
        if d != h:
            raw = F.interpolate(images.reshape(b * n, 3, h, w), size=(d, d), mode="bilinear", align_corners=False)
            raw = raw.reshape(b, n, 3, d * d)
        else:
            raw = images.reshape(b, n, 3, d * d)
        idx = pixel_index.long()
        if idx.device.type != "meta" and (bool((idx < 0).any()) or bool((idx >= d * d).any())):
            raise ValueError(f"pixel_index values must lie in [0, {d * d}) for a {d}x{d} decoder grid")
        m = idx.shape[1]
        # Sampling positions and features in float32 even under autocast: bf16 coordinates would be off by pixels.
        feats = features.reshape(b * n, features.shape[2], features.shape[3], features.shape[4]).float()
        chunk = max(1, cfg.decoder_chunk)
        pooled = []
        for start in range(0, m, chunk):
            sel = idx[:, start:start + chunk]                                        # (B, mc)
            mc = sel.shape[1]
            o = torch.gather(raw, 3, sel[:, None, None, :].expand(b, n, 3, mc))      # (B, N, 3, mc)
            o = o.permute(0, 3, 1, 2).reshape(b * mc, n, 3)
            rows = torch.div(sel, d, rounding_mode="floor")
            cols = sel - rows * d
            grid = torch.stack([2.0 * cols / d - 1.0, 2.0 * rows / d - 1.0], dim=-1)  # (B, mc, 2): x=col, y=row
            grid = grid.float()[:, None, None].expand(b, n, 1, mc, 2).reshape(b * n, 1, mc, 2)
            with _no_autocast(feats.device):
                f = F.grid_sample(feats, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
            f = f.reshape(b, n, -1, mc).permute(0, 3, 1, 2).reshape(b * mc, n, -1)     # (B*mc, N, C)
            x = self._stage("glc_upsample", torch.cat([o, f.to(o.dtype)], dim=-1))   # (B*mc, N, Du)
            x = self._stage("glc_aggregation", torch.cat([o.to(x.dtype), x], dim=-1))  # (B*mc, Da)
            pooled.append(x.reshape(b, mc, -1))
        x = torch.cat(pooled, dim=1) if len(pooled) > 1 else pooled[0]
        return self._stage("regressor", x, clamp=clamp)

    def _stage(self, name: str, x: torch.Tensor, **kwargs) -> torch.Tensor:
        """Run decoder stage ``name`` on x; at inference under autocast the stages in :attr:`fp32_under_autocast`
        run in float32 (training keeps autocast everywhere)."""
        module = getattr(self, name)
        dev = x.device.type
        if (not self.training and name in self.fp32_under_autocast and dev in ("cpu", "cuda")
                and torch.is_autocast_enabled(dev)):
            with torch.autocast(device_type=dev, enabled=False):
                return module(x.float(), **kwargs)
        return module(x, **kwargs)

    def forward(self, images: torch.Tensor, mask: torch.Tensor, pixel_index: torch.Tensor, clamp: bool = True
                ) -> dict[str, torch.Tensor]:
        """``decode(images, mask, encode(images, mask), pixel_index, clamp=clamp)``; shapes as in :meth:`decode`."""
        return self.decode(images, mask, self.encode(images, mask), pixel_index, clamp=clamp)


def build_model(config: SDMUniPSConfig, state_dict: dict[str, torch.Tensor] | None = None) -> SDMUniPS:
    """A model for ``config``; with ``state_dict`` it is built on the meta device (no wasted random init) and the
    given tensors are loaded strictly (``assign=True``: the model then uses those tensors)."""
    if state_dict is None:
        return SDMUniPS(config)
    with torch.device("meta"):
        model = SDMUniPS(config)
    model.load_state_dict(state_dict, strict=True, assign=True)
    return model
