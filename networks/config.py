"""Configuration of the SDM-UniPS network (:class:`SDMUniPSConfig`) and its named presets.

Presets (``get_config(name, target)``):

``paper``
    Exactly the published network (Ikehata, CVPR 2023): ConvNeXt-T backbone, UPerNet fusion with 256 channels,
    glc_upsample 256/1024, glc_aggregation 384/1024 + PMA 512, regressor 384/1024. Its ``state_dict`` keys and
    shapes equal the published checkpoints' (without ``module.``). 62,753,711 parameters (normal target).

``small``
    A CPU-trainable network. FLOPs counted with ``torch.utils.flop_counter.FlopCounterMode`` (meta tensors;
    ``python benchmarks/bench_networks.py --flops``) for one object at 512x512, K=16 images, every pixel predicted
    in sample sets of 10,000: paper 57.8 TFLOP, small 5.0 TFLOP, i.e. **11.5x fewer FLOPs per pixel** (encoder
    10.2x, per-pixel decoder 13.7x, regressor attention over the sample set 6.7x). In a training-like setting
    (256x256, K=10, 2048 supervised pixels) the forward pass is ~11x cheaper as well (0.66 vs 0.058 TFLOP).
    Measured wall time (512x512, K=16, 166,740 mask pixels, fp32, 2 threads on a shared 2-core machine at load
    ~7, so pessimistic): small 130 s; paper at K=4 349 s (paper K=16 not measured here). Re-measure with
    ``benchmarks/bench_networks.py`` on an idle machine.
    Definition: backbone depths (2, 2, 6, 2), dims (48, 96, 192, 384); light-axis attention blocks (0, 1, 1, 2);
    fusion 64 channels; glc_upsample 2 blocks 96 wide / feed-forward 192; glc_aggregation 2 blocks 128 wide /
    feed-forward 256, PMA feed-forward 256; regressor 1 block 128 wide / feed-forward 256 (heads 128 -> 64 -> k).
    7.87 M parameters (normal target; 62.75 M for paper).

``tiny``
    For tests: a forward pass on 2 images at 64x64 runs in a few tens of milliseconds.

The config is stored in checkpoint metadata as JSON (:meth:`SDMUniPSConfig.to_dict` / :meth:`from_dict`).
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

TARGETS = ("normal", "brdf")
PRESETS = ("paper", "small", "tiny")
BF16_FP32_STAGES = ("glc_upsample", "glc_aggregation.pma", "regressor")


@dataclass
class SDMUniPSConfig:
    """All shape-defining settings of an SDM-UniPS network (plus a few run-time defaults)."""

    target: str = "normal"
    """Which outputs the network predicts: "normal" (normal head only) or "brdf" (normal + base colour, roughness,
    metallic heads)."""

    in_channels: int = 4
    """Channels of one encoder input image: masked RGB (3) + mask (1)."""

    backbone_depths: tuple[int, ...] = (3, 3, 9, 3)
    """ConvNeXt blocks per stage (4 stages; ConvNeXt-T in the paper)."""

    backbone_dims: tuple[int, ...] = (96, 192, 384, 768)
    """ConvNeXt channels per stage. Stage i runs at 1/2^(i+2) of the canonical resolution."""

    backbone_layer_scale_init: float = 1e-6
    """Initial value of the ConvNeXt layer-scale ``gamma`` (training from scratch only)."""

    light_attention_blocks: tuple[int, ...] = (0, 2, 3, 5)
    """Self-attention blocks across the images of one object, per pixel, after each backbone stage ("comm" blocks;
    hidden and feed-forward width = that stage's channels). The first stage has none (must be 0); the others >= 1."""

    fusion_channels: int = 256
    """UPerNet fusion width = channels of the encoder's output features."""

    pool_scales: tuple[int, ...] = (1, 2, 3, 6)
    """Pyramid pooling scales of the UPerNet PPM module."""

    canonical_resolution: int = 256
    """G: side of the images seen by the encoder. Inputs must be square with a side that is a multiple of G; an
    input of side H is encoded as the whole image resized to G plus (H/G)^2 polyphase sub-images."""

    gaussian_kernel_factor: int = 10
    """Feature smoothing kernel size = factor * (decoder_resolution / G) + 1 (sigma ``gaussian_sigma``)."""

    gaussian_sigma: float = 1.0
    """Sigma (in feature pixels) of the depthwise Gaussian feature smoothing."""

    glc_upsample_dim: int = 256
    """Width of the glc_upsample blocks (attention across the N images of a pixel on [raw RGB, feature])."""

    glc_upsample_blocks: int = 2
    """Number of self-attention blocks in glc_upsample (the first maps 3 + fusion_channels -> glc_upsample_dim)."""

    glc_upsample_ff: int = 1024
    """Feed-forward width of the glc_upsample blocks."""

    glc_aggregation_dim: int = 384
    """Width of the glc_aggregation blocks and of the per-pixel vector handed to the regressor."""

    glc_aggregation_blocks: int = 3
    """Self-attention blocks in glc_aggregation before the PMA pooling (first maps 3 + glc_upsample_dim -> dim)."""

    glc_aggregation_ff: int = 1024
    """Feed-forward width of the glc_aggregation self-attention blocks."""

    pma_ff: int = 512
    """Feed-forward width of the PMA (pooling by multi-head attention) block."""

    regressor_blocks: int = 2
    """Self-attention blocks of the regressor (attention across the pixels of one sample set)."""

    regressor_ff: int = 1024
    """Feed-forward width of the regressor blocks."""

    head_hidden: int = 0
    """Hidden width of the prediction heads (Linear-ReLU-Linear); 0 = glc_aggregation_dim // 2 (as published)."""

    heads: int = 8
    """Attention heads of every attention block."""

    pixel_samples: int = 10000
    """Default size m of a pixel sample set at inference (mask pixels are split into len//m + 1 sets when there
    are more than m). Training code chooses its own (the paper trains with 2048)."""

    dropout: float = 0.1
    """Dropout of the attention blocks (attention weights and feed-forward), active in training mode only."""

    attention_ln_eps: float = 1e-5
    """LayerNorm eps inside the attention blocks (PyTorch default, as published)."""

    backbone_ln_eps: float = 1e-6
    """LayerNorm eps in the ConvNeXt backbone."""

    decoder_chunk: int = 2048
    """Pixels per chunk in the per-pixel decoder stages (bounds memory; no effect on results)."""

    preset: str = ""
    """Name of the preset this config was made from (informational, except for ``bf16_fp32_stages`` = None)."""

    bf16_fp32_stages: tuple[str, ...] | None = None
    """Decoder parts that stay float32 at inference under bf16 autocast: any of "glc_upsample",
    "glc_aggregation.pma", "regressor". None: by preset (:meth:`resolved_bf16_fp32_stages`). Measured normals, bf16
    vs fp32, 512², K=16 ("bench" weights, first sample set; ``benchmarks/bench_speed.py --no-old --threads 1
    --sets 1``): ``paper`` with glc_upsample + PMA + regressor in fp32 0.28° mean (1.53x fewer CPU s than fp32;
    glc_upsample + PMA alone 0.34-0.48°, all bf16 0.66°); ``small`` with PMA + regressor 0.11° (1.23x; PMA alone
    0.23°). The regressor's attention is no faster in bf16 on CPU, so keeping it in fp32 is free."""

    extra: dict[str, Any] = field(default_factory=dict)
    """Free-form, JSON-serialisable notes (not used by the model)."""

    def __post_init__(self) -> None:
        for name in ("backbone_depths", "backbone_dims", "light_attention_blocks", "pool_scales"):
            setattr(self, name, tuple(int(v) for v in getattr(self, name)))
        if self.bf16_fp32_stages is not None:
            self.bf16_fp32_stages = tuple(str(v) for v in self.bf16_fp32_stages)
        self.validate()

    def resolved_bf16_fp32_stages(self) -> tuple[str, ...]:
        """``bf16_fp32_stages``, or when None: ("glc_upsample", "glc_aggregation.pma", "regressor") for the
        ``paper`` preset (its bf16 error needs glc_upsample) and ("glc_aggregation.pma", "regressor") otherwise."""
        if self.bf16_fp32_stages is not None:
            return self.bf16_fp32_stages
        if self.preset == "paper":
            return ("glc_upsample", "glc_aggregation.pma", "regressor")
        return ("glc_aggregation.pma", "regressor")

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise ValueError when the settings do not describe a buildable network."""
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {self.target!r}")
        n = len(self.backbone_dims)
        if n < 2 or len(self.backbone_depths) != n or len(self.light_attention_blocks) != n:
            raise ValueError(
                "backbone_depths, backbone_dims and light_attention_blocks need the same length >= 2, got "
                f"{self.backbone_depths}, {self.backbone_dims}, {self.light_attention_blocks}"
            )
        if self.light_attention_blocks[0] != 0 or min(self.light_attention_blocks[1:]) < 1:
            raise ValueError(
                f"light_attention_blocks must be 0 for the first stage and >= 1 after, got {self.light_attention_blocks}"
            )
        widths = {
            "light attention": self.backbone_dims[1:],
            "glc_upsample_dim": (self.glc_upsample_dim,),
            "glc_aggregation_dim": (self.glc_aggregation_dim,),
        }
        for what, dims in widths.items():
            for d in dims:
                if d % self.heads:
                    raise ValueError(f"{what} width {d} is not divisible by heads={self.heads}")
        if self.glc_upsample_blocks < 1 or self.glc_aggregation_blocks < 1 or self.regressor_blocks < 1:
            raise ValueError("glc_upsample_blocks, glc_aggregation_blocks and regressor_blocks must be >= 1")
        if self.canonical_resolution % 32:
            raise ValueError(f"canonical_resolution must be a multiple of 32, got {self.canonical_resolution}")
        if self.pixel_samples < 1 or self.decoder_chunk < 1:
            raise ValueError("pixel_samples and decoder_chunk must be >= 1")
        stages = set(self.bf16_fp32_stages or ()) - set(BF16_FP32_STAGES)
        if stages:
            raise ValueError(f"bf16_fp32_stages: unknown {sorted(stages)}; choose from {BF16_FP32_STAGES}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")

    @property
    def head_width(self) -> int:
        """Hidden width of the prediction heads."""
        return self.head_hidden or self.glc_aggregation_dim // 2

    @property
    def feature_channels(self) -> int:
        """Channels of the encoder's output features."""
        return self.fusion_channels

    # ------------------------------------------------------------ (de)serialise
    def to_dict(self) -> dict[str, Any]:
        """A JSON-serialisable dict (tuples become lists)."""
        d = dataclasses.asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SDMUniPSConfig":
        """Inverse of :meth:`to_dict`; refuses unknown keys with a ValueError."""
        if not isinstance(d, dict):
            raise ValueError(f"config must be a dict, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown SDMUniPSConfig fields: {unknown}")
        return cls(**d)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "SDMUniPSConfig":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"config is not valid JSON: {exc}") from None
        return cls.from_dict(d)


def get_config(name: str = "paper", target: str = "normal") -> SDMUniPSConfig:
    """A preset: ``"paper"`` (published shapes), ``"small"`` (CPU-trainable, ~10x fewer FLOPs), ``"tiny"`` (tests)."""
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
    if name == "paper":
        return SDMUniPSConfig(target=target, preset="paper")
    if name == "small":
        return SDMUniPSConfig(
            target=target,
            preset="small",
            backbone_depths=(2, 2, 6, 2),
            backbone_dims=(48, 96, 192, 384),
            light_attention_blocks=(0, 1, 1, 2),
            fusion_channels=64,
            glc_upsample_dim=96,
            glc_upsample_blocks=2,
            glc_upsample_ff=192,
            glc_aggregation_dim=128,
            glc_aggregation_blocks=2,
            glc_aggregation_ff=256,
            pma_ff=256,
            regressor_blocks=1,
            regressor_ff=256,
        )
    if name == "tiny":
        return SDMUniPSConfig(
            target=target,
            preset="tiny",
            backbone_depths=(1, 1, 1, 1),
            backbone_dims=(8, 16, 16, 32),
            light_attention_blocks=(0, 1, 1, 1),
            fusion_channels=16,
            pool_scales=(1, 2),
            canonical_resolution=32,
            glc_upsample_dim=16,
            glc_upsample_blocks=1,
            glc_upsample_ff=32,
            glc_aggregation_dim=32,
            glc_aggregation_blocks=1,
            glc_aggregation_ff=32,
            pma_ff=32,
            regressor_blocks=1,
            regressor_ff=32,
            pixel_samples=256,
            decoder_chunk=512,
        )
    raise ValueError(f"unknown preset {name!r}; choose one of {PRESETS}")
