"""Installed models (`networks/weights/`): listing, installing a trained run's weights with a model card, and
converting the published SDM-UniPS checkpoints (``matcap weights import``)."""
from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

from matcap.errors import MatcapError

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "networks" / "weights"


def installed_models(folder: str | os.PathLike = WEIGHTS_DIR) -> list[dict[str, Any]]:
    """One record per ``*.safetensors`` in ``folder``: name, path, target, preset, parameters, size, card."""
    from networks.checkpoint import read_metadata

    out = []
    for p in sorted(Path(folder).glob("*.safetensors")):
        try:
            config, card = read_metadata(p)
        except ValueError as exc:
            out.append({"name": p.stem, "path": str(p), "error": str(exc)})
            continue
        out.append({"name": p.stem, "path": str(p), "target": config.target, "preset": config.preset,
                    "size_mb": round(p.stat().st_size / 1e6, 2), "card": card,
                    "card_file": str(p.with_suffix(".md")) if p.with_suffix(".md").exists() else None})
    return out


def card_markdown(name: str, config, card: dict[str, Any], notes: str = "") -> str:
    """A model card (Markdown) from the card metadata stored with the weights."""
    val = card.get("validation") or {}
    tc = card.get("train_config") or {}
    lines = [
        f"# {name}", "",
        f"SDM-UniPS **{config.target}** network, preset `{config.preset}` "
        f"(canonical resolution {config.canonical_resolution}, native input side "
        f"{config.extra.get('native_resolution', 2 * config.canonical_resolution)}). Trained by matcap on matcap's own "
        "synthetic data; licence MIT (same as matcap).", "",
        "| field | value |", "|---|---|",
        f"| steps | {card.get('steps', '?')} |",
        f"| wall time | {card.get('wall_time_s', '?')} s |",
        f"| training data | `{card.get('data', '?')}` ({card.get('train_scenes', '?')} scenes) |",
        f"| validation data | `{card.get('val_data', '?')}` |",
        f"| processes | {card.get('world_size', 1)} |",
    ]
    for k in ("lr", "batch", "weight_decay", "warmup_steps", "decay_every", "decay_factor", "seed", "dropout",
              "canonical_resolution", "bf16", "brdf_weights", "brdf_loss_before_relu"):
        if k in ("dropout", "canonical_resolution"):  # the network's (the run's flag may say "inherit")
            lines.append(f"| {k} | {getattr(config, k)} |")
        elif k in tc and (config.target == "brdf" or not k.startswith("brdf_")):
            lines.append(f"| {k} | {tc[k]} |")
    if "sample" in tc:
        lines.append(f"| sampling | {json.dumps(tc['sample'])} |")
    lines += ["", "## Validation (synthetic test split)", ""]
    if val:
        lines += ["| metric | value |", "|---|---|"] + [f"| {k} | {v:.3f} |" for k, v in sorted(val.items())]
    else:
        lines.append("none recorded")
    if notes:
        lines += ["", notes.strip()]
    return "\n".join(lines) + "\n"


def install(weights: str | os.PathLike, name: str, *, fp16: bool = True, overwrite: bool = False,
            notes: str = "", folder: str | os.PathLike = WEIGHTS_DIR, pixel_samples: int | None = None) -> Path:
    """Copy a trained run's weights into ``folder`` as ``NAME.safetensors`` (fp16 if asked) + ``NAME.md``.

    ``pixel_samples`` sets the model's default inference sample-set size (pixels per attention set; the run's
    training value otherwise). It changes no weight: the regressor takes sets of any size."""
    import dataclasses

    import torch
    from safetensors.torch import load_file, save_file

    from matcap.imageio import atomic_path, write_text_atomic
    from networks.checkpoint import CARD_KEY, CONFIG_KEY, read_metadata

    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name or ""):
        raise MatcapError(f"--name {name!r}: use letters, digits, '.', '_' and '-' only (a file name in {folder}, "
                          "not a path)")
    src = Path(weights)
    config, card = read_metadata(src)
    if pixel_samples is not None:
        if pixel_samples < 1:
            raise MatcapError(f"--pixel-samples must be at least 1, got {pixel_samples}")
        card = dict(card, inference_pixel_samples=int(pixel_samples), trained_pixel_samples=config.pixel_samples)
        config = dataclasses.replace(config, pixel_samples=int(pixel_samples))
    dst = Path(folder) / f"{name}.safetensors"
    if dst.exists() and not overwrite:
        raise MatcapError(f"{dst} exists; pass --overwrite to replace it")
    state = load_file(str(src))
    if fp16:
        state = {k: v.to(torch.float16) if v.is_floating_point() else v for k, v in state.items()}
    card = dict(card, stored_dtype="float16" if fp16 else "float32", installed_from=str(src))
    meta = {"format": "pt", CONFIG_KEY: config.to_json(), CARD_KEY: json.dumps(card, sort_keys=True)}
    with atomic_path(dst) as tmp:
        save_file(state, tmp, metadata=meta)
    write_text_atomic(dst.with_suffix(".md"), card_markdown(name, config, card, notes))
    return dst


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def import_published(files: list[str | os.PathLike], out: str | os.PathLike, *,
                     overwrite: bool = False) -> list[dict[str, Any]]:
    """Convert the published SDM-UniPS checkpoints (``nml.pytmodel`` / ``brdf.pytmodel``; read with
    ``weights_only=True``, never unpickled) into ``out/normal.safetensors`` / ``out/brdf.safetensors`` with the
    config and a model card (source file, sha256, license) in the metadata. Every file is read and checked before
    any is written. Returns ``[{"source", "dest", "target", "parameters"}]``."""
    from networks.checkpoint import PUBLISHED_LICENSE, import_published as read_published, save_weights
    from networks.model import build_model

    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise MatcapError(f"--out {out_dir} exists and is not a folder")
    converted: dict[str, tuple] = {}
    for name in files:
        path = Path(name)
        config, state = read_published(path)
        target = config.target
        if target in converted:
            raise MatcapError(f"two {target} checkpoints given ({converted[target][0]} and {path})")
        dest = out_dir / f"{target}.safetensors"
        if dest.exists() and not overwrite:
            raise MatcapError(f"{dest} exists; pass --overwrite to replace it")
        converted[target] = (path, config, state, dest)
    done = []
    for target, (path, config, state, dest) in converted.items():
        card = {
            "name": f"sdm-unips-{target}-published",
            "architecture": "SDM-UniPS (Ikehata, CVPR 2023)",
            "preset": "paper",
            "target": target,
            "source_file": path.name,
            "source_sha256": _sha256(path),
            "license": PUBLISHED_LICENSE,
            "commercial_use": False,
            "redistribute": False,
        }
        save_weights(dest, build_model(config, state), config, card)
        done.append({"source": str(path), "dest": str(dest), "target": target,
                     "parameters": sum(v.numel() for v in state.values())})
    return done
