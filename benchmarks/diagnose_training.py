"""Diagnostics behind the statements in docs/training.md and the bundled BRDF model's card.

  python benchmarks/diagnose_training.py overfit --data DATA [--init W] [--steps 60] [--target normal|brdf]
      Fit ONE fixed batch (B=2, K=4, 128^2, 768 pixels, the small recipe, bf16) and print its loss and mean angular
      error (BRDF: RMSE of base color, roughness, metallic) every 5 steps: if this does not fall, the optimisation
      is broken; if it does while validation stalls, the model is short of data and steps.
  python benchmarks/diagnose_training.py albedo-bound --data DATA_TEST
      Base-color RMSE of the best constant vs. an oracle that knows the relative albedo (ground truth divided by
      the scene's brightest pixel) and scales it by one global factor: the most an albedo predictor can gain when
      the per-image normalisation hides the absolute scale.
  python benchmarks/diagnose_training.py constants --data DATA_TEST
      RMSE of base color, roughness and metallic for the best constant (each map's mean: an oracle) and for
      export's defaults (what a capture gets without a BRDF model), over every valid pixel, as validation pools them.
  python benchmarks/diagnose_training.py self-calibrated --data DATA_TEST [--init W]
      A rejected refinement: lights estimated from the network's normals, normals re-solved by robust least squares
      with them and averaged with the network's. Prints the mean angular error per lighting group of the network
      alone, the re-solved normals and the average (docs/training.md).
  python benchmarks/diagnose_training.py brdf-outputs --data DATA [--init W] [--scenes 12]
      What the BRDF network's roughness and metallic heads do on every mask pixel of the first scenes: the share of
      outputs below zero before the ReLU (no gradient there when the loss is on the ReLU), the mean of prediction
      and truth, their correlation, and for metallic the mean prediction on metals (truth > 0.5) and on the rest.
  python benchmarks/diagnose_training.py brdf-by-material --data DATA_TEST [--init W] [--assets ../shared/data]
      Roughness and metallic error of the BRDF network per material group (objects / backdrop x the generator's
      diffuse / specular / metallic category, found by re-rendering each scene's shapes from its spec.json with an
      object-index pass), and the roughness RMSE of a predictor that is exact except on diffuse materials (specular
      <= 0.3), where it predicts their mean: what is left of the constant if roughness cannot be seen there.
  python benchmarks/diagnose_training.py normal-by-material --data DATA_TEST [--init W] [--assets ../shared/data]
      Mean angular error of the normal network per lighting group and material group (as brdf-by-material).
  python benchmarks/diagnose_training.py head-refit --data DATA --val-data DATA_VAL [--init W] [--scenes 150]
      A rejected shortcut: refit each BRDF head's last linear layer by ridge least squares (lambda 0.1) on the
      regressor's features of random training scenes, and compare its validation RMSE with the trained head's.
  python benchmarks/diagnose_training.py average --out AVG.safetensors W1 W2 [...]
      The element-wise mean of weights of one network (config and card of W1), to score with networks.validate
      (docs/training.md: averaging checkpoints does not help).
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np


def overfit(data: str, init: str | None, steps: int, lr: float, target: str = "normal") -> None:
    import torch

    from networks.checkpoint import load_model
    from networks.config import get_config
    from networks.data import SampleSpec, SceneCache, draw_batch, list_scenes
    from networks.model import SDMUniPS
    from networks.train import compute_loss, gather_pixels, to_torch

    torch.set_num_threads(1)
    torch.manual_seed(0)
    cfg = dataclasses.replace(get_config("small", target), canonical_resolution=128, dropout=0.0, pixel_samples=768)
    model = SDMUniPS(cfg)
    if init:
        model.load_state_dict(load_model(init)[0].state_dict(), strict=target == "normal")
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr, weight_decay=0.05)
    spec = SampleSpec(resolution=128, min_images=4, max_images=4, pixel_samples=768)
    batch = to_torch(draw_batch(SceneCache(list_scenes(data)), spec, 2, 0, 12345), "cpu")
    truth = {key: gather_pixels(batch[key], batch["pixel_index"])
             for key in ("normal", "base_color", "roughness", "metallic")}
    for step in range(steps):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            pred = model(batch["images"], batch["input_mask"], batch["pixel_index"])
        loss, _ = compute_loss(pred, batch, target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        if step % 5 == 0 or step == steps - 1:
            if target == "normal":
                cos = (pred["normal"].detach().float() * truth["normal"]).sum(-1).clamp(-1, 1)
                score = f"MAE {float(torch.rad2deg(torch.acos(cos)).mean()):.2f} deg"
            else:
                score = "  ".join(
                    f"{key} RMSE {float((pred[key].detach().float().reshape(truth[key].shape) - truth[key]).pow(2).mean().sqrt()):.3f}"
                    f" (const {float(truth[key].std(unbiased=False)):.3f})"
                    for key in ("base_color", "roughness", "metallic"))
            print(f"step {step:3d}  loss {float(loss.detach()):.4f}  {score}", flush=True)


def _valid_pixels(scene) -> np.ndarray:
    """(H, W) bool: the pixels validation scores (inside the mask, with a unit ground-truth normal)."""
    return scene["mask"].astype(bool) & (np.linalg.norm(scene["normal"].astype(np.float64), axis=2) > 0.5)


def _network_input(scene):
    """(mask (H, W) bool tensor, images (N, 3, H, W) normalised as at inference) of a loaded scene."""
    import torch

    from networks.preprocess import normalize_images

    m = torch.from_numpy(scene["mask"].astype(bool))
    images = torch.from_numpy(scene["images"].astype(np.float32)).permute(0, 3, 1, 2)
    return m, normalize_images(images, m.float().unsqueeze(0))


def _truth(data: str) -> dict[str, list[np.ndarray]]:
    """Per scene, the ground-truth base color (P, 3), roughness (P,) and metallic (P,) at its valid pixels (mask
    and a unit normal), as training validation selects them."""
    from networks.data import list_scenes

    out: dict[str, list[np.ndarray]] = {"base_color": [], "roughness": [], "metallic": []}
    for path in list_scenes(data):
        with np.load(Path(path) / "data.npz") as z:
            valid = _valid_pixels(z)
            for key, values in out.items():
                values.append(z[key].astype(np.float64)[valid])
    return out


def albedo_bound(data: str) -> None:
    truth = _truth(data)["base_color"]
    relative = [b / max(b.mean(1).max(), 1e-3) for b in truth]
    g, r = np.concatenate(truth), np.concatenate(relative)
    k = (r * g).sum() / (r * r).sum()
    const, oracle = g.std(), np.sqrt(((k * r - g) ** 2).mean())
    print(f"scenes {len(truth)}  constant RMSE {const:.4f}  relative-albedo oracle RMSE {oracle:.4f} "
          f"({1 - oracle / const:.0%} below the constant)")


def constants(data: str) -> None:
    from matcap.export import DEFAULTS

    for key, values in _truth(data).items():
        g = np.concatenate(values)
        default = np.asarray(DEFAULTS[key], np.float64)
        print(f"{key:<10}  best constant {g.mean():.3f}: RMSE {g.std():.3f}   export default "
              f"{DEFAULTS[key]}: RMSE {np.sqrt(((g - default) ** 2).mean()):.3f}")


def _lights_from_normals(obs: np.ndarray, normals: np.ndarray, weight: np.ndarray, rounds: int = 6) -> np.ndarray:
    """Directional lights (K, 3), intensity in the length, that explain grey observations ``obs`` (K, P) with the
    fixed unit ``normals`` (P, 3): alternating least squares for the lights and the per-pixel albedo, on the
    observations that ``weight`` (K, P) keeps."""
    albedo = np.ones(obs.shape[1])
    lights = np.zeros((obs.shape[0], 3))
    for _ in range(rounds):
        for k in range(obs.shape[0]):
            root = np.sqrt(weight[k])
            lights[k] = np.linalg.lstsq(albedo[:, None] * normals * root[:, None], obs[k] * root, rcond=None)[0]
        shading = np.maximum(lights @ normals.T, 0.0)
        albedo = np.maximum((weight * shading * obs).sum(0) / np.maximum((weight * shading**2).sum(0), 1e-12), 0.0)
    return lights


def self_calibrated(data: str, init: str) -> None:
    import json

    import torch

    from matcap.evaluation.baselines import robust_keep_weights
    from networks.checkpoint import load_model
    from networks.data import list_scenes, load_scene
    from networks.inference import predict
    from networks.preprocess import normalize_images

    model = load_model(init)[0].eval()
    errors: dict[str, dict[str, list[float]]] = {}
    for path in list_scenes(data):
        scene = load_scene(path)
        mask = scene["mask"].astype(bool)
        truth = scene["normal"].astype(np.float64)
        valid = mask & (np.linalg.norm(truth, axis=2) > 0.5)
        images = torch.from_numpy(scene["images"].astype(np.float32)).permute(0, 3, 1, 2)
        m = torch.from_numpy(mask)
        net = predict(model, normalize_images(images, m.float().unsqueeze(0)), m, seed=0)["normal"][valid]
        net = net.astype(np.float64) / np.maximum(np.linalg.norm(net, axis=1, keepdims=True), 1e-12)
        obs = scene["images"].astype(np.float64)[:, valid].mean(2)
        obs /= max(obs.max(), 1e-12)
        keep = robust_keep_weights(obs, 0.3, 0.1)
        lights = _lights_from_normals(obs, net, keep)
        keep = keep * (lights @ net.T > 0)  # attached shadows under the estimated lights
        a = np.einsum("kp,ki,kj->pij", keep, lights, lights) + 1e-9 * np.eye(3)
        g = np.linalg.solve(a, ((keep * obs).T @ lights)[:, :, None])[:, :, 0]
        solved = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
        mean = solved + net
        mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
        gt = truth[valid] / np.linalg.norm(truth[valid], axis=1, keepdims=True)
        group = json.loads((path / "spec.json").read_text()).get("lighting_group") or "all"
        for name, n in (("network", net), ("re-solved", solved), ("average", mean)):
            err = np.degrees(np.arccos(np.clip((n * gt).sum(1), -1, 1))).mean()
            errors.setdefault(group, {}).setdefault(name, []).append(float(err))
    print("| group | scenes | network | re-solved | average |")
    print("|---|---:|---:|---:|---:|")
    for group, row in sorted(errors.items()):
        print(f"| {group} | {len(row['network'])} | " + " | ".join(f"{np.mean(row[k]):.2f}" for k in row) + " |")


def _predictions(model, data: str, scenes: int | None):
    """Per scene of ``data`` (the first ``scenes``): (scene folder, loaded scene, mask (H, W) bool, predicted maps),
    the maps from one view of all stored images with the ground-truth mask, as validation predicts them."""
    from networks.data import list_scenes, load_scene
    from networks.inference import predict

    for path in list_scenes(data)[:scenes]:
        scene = load_scene(path)
        m, images = _network_input(scene)
        yield Path(path), scene, m.numpy(), predict(model, images, m, seed=0)


def brdf_outputs(data: str, init: str, scenes: int) -> None:
    import torch

    from networks.checkpoint import load_model

    torch.set_num_threads(1)
    model, _, _ = load_model(init)
    heads = {"roughness": model.regressor.prediction_rough, "metallic": model.regressor.prediction_metal}
    raw: dict[str, list] = {k: [] for k in heads}
    for key, head in heads.items():
        head.register_forward_hook(lambda _m, _i, out, key=key: raw[key].append(out.detach().float().reshape(-1)))
    pre: dict[str, list] = {k: [] for k in heads}
    pred: dict[str, list] = {k: [] for k in heads}
    truth: dict[str, list] = {k: [] for k in heads}
    for _, scene, mask, out in _predictions(model, data, scenes):
        for key in heads:
            pre[key].append(torch.cat(raw[key]).numpy())
            raw[key].clear()
            pred[key].append(out[key][mask].reshape(-1))
            truth[key].append(scene[key][mask].astype(np.float64).reshape(-1))
    print(f"{init} on the first {scenes} scenes of {data}")
    print("| map | outputs < 0 before ReLU | mean prediction | mean truth | correlation |")
    print("|---|---:|---:|---:|---:|")
    for key in heads:
        x, p, t = (np.concatenate(d[key]) for d in (pre, pred, truth))
        print(f"| {key} | {(x < 0).mean():.1%} | {p.mean():.3f} | {t.mean():.3f} | {np.corrcoef(p, t)[0, 1]:.3f} |")
    p, t = np.concatenate(pred["metallic"]), np.concatenate(truth["metallic"])
    print(f"metallic: mean prediction {p[t > 0.5].mean():.3f} on metals ({(t > 0.5).mean():.1%} of pixels), "
          f"{p[t <= 0.5].mean():.3f} on the rest")


CATEGORIES = ("diffuse", "specular", "metallic")


def material_groups(spec_json: dict, resolution: int, assets: str, cache: dict) -> np.ndarray:
    """(H, W) int: per pixel, 2 * category index + (1 on the backdrop), -1 where no surface; categories as in
    :data:`CATEGORIES` (the generator's material category of the visible shape)."""
    from matcap.synth import AssetCache
    from renderers.synth import render_object_index
    from scenes.synth_build import RenderObject, object_geometry
    from scenes.synth_spec import scene_from_dict

    spec = scene_from_dict(spec_json)
    assets_cache = cache.setdefault("assets", AssetCache(assets))
    items = [(o, False) for o in spec.objects] + ([(spec.background, True)] if spec.background else [])
    blank = np.zeros((2, 2), np.float32)
    objects = [RenderObject(object_geometry(o, assets_cache.mesh(o.mesh) if o.shape == "mesh" else None),
                            np.zeros((2, 2, 3), np.float32), blank, blank, o.material.specular, 1.0, bg)
               for o, bg in items]
    index = render_object_index(objects, resolution)
    code = np.int16([2 * CATEGORIES.index(o.material.category) + int(bg) for o, bg in items] + [-1])
    return code[index]  # index -1 picks the trailing -1


def brdf_by_material(data: str, init: str, assets: str, scenes: int | None) -> None:
    import json

    import torch

    from networks.checkpoint import load_model

    torch.set_num_threads(1)
    model, _, _ = load_model(init)
    keys = ("roughness", "metallic")
    groups, truth, pred = [], {k: [] for k in keys}, {k: [] for k in keys}
    cache: dict = {}
    for path, scene, mask, out in _predictions(model, data, scenes):
        valid = _valid_pixels(scene)
        g = material_groups(json.loads((path / "spec.json").read_text()), mask.shape[0], assets, cache)
        if (g[valid] < 0).any():
            raise SystemExit(f"{path}: the re-rendered shapes miss {(g[valid] < 0).sum()} valid pixels")
        groups.append(g[valid])
        for k in keys:
            truth[k].append(scene[k][valid].astype(np.float64))
            pred[k].append(out[k][valid].astype(np.float64))
    g = np.concatenate(groups)
    t = {k: np.concatenate(v) for k, v in truth.items()}
    p = {k: np.concatenate(v) for k, v in pred.items()}

    def rmse(a, b):
        return float(np.sqrt(((a - b) ** 2).mean())) if a.size else float("nan")

    print(f"{init} on {len(groups)} scenes of {data}: every valid pixel, grouped by the generator's material")
    print("| surface | material | pixels | roughness mean: truth (std), network | roughness RMSE: network, constant "
          "| metallic mean: truth, network | metallic RMSE: network, constant |")
    print("|---|---|---:|---:|---:|---:|---:|")
    const = {k: t[k].mean() for k in keys}
    rows = [(f"{'backdrop' if code % 2 else 'objects'}", CATEGORIES[code // 2], g == code) for code in range(6)]
    for surface, cat, sel in rows + [("all", "all", np.ones_like(g, bool))]:
        if not sel.any():
            continue
        r, m = t["roughness"][sel], t["metallic"][sel]
        print(f"| {surface} | {cat} | {sel.mean():.1%} | {r.mean():.3f} ({r.std():.3f}), "
              f"{p['roughness'][sel].mean():.3f} | {rmse(p['roughness'][sel], r):.3f}, {rmse(const['roughness'], r):.3f} "
              f"| {m.mean():.3f}, {p['metallic'][sel].mean():.3f} | "
              f"{rmse(p['metallic'][sel], m):.3f}, {rmse(const['metallic'], m):.3f} |")
    # If roughness cannot be seen on diffuse materials (specular <= 0.3), the best a predictor can do there is the
    # mean over them; exact everywhere else.
    diffuse = g // 2 == 0
    bound = np.where(diffuse, t["roughness"][diffuse].mean(), t["roughness"])
    c = rmse(const["roughness"], t["roughness"])
    b = rmse(bound, t["roughness"])
    print(f"roughness: best constant RMSE {c:.3f}; exact except on diffuse materials (their mean there) {b:.3f} "
          f"({1 - b / c:.0%} below the constant); network {rmse(p['roughness'], t['roughness']):.3f}")


def normal_by_material(data: str, init: str, assets: str, scenes: int | None) -> None:
    import json

    import torch

    from networks.checkpoint import load_model

    torch.set_num_threads(1)
    model, _, _ = load_model(init)
    rows: dict[tuple[str, str], list[np.ndarray]] = {}
    cache: dict = {}
    for path, scene, mask, out in _predictions(model, data, scenes):
        truth = scene["normal"].astype(np.float64)
        valid = _valid_pixels(scene)
        spec = json.loads((path / "spec.json").read_text())
        g = material_groups(spec, mask.shape[0], assets, cache)
        cos = np.clip((out["normal"].astype(np.float64) * truth).sum(-1), -1, 1)
        err = np.degrees(np.arccos(cos))
        group = spec.get("lighting_group", "?")
        for code in range(6):
            sel = valid & (g == code)
            rows.setdefault((group, code), []).append(err[sel])
    print(f"{init} on {data}: mean angular error (degrees) over the valid pixels of each lighting group and material "
          "group (pixel-weighted, so it differs from validation's mean of per-scene means)")
    groups = sorted({k[0] for k in rows})
    print("| surface | material | " + " | ".join(groups) + " | all | share of pixels |")
    print("|---|---|" + "---:|" * (len(groups) + 2))
    total = sum(sum(a.size for a in v) for v in rows.values())
    for code in range(6):
        cells = [np.concatenate(rows.get((grp, code), [np.zeros(0)])) for grp in groups]
        both = np.concatenate(cells)
        if not both.size:
            continue
        print(f"| {'backdrop' if code % 2 else 'objects'} | {CATEGORIES[code // 2]} | "
              + " | ".join(f"{c.mean():.2f}" if c.size else "-" for c in cells) + f" | {both.mean():.2f} | "
              f"{both.size / total:.1%} |")


def _regressor_features(model, path: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """The regressor's per-pixel features (P, dim) (what every prediction head reads) at the valid pixels of one
    scene, their flat pixel indices (P,), and the loaded scene; predicted as :func:`networks.inference.predict` does."""
    import torch

    from networks.data import load_scene

    scene = load_scene(path)
    valid = _valid_pixels(scene).reshape(-1)
    m, images = _network_input(scene)
    x, mk = images[None], m[None, None].float()
    ids = torch.nonzero(m.reshape(-1)).squeeze(1)
    ids = ids[torch.randperm(ids.numel(), generator=torch.Generator().manual_seed(0))]
    got: list = []
    hook = model.regressor.comm.register_forward_hook(lambda _m, _i, out: got.append(out.detach().float()[0]))
    try:
        with torch.inference_mode():
            feats = model.encode(x, mk)
            for start in range(0, ids.numel(), model.config.pixel_samples):
                model.decode(x, mk, feats, ids[start:start + model.config.pixel_samples][None])
    finally:
        hook.remove()
    f, idx = torch.cat(got).numpy(), ids.numpy()
    keep = valid[idx]
    return f[keep], idx[keep], scene


def head_refit(fit_data: str, val_data: str, init: str, fit_scenes: int, per_scene: int) -> None:
    """Refit each BRDF head's last linear layer by (ridge) least squares on features of ``fit_scenes`` random scenes
    of ``fit_data`` (``per_scene`` random valid pixels each) and score it on every valid pixel of ``val_data``."""
    import torch

    from networks.checkpoint import load_model
    from networks.data import list_scenes

    torch.set_num_threads(1)
    model, _, _ = load_model(init)
    model.eval()
    heads = {"base_color": "prediction_base", "roughness": "prediction_rough", "metallic": "prediction_metal"}

    def collect(paths, limit, rng):
        feats, truth = [], {k: [] for k in heads}
        for path in paths:
            f, idx, scene = _regressor_features(model, Path(path))
            if limit and len(idx) > limit:
                pick = rng.choice(len(idx), limit, replace=False)
                f, idx = f[pick], idx[pick]
            feats.append(f)
            for key, values in truth.items():
                values.append(scene[key].reshape(-1, *scene[key].shape[2:])[idx].astype(np.float64))
        return np.concatenate(feats).astype(np.float64), {k: np.concatenate(v) for k, v in truth.items()}

    paths = list_scenes(fit_data)
    pick = np.random.default_rng(1).choice(len(paths), min(fit_scenes, len(paths)), replace=False)
    f_fit, t_fit = collect([paths[i] for i in pick], per_scene, np.random.default_rng(0))
    f_val, t_val = collect(list_scenes(val_data), 0, None)

    def rmse(pred, truth):
        return float(np.sqrt(((np.maximum(pred, 0) - truth) ** 2).mean()))

    print(f"{init}: last layers refit on {len(pick)} scenes of {fit_data} ({len(f_fit)} pixels), scored on "
          f"{val_data} ({len(f_val)} pixels); RMSE after the ReLU")
    print("| map | constant | network head | refit: validation | refit: fit data | network head: fit data |")
    print("|---|---:|---:|---:|---:|---:|")
    for key, name in heads.items():
        seq = getattr(model.regressor, name).regression
        w1, b1 = seq[0].weight.detach().double().numpy(), seq[0].bias.detach().double().numpy()
        w2, b2 = seq[2].weight.detach().double().numpy(), seq[2].bias.detach().double().numpy()
        h_fit, h_val = (np.hstack([np.maximum(f @ w1.T + b1, 0), np.ones((len(f), 1))]) for f in (f_fit, f_val))
        t = t_fit[key].reshape(len(h_fit), -1)
        sol = np.linalg.solve(h_fit.T @ h_fit + 0.1 * np.eye(h_fit.shape[1]), h_fit.T @ t)
        head = np.vstack([w2.T, b2[None]])
        tv = t_val[key].reshape(len(h_val), -1)
        const = float(np.sqrt(((tv - tv.mean(0)) ** 2).mean()))
        print(f"| {key} | {const:.4f} | {rmse(h_val @ head, tv):.4f} | {rmse(h_val @ sol, tv):.4f} | "
              f"{rmse(h_fit @ sol, t):.4f} | {rmse(h_fit @ head, t):.4f} |")


def average(out: str, weights: list[str]) -> None:
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    with safe_open(weights[0], "pt") as f:
        meta = f.metadata()
    states = [load_file(w) for w in weights]
    mean = {k: (sum(s[k].float() for s in states) / len(states)).to(states[0][k].dtype) for k in states[0]}
    save_file(mean, out, metadata=meta)
    print(f"wrote {out}: mean of {len(weights)} weights")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    o = sub.add_parser("overfit")
    o.add_argument("--data", required=True)
    o.add_argument("--init", help="start from these weights (default: random)")
    o.add_argument("--steps", type=int, default=60)
    o.add_argument("--lr", type=float, default=4e-4)
    o.add_argument("--target", choices=("normal", "brdf"), default="normal")
    for name in ("albedo-bound", "constants"):
        sub.add_parser(name).add_argument("--data", required=True)
    c = sub.add_parser("self-calibrated")
    c.add_argument("--data", required=True)
    c.add_argument("--init", default="networks/weights/normal_small.safetensors", help="normal network weights")
    b = sub.add_parser("brdf-outputs")
    b.add_argument("--data", required=True)
    b.add_argument("--init", default="networks/weights/brdf_small.safetensors", help="BRDF network weights")
    b.add_argument("--scenes", type=int, default=12)
    m = sub.add_parser("brdf-by-material")
    m.add_argument("--data", required=True)
    m.add_argument("--init", default="networks/weights/brdf_small.safetensors", help="BRDF network weights")
    m.add_argument("--assets", default="../shared/data", help="the assets the data was rendered from (meshes)")
    m.add_argument("--scenes", type=int, help="the first N scenes (default: all)")
    n = sub.add_parser("normal-by-material")
    n.add_argument("--data", required=True)
    n.add_argument("--init", default="networks/weights/normal_small.safetensors", help="normal network weights")
    n.add_argument("--assets", default="../shared/data", help="the assets the data was rendered from (meshes)")
    n.add_argument("--scenes", type=int, help="the first N scenes (default: all)")
    h = sub.add_parser("head-refit")
    h.add_argument("--data", required=True, help="scenes to refit on (the training data)")
    h.add_argument("--val-data", required=True)
    h.add_argument("--init", default="networks/weights/brdf_small.safetensors", help="BRDF network weights")
    h.add_argument("--scenes", type=int, default=150, help="random scenes of --data to refit on")
    h.add_argument("--pixels", type=int, default=3000, help="random valid pixels per refit scene")
    a = sub.add_parser("average")
    a.add_argument("--out", required=True)
    a.add_argument("weights", nargs="+")
    args = ap.parse_args(argv)
    if args.what == "overfit":
        overfit(args.data, args.init, args.steps, args.lr, args.target)
    elif args.what == "self-calibrated":
        self_calibrated(args.data, args.init)
    elif args.what == "average":
        average(args.out, args.weights)
    elif args.what == "brdf-by-material":
        brdf_by_material(args.data, args.init, args.assets, args.scenes)
    elif args.what == "normal-by-material":
        normal_by_material(args.data, args.init, args.assets, args.scenes)
    elif args.what == "head-refit":
        head_refit(args.data, args.val_data, args.init, args.scenes, args.pixels)
    elif args.what == "brdf-outputs":
        brdf_outputs(args.data, args.init, args.scenes)
    elif args.what == "albedo-bound":
        albedo_bound(args.data)
    else:
        constants(args.data)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
