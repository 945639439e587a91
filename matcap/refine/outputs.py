"""Files the refinement adds to a result folder: ``lights.json``, ``fit.json``, ``residual.png``,
``light_variation.png`` (see docs/refine.md)."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from matcap import imageio

FRAME = "camera: x right, y up, z toward the camera (as normal.exr); orthographic view along -z"
REFINE_FILES = ("lights.json", "fit.json", "residual.png", "light_variation.png")
RESIDUAL_MAX = 0.5  # residual.png: 0 .. 0.5 x the photos' mean mapped blue -> red
VARIATION_MAX = 0.5  # light_variation.png: 0 .. 0.5 mapped blue -> red


def lights_document(entries: Sequence[dict[str, Any]], files: Sequence[str], colour: str, psnr=None) -> dict:
    """The lights.json document (schema version 1) for fitted light ``entries`` of the photos ``files``."""
    images = []
    for i, (e, name) in enumerate(zip(entries, files, strict=True)):
        item = {"index": i, "file": name, **e}
        if psnr is not None:
            item["psnr"] = psnr[i]
        images.append(item)
    return {"version": 1, "frame": FRAME, "colour": f"linear RGB in the units of the decoded photos ({colour})",
            "images": images}


def colour_map(value: np.ndarray, vmax: float) -> np.ndarray:
    """(H, W) values (NaN = background) -> (H, W, 3) in [0, 1], 0 .. ``vmax`` blue -> red, background black."""
    from matcap.evaluation.metrics import colorize_error

    return colorize_error(value, max_deg=vmax, background=0.0)


def write_refine_outputs(folder: str | os.PathLike, result, files: Sequence[str], colour: str,
                         extra_report: dict[str, Any] | None = None, source: str = "estimated") -> list[str]:
    """Write the four refinement files into ``folder`` (each write atomic). Returns their names. ``source``:
    where the lights came from ("file", "ball" or "estimated"), recorded in lights.json, and with it what their
    intensities are: in the photos' units where the fit held the given lights' power, else relative."""
    from matcap.refine.lightfile import write_lights

    folder = Path(folder)
    doc = lights_document(result.lights, files, colour, result.report.get("psnr_db"))
    given = result.report.get("lights")
    units = "photos" if isinstance(given, dict) and given.get("power_held") else "relative"
    write_lights(folder / "lights.json", doc["images"], photos_colour=colour, source=source, intensity_units=units)
    report = dict(result.report)
    report["files"] = list(files)
    report.update(extra_report or {})
    imageio.write_text_atomic(folder / "fit.json", json.dumps(report, indent=2, default=_default) + "\n")
    imageio.write_png(folder / "residual.png", colour_map(result.residual, RESIDUAL_MAX), bits=8)
    imageio.write_png(folder / "light_variation.png", colour_map(result.variation, VARIATION_MAX), bits=8)
    return list(REFINE_FILES)


def _default(obj):
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
