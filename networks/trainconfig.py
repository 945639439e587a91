"""Training run settings and their command-line flags (no torch import: `matcap train --help` stays fast)."""
from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import math
import textwrap
from dataclasses import dataclass, field

from networks.data import SampleSpec


@dataclass
class TrainConfig:
    """Everything that defines a training run (stored in the checkpoint and the model card)."""

    data: str = ""
    """Training dataset folder (output of `matcap synth --split train`)."""
    target: str = "normal"
    """"normal" or "brdf"."""
    preset: str = "small"
    """Network preset: paper, small or tiny."""
    out: str = "runs/default"
    """Run folder (checkpoints, logs, best weights)."""
    steps: int = 20000
    """Total optimiser steps."""
    batch: int = 4
    """Samples per micro-batch per process."""
    accumulate: int = 1
    """Micro-batches per optimiser step: their gradients are averaged before the step, so the effective batch is
    batch x accumulate x processes at the memory of one micro-batch."""
    lr: float = 1e-4
    """Peak learning rate (AdamW)."""
    weight_decay: float = 0.05
    """AdamW weight decay."""
    warmup_steps: int = 200
    """Linear warm-up from 0 to lr."""
    decay_every: int = 5000
    """Multiply the learning rate by ``decay_factor`` every this many steps."""
    decay_factor: float = 0.8
    """Step-decay factor."""
    grad_clip: float = 1.0
    """Max global gradient norm (0 = off)."""
    brdf_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """BRDF net: loss weights of the base color, roughness and metallic MSEs (the paper sums them unweighted)."""
    brdf_loss_before_relu: bool = False
    """BRDF net: compute the loss on the heads' linear outputs instead of their ReLU, so a pixel whose output
    sits below zero still gets a gradient (the ReLU of an unclamped prediction is what inference returns). The
    BRDF terms in the training log are then those of the linear outputs; validation always scores the ReLU."""
    canonical_resolution: int = 0
    """Encoder canonical resolution (0 = that of the ``--init`` weights, else the preset's: 256, tiny 32).
    The bundled CPU-trained models use 128 (with --resolution 128)."""
    dropout: float = -1.0
    """Attention dropout (< 0 = that of the ``--init`` weights, else the preset's 0.1)."""
    sample: SampleSpec = field(default_factory=SampleSpec)
    """How samples are drawn (resolution, K range, pixel samples, augmentation)."""
    val_data: str = ""
    """Validation dataset that chooses ``best.safetensors`` (a `--split test` set kept apart from the reported
    test split); empty = no validation."""
    val_scenes: int = 24
    """Validate on at most this many scenes (the first ones, always the same)."""
    val_every_s: float = 900.0
    """Validate every this many seconds of training (and at the end)."""
    checkpoint_every_s: float = 180.0
    """Write checkpoint.pt every this many seconds (and at the end)."""
    log_every: int = 10
    """Write a log record every this many steps."""
    seed: int = 0
    """Seed of initial weights, data order and dropout."""
    device: str = "cpu"
    """torch device (cpu, cuda, cuda:N)."""
    bf16: bool = False
    """bfloat16 autocast for forward/backward."""
    threads: int = 0
    """torch intra-op threads (0 = torch default)."""
    workers: int = 0
    """Processes that draw the next batches ahead of the optimiser (0 = draw them in the training loop). The
    batches are the same either way (each is a pure function of its step); use them when a GPU waits for data."""
    rescan_every_s: float = 0.0
    """Re-list --data every this many seconds and draw from the scenes that appeared since, for a folder that a
    generator is still rendering into (0 = list it once). New scenes join at the end of the run's scene order
    (OUT/scenes.txt), and each growth is logged (event=data: the first step that draws from it, the scene count)."""
    save_all_ranks: bool = False
    """Every rank writes final_rank<r>.safetensors (used by the DDP test)."""


def _three_floats(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or any(not v >= 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected three non-negative numbers like 1,2,2, got {text!r}")
    return values


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (the string literal after ``name: type = default``), with
    whitespace collapsed: the one place a setting is described, shown by ``--help``."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):  # no source to read (a frozen install): flags without help text
        return {}
    body = tree.body[0].body
    docs = {}
    for stmt, nxt in zip(body, body[1:]):
        if (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name) and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)):
            docs[stmt.target.id] = " ".join(nxt.value.value.split()).replace("%", "%%")
    return docs


def add_arguments(p: argparse.ArgumentParser) -> None:
    """CLI flags for every TrainConfig field (shared by `matcap train` and `python -m networks.train`); their help is
    the field's docstring."""
    d, s = TrainConfig(), SampleSpec()
    docs = {**field_docs(TrainConfig), **field_docs(SampleSpec)}

    def flag(name: str, **kw) -> None:
        value = getattr(d, name) if hasattr(d, name) else getattr(s, name)
        shown = "" if kw.get("action") or kw.get("required") or value == "" else f" (default: {value})"
        p.add_argument(f"--{name.replace('_', '-')}", default=value, help=kw.pop("help", docs.get(name, "") + shown), **kw)

    flag("data", required=True)
    flag("target", choices=("normal", "brdf"))
    flag("preset", choices=("paper", "small", "tiny"))
    flag("out")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt (model, optimiser, "
                   "schedule and data order: bit-for-bit where it stopped)")
    p.add_argument("--overwrite", action="store_true",
                   help="start a fresh run in an --out folder that holds an earlier run (its checkpoint and weights "
                        "are replaced); without it such a folder is refused unless --resume")
    p.add_argument("--init", help="start from these weights (.safetensors) instead of random init")
    for name in ("canonical_resolution", "steps", "batch", "accumulate", "warmup_steps", "decay_every", "log_every", "seed",
                 "threads", "workers", "val_scenes", "resolution", "min_images", "max_images", "pixel_samples"):
        flag(name, type=int)
    for name in ("dropout", "lr", "weight_decay", "decay_factor", "grad_clip", "val_every_s", "checkpoint_every_s",
                 "rescan_every_s", "fresh_combination_prob", "drop_mask_prob", "min_crop"):
        flag(name, type=float)
    flag("brdf_weights", type=_three_floats, metavar="B,R,M",
         help=docs.get("brdf_weights", "") + " (default: 1,1,1)")
    flag("brdf_loss_before_relu", action="store_true")
    p.add_argument("--no-dihedral", dest="dihedral", action="store_false",
                   help="no random mirror / 90-degree rotation augmentation (default: on). " + docs.get("dihedral", ""))
    flag("val_data")
    flag("device")
    flag("bf16", action="store_true")
    p.add_argument("--save-all-ranks", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--quiet", action="store_true", help="no progress output")


def check_config(tc: TrainConfig) -> None:
    """Raise ``ValueError`` (one line that names the flag) for a setting the trainer would crash on, silently
    ignore or misread: counts below their minimum, probabilities outside [0, 1], negative or non-finite rates."""

    def flag(name: str) -> str:
        return "--" + name.replace("_", "-")

    s = tc.sample
    at_least = {"steps": (tc.steps, 1), "batch": (tc.batch, 1), "accumulate": (tc.accumulate, 1),
                "log_every": (tc.log_every, 1), "decay_every": (tc.decay_every, 1),
                "warmup_steps": (tc.warmup_steps, 0), "threads": (tc.threads, 0), "workers": (tc.workers, 0),
                "val_scenes": (tc.val_scenes, 1), "seed": (tc.seed, 0), "resolution": (s.resolution, 1),
                "min_images": (s.min_images, 1), "pixel_samples": (s.pixel_samples, 1)}
    for name, (value, low) in at_least.items():
        if value < low:
            raise ValueError(f"{flag(name)} must be at least {low}, got {value}")
    if s.max_images < s.min_images:
        raise ValueError(f"--max-images ({s.max_images}) must not be below --min-images ({s.min_images})")
    for name in ("fresh_combination_prob", "drop_mask_prob"):
        value = getattr(s, name)
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{flag(name)} must be a probability in [0, 1], got {value}")
    if not 0.0 < s.min_crop <= 1.0:
        raise ValueError(f"--min-crop must be a fraction in (0, 1], got {s.min_crop}")
    for name in ("lr", "weight_decay", "grad_clip", "decay_factor", "rescan_every_s"):
        value = getattr(tc, name)
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"{flag(name)} must be a finite number >= 0, got {value}")
    for name in ("val_every_s", "checkpoint_every_s"):
        value = getattr(tc, name)
        if not value > 0:
            raise ValueError(f"{flag(name)} must be positive, got {value}")


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    sample = SampleSpec(**{f.name: getattr(args, f.name) for f in dataclasses.fields(SampleSpec)})
    fields = {f.name for f in dataclasses.fields(TrainConfig)} - {"sample"}
    return TrainConfig(sample=sample, **{k: getattr(args, k) for k in fields})
