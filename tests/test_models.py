"""`matcap models`: install trained weights as float16 with a model card, list them, load them for capture."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from matcap.models import install, installed_models


def test_install_fp16_lists_and_loads(tmp_path):
    from networks.checkpoint import load_model, save_weights
    from networks.config import get_config
    from networks.model import SDMUniPS

    torch.manual_seed(0)
    cfg = get_config("tiny", "normal")
    model = SDMUniPS(cfg).eval()
    src = save_weights(tmp_path / "best.safetensors", model, cfg,
                       {"steps": 12, "validation": {"mae": 21.5}, "train_config": {"lr": 4e-4}})
    folder = tmp_path / "weights"
    folder.mkdir()
    dst = install(src, "normal_tiny", fp16=True, notes="## Notes\ntrained in a test", folder=folder)
    assert dst.stat().st_size < 0.6 * src.stat().st_size  # float16 storage
    card = dst.with_suffix(".md").read_text()
    assert "| steps | 12 |" in card and "| mae | 21.500 |" in card and "trained in a test" in card
    [entry] = installed_models(folder)
    assert entry["target"] == "normal" and entry["card"]["stored_dtype"] == "float16"
    loaded, _, _ = load_model(dst)
    x = torch.rand(1, 3, 3, 64, 64)
    m = torch.ones(1, 1, 64, 64)
    idx = torch.arange(100).view(1, 100)
    with torch.no_grad():
        a = model(x, m, idx)["normal"]
        b = loaded(x, m, idx)["normal"]
    deg = torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))
    assert float(deg.max()) < 0.5  # fp16 storage does not hurt
    try:
        install(src, "normal_tiny", folder=folder)
    except Exception as exc:
        assert "exists" in str(exc)
    else:
        raise AssertionError("install overwrote without --overwrite")


def test_install_can_set_the_inference_sample_set_size(tmp_path):
    from networks.checkpoint import load_model, read_metadata, save_weights
    from networks.config import get_config
    from networks.model import SDMUniPS

    cfg = get_config("tiny", "normal")
    src = save_weights(tmp_path / "best.safetensors", SDMUniPS(cfg), cfg, {"steps": 1})
    dst = install(src, "n", folder=tmp_path, pixel_samples=300)
    config, card = read_metadata(dst)
    assert config.pixel_samples == 300 and card["inference_pixel_samples"] == 300
    assert card["trained_pixel_samples"] == cfg.pixel_samples
    loaded, _, _ = load_model(dst)
    assert loaded.config.pixel_samples == 300
    with pytest.raises(Exception, match="pixel-samples"):
        install(src, "m", folder=tmp_path, pixel_samples=0)


def test_models_cli_lists_the_bundled_models():
    r = subprocess.run([sys.executable, "-m", "matcap", "models"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = {line.split(":")[0]: line for line in r.stdout.splitlines() if not line.startswith(" ")}
    assert set(lines) == {"normal_small (default)", "brdf_small (default)"}, r.stdout
    assert "mean angular error" in lines["normal_small (default)"]
    brdf = lines["brdf_small (default)"]  # its normal head is untrained: no normal error shown for it
    assert "angular" not in brdf and "mae" not in brdf and "RMSE base color / roughness / metallic" in brdf


def test_validation_summary_per_target():
    from matcap.commands.models import validation_summary

    val = {"mae": 34.6, "mae_directional": 36.4, "rmse_base_color": 0.162, "rmse_roughness": 0.225,
           "rmse_metallic": 0.294, "rmse_const_base_color": 0.203, "rmse_const_roughness": 0.247,
           "rmse_const_metallic": 0.336}
    assert validation_summary("brdf", val) == ("RMSE base color / roughness / metallic 0.162 / 0.225 / 0.294 "
                                               "(best constant: 0.203 / 0.247 / 0.336)")
    assert validation_summary("normal", val) == "mean angular error 34.60° (directional 36.40°)"
    assert validation_summary("normal", {}) == "none" and validation_summary("brdf", {"mae": 3}) == "none"


def test_bundled_models_on_the_example_capture(tmp_path):
    """The README's run command, on 8 of the 50 bundled photos: the shipped weights are used with no flag, and the
    normal map looks like a convex object seen from the front (normals lean outward from the silhouette's middle)."""
    import json

    import numpy as np

    from matcap import imageio

    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "bunny-maps"
    r = subprocess.run([sys.executable, "-m", "matcap", "capture", str(repo / "examples" / "bunny"), "--linear", "--out",
                        str(out), "--max-images", "8", "--quiet"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    info = json.loads((out / "capture.json").read_text())
    for target in ("normal", "brdf"):
        assert Path(info["models"][target]["weights"]).name == f"{target}_small.safetensors"
    normal = imageio.read_exr(out / "normal.exr")
    mask = imageio.read_image(out / "mask.png").pixels[..., 0] > 0
    n = normal[mask]
    assert mask.mean() > 0.2 and np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-3)
    assert np.median(n[:, 2]) > 0.6  # mostly facing the camera
    rows, cols = np.nonzero(mask)
    # x grows to the right, y upward (row 0 is the top): both must follow the position in the silhouette
    assert np.corrcoef(n[:, 0], cols - cols.mean())[0, 1] > 0.4
    assert np.corrcoef(n[:, 1], rows.mean() - rows)[0, 1] > 0.4
    for name in ("basecolor.png", "roughness.png", "metallic.png"):
        assert (out / name).exists()
