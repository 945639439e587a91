"""Weights: our safetensors format, import of the published checkpoints, deterministic reference weights.

Our format: one ``.safetensors`` file holding the model's ``state_dict`` (float32) with metadata
``{"format": "pt", "matcap.config": <SDMUniPSConfig JSON>, "matcap.card": <model card JSON>}``.

The published SDM-UniPS files (``nml.pytmodel`` / ``brdf.pytmodel``) are ``torch.save``-d state dicts of a
``DataParallel`` wrapper (every key starts with ``module.``). They are read with ``torch.load(...,
weights_only=True)`` only: arbitrary pickled objects are refused, never executed.
"""
from __future__ import annotations

import json
import math
import os
import warnings
import zlib
from pathlib import Path
from typing import Any, Iterable

import torch

from networks.config import SDMUniPSConfig, get_config
from networks.model import SDMUniPS, build_model
from scenes.atomic import atomic_path

CONFIG_KEY = "matcap.config"
CARD_KEY = "matcap.card"
PUBLISHED_PREFIX = "module."
PUBLISHED_LICENSE = (
    "SDM-UniPS published weights (Satoshi Ikehata, CVPR 2023): MIT licence with a non-commercial clause - "
    "research / non-commercial use only; do not redistribute."
)


# ------------------------------------------------------------------------------------------------ our format
def save_weights(path: str | os.PathLike, model: torch.nn.Module, config: SDMUniPSConfig,
                 card: dict[str, Any] | None = None) -> Path:
    """Write ``model.state_dict()`` (as float32) + config + card to ``path`` atomically. Returns the path."""
    from safetensors.torch import save_file

    path = Path(path)
    state = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in model.state_dict().items()}
    if not state:
        raise ValueError("model has no parameters to save")
    metadata = {"format": "pt", CONFIG_KEY: config.to_json(), CARD_KEY: json.dumps(card or {}, sort_keys=True)}
    with atomic_path(path) as tmp:
        save_file(state, tmp, metadata=metadata)
    return path


def read_metadata(path: str | os.PathLike) -> tuple[SDMUniPSConfig, dict[str, Any]]:
    """(config, card) stored in one of our safetensors files."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no weights file at {path}")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except Exception as exc:  # safetensors raises its own error types
        raise ValueError(f"{path} is not a safetensors file: {' '.join(str(exc).split())}") from None
    if CONFIG_KEY not in meta:
        raise ValueError(f"{path} has no '{CONFIG_KEY}' metadata; not a matcap weights file")
    config = SDMUniPSConfig.from_json(meta[CONFIG_KEY])
    try:
        card = json.loads(meta.get(CARD_KEY, "{}"))
    except json.JSONDecodeError:
        raise ValueError(f"{path} has an unreadable '{CARD_KEY}' metadata entry") from None
    return config, card


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu"
               ) -> tuple[SDMUniPS, SDMUniPSConfig, dict[str, Any]]:
    """Load one of our weight files (strict). Returns ``(model in eval mode on device, config, card)``."""
    from safetensors.torch import load_file

    config, card = read_metadata(path)
    state = load_file(str(path), device="cpu")
    # shipped weights may be stored as float16: the model always computes in float32 (or under autocast)
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    with torch.device("meta"):
        expected = SDMUniPS(config).state_dict()
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    if missing or unexpected:
        raise ValueError(f"{path} does not fit its config: {len(missing)} missing keys (e.g. {missing[:1]}), "
                         f"{len(unexpected)} unexpected (e.g. {unexpected[:1]})")
    for k, v in expected.items():
        if tuple(state[k].shape) != tuple(v.shape):
            raise ValueError(f"{path}: {k} has shape {tuple(state[k].shape)}, config expects {tuple(v.shape)}")
    model = build_model(config, state)
    return model.to(device).eval(), config, card


# ----------------------------------------------------------------------------------------- published files
def _paper_shapes(target: str) -> list[tuple[str, tuple[int, ...]]]:
    with torch.device("meta"):
        model = SDMUniPS(get_config("paper", target))
    return [(k, tuple(v.shape)) for k, v in model.state_dict().items()]


def detect_published_target(keys: Iterable[str]) -> str:
    """"brdf" when the (prefixed or not) keys contain the base-colour head, else "normal"."""
    ks = {k[len(PUBLISHED_PREFIX):] if k.startswith(PUBLISHED_PREFIX) else k for k in keys}
    return "brdf" if "regressor.prediction_base.regression.0.weight" in ks else "normal"


def convert_published_state_dict(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Map a published state dict (keys ``module.<ours>``) onto our ``paper`` keys; strict.

    Every key must carry the ``module.`` prefix; the stripped keys and shapes must equal the paper preset's (normal
    or brdf, detected from the keys). Returns a new dict (float32 tensors, our order); raises a one-line ValueError.
    """
    if not isinstance(state_dict, dict) or not state_dict:
        raise ValueError("not a state dict (expected a non-empty dict of tensors)")
    bad = [k for k in state_dict if not isinstance(k, str) or not k.startswith(PUBLISHED_PREFIX)]
    if bad:
        raise ValueError(f"not a published SDM-UniPS state dict: key {bad[0]!r} lacks the '{PUBLISHED_PREFIX}' prefix")
    stripped = {k[len(PUBLISHED_PREFIX):]: v for k, v in state_dict.items()}
    for k, v in stripped.items():
        if not isinstance(v, torch.Tensor):
            raise ValueError(f"not a state dict: entry {k!r} is a {type(v).__name__}, not a tensor")
    target = detect_published_target(stripped)
    expected = _paper_shapes(target)
    exp_keys = {k for k, _ in expected}
    missing = [k for k, _ in expected if k not in stripped]
    unexpected = [k for k in stripped if k not in exp_keys]
    if missing or unexpected:
        raise ValueError(f"does not match the published SDM-UniPS {target} network: {len(missing)} missing keys "
                         f"(e.g. {missing[:1]}), {len(unexpected)} unexpected (e.g. {unexpected[:1]})")
    out = {}
    for k, shape in expected:
        v = stripped[k]
        if tuple(v.shape) != shape:
            raise ValueError(f"{PUBLISHED_PREFIX}{k} has shape {tuple(v.shape)}, expected {shape}")
        if not v.is_floating_point():
            raise ValueError(f"{PUBLISHED_PREFIX}{k} has dtype {v.dtype}, expected floating point")
        out[k] = v.detach().to(torch.float32).contiguous()
    return out


def import_published(path: str | os.PathLike) -> tuple[SDMUniPSConfig, dict[str, torch.Tensor]]:
    """Read a published checkpoint with ``torch.load(weights_only=True)``; returns ``(paper config, our state
    dict)``. Anything that is not such a file is refused with a one-line ValueError."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder; give the published checkpoint files (e.g. nml.pytmodel brdf.pytmodel)")
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    if path.suffix == ".safetensors":
        raise ValueError(f"{path} is a safetensors file (matcap's own weights need no import: pass it to --weights); "
                         "this converts the published .pytmodel checkpoints")
    try:
        with warnings.catch_warnings():  # a plain pickle draws a protocol UserWarning before the refusal below
            warnings.filterwarnings("ignore", message=r"Detected pickle protocol", category=UserWarning)
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # UnpicklingError for disallowed objects, RuntimeError/EOFError for garbage
        first = " ".join(str(exc).split()).split(". ")[0][:160]  # the first sentence, not a cut-off paragraph
        raise ValueError(f"{path} is not a loadable weights-only PyTorch file ({type(exc).__name__}: {first})"
                         ) from None
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    try:
        ours = convert_published_state_dict(state)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    return get_config("paper", detect_published_target(ours)), ours


# --------------------------------------------------------------------------------------- reference weights
def reference_weights(config: SDMUniPSConfig, salt: str,
                      manifest: list[tuple[str, list[int]]] | None = None) -> dict[str, torch.Tensor]:
    """The SPEC's deterministic weights for ``config`` (float32), in our state-dict order.

    For each ``(key, shape)``: ``g = torch.Generator().manual_seed(zlib.crc32(f"{salt}:{key}"))``,
    ``r = torch.randn(shape, generator=g, dtype=float64)``; 1-D: ``0.1 r`` (+1 for keys ending in ``.weight``);
    otherwise ``r / sqrt(prod(shape[1:]))``; cast to float32. ``manifest`` (the reference ``[[key, shape], ...]``
    for this target, without ``module.``) is checked against our order when given.
    """
    with torch.device("meta"):
        model = SDMUniPS(config)
    ours = [(k, tuple(v.shape)) for k, v in model.state_dict().items()]
    if manifest is not None:
        ref = [(k, tuple(s)) for k, s in manifest]
        assert ours == ref, "our state_dict order/shapes differ from the manifest"
    out: dict[str, torch.Tensor] = {}
    for key, shape in ours:
        g = torch.Generator().manual_seed(zlib.crc32(f"{salt}:{key}".encode()))
        r = torch.randn(shape, generator=g, dtype=torch.float64)
        if len(shape) == 1:
            w = 0.1 * r + (1.0 if key.endswith(".weight") else 0.0)
        else:
            w = r / math.sqrt(math.prod(shape[1:]))
        out[key] = w.to(torch.float32)
    return out
