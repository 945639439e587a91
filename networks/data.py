"""Training samples drawn from `matcap synth` datasets (numpy only; reads each scene's ``data.npz``).

A scene folder holds ``data.npz`` with ``basis`` (B, H, W, 3) float16 linear renders of the basis lights,
``basis_kind`` (B,) ("env" / "directional" / "point"), ``images`` (10, H, W, 3) float16, ``normal`` (H, W, 3),
``mask`` (H, W) bool, ``base_color`` (H, W, 3), ``roughness`` (H, W), ``metallic`` (H, W).

Data v2 scenes (``matcap synth --data-version 2``) add basis kinds "spot" and "area", ``data_version`` (2),
``basis_light_vec`` (B, 3) the vector irradiance of each basis light at the scene origin and ``light_vec``
(10, 3) that of each stored image (exposure included); samples then carry ``light_vec`` (K, 3) for every image
(zeros, with ``light_known`` False, for v1 scenes) so a light-alignment loss can use it.

Every random choice of a sample comes from ``numpy.random.default_rng([seed, step, rank, slot])``, so the data
order is a pure function of the step: training resumes bit-for-bit without saving loader state, and
data-parallel ranks draw different samples without a sampler.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from networks.dihedral import DIHEDRAL, transform_map

#: The five light configurations of PS-Mix: (a) env, (b) directional, (c) point, (d) a+b, (e) a+c; data v2 adds
#: spot, area, env+spot, env+area (used only where a scene has those kinds, so v1 draws are unchanged).
CONFIGURATIONS = (("env",), ("directional",), ("point",), ("env", "directional"), ("env", "point"),
                  ("spot",), ("area",), ("env", "spot"), ("env", "area"))
#: Data v2: probability that a sample's fresh images share one strong fixed light plus a weak moving one.
FIXED_MOVING_PROB = 0.15


def finished_scenes(root: Path) -> list[Path]:
    """The scene folders under ``root`` that hold ``data.npz``, leaving out hidden ones: a generator writes each
    scene into a hidden temporary folder (``.tmp-scene_...``) and renames it when complete."""
    return [p.parent for p in root.glob("*/data.npz") if not p.parent.name.startswith(".")]


def list_scenes(root: str | Path) -> list[Path]:
    """Scene folders of a dataset (those with ``data.npz``), in the manifest's order when there is one."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: not a dataset folder")
    manifest = root / "manifest.json"
    names: list[str] = []
    if manifest.exists():
        try:
            names = list(json.loads(manifest.read_text()).get("scenes", []))
        except json.JSONDecodeError:
            names = []
    scenes = [root / n for n in names if (root / n / "data.npz").exists()]
    # scenes finished after the manifest was last written (e.g. a generator still running) come after it, sorted
    listed = set(scenes)
    scenes += sorted(p for p in finished_scenes(root) if p not in listed)
    if not scenes:
        raise ValueError(f"{root}: no scenes with data.npz (make some with `matcap synth --out {root}`)")
    return scenes


class GrowingScenes:
    """The scenes of a dataset folder that is still being written (a generator rendering into it), in an order that
    only ever grows at the end: each :meth:`refresh` appends the scene folders that appeared since, sorted by name,
    so the first ``n`` scenes never change and a sample that picks scene ``i < n`` always gets the same one.

    The order is kept in ``index`` (a text file, one scene name per line, written before a larger count is used):
    worker processes read it to follow the growth, and it records which scenes a run trained on in which order.
    ``resume=True`` starts from an existing ``index`` when every scene it names is still there (the same folder on
    the same machine); otherwise the folder is listed afresh and the index rewritten.
    """

    def __init__(self, root: str | Path, index: str | Path, resume: bool = False):
        self.root = Path(root)
        self.index = Path(index)
        self.scenes: list[Path] = []
        kept = read_scene_index(self.index, self.root) if resume and self.index.exists() else None
        if kept is not None:
            self.scenes = kept
            self.refresh()
        else:
            self.scenes = list_scenes(self.root)
            self._write(self.scenes, mode="w")

    def __len__(self) -> int:
        return len(self.scenes)

    def _write(self, paths: list[Path], mode: str) -> None:
        self.index.parent.mkdir(parents=True, exist_ok=True)
        with open(self.index, mode) as f:
            f.writelines(p.name + "\n" for p in paths)
            f.flush()
            os.fsync(f.fileno())

    def refresh(self) -> int:
        """Append the scenes that appeared since the last look; returns how many."""
        known = {p.name for p in self.scenes}
        new = sorted((p for p in finished_scenes(self.root) if p.name not in known), key=lambda p: p.name)
        if new:
            self._write(new, mode="a")
            self.scenes.extend(new)
        return len(new)


def read_scene_index(index: str | Path, root: str | Path, count: int | None = None) -> list[Path] | None:
    """The first ``count`` (default: all) scenes named in a :class:`GrowingScenes` index, as paths under ``root``;
    None when one of them has no ``data.npz`` there."""
    root = Path(root)
    names = Path(index).read_text().split()
    if count is not None:
        if len(names) < count:
            raise ValueError(f"{index} names {len(names)} scenes, fewer than the {count} asked for")
        names = names[:count]
    paths = [root / n for n in names]
    if not all((p / "data.npz").exists() for p in paths):
        return None
    return paths


@dataclass
class SampleSpec:
    """How training samples are drawn (all fields documented; defaults follow the paper where it says)."""

    resolution: int = 256
    """Side of the square training crop fed to the network (256 as in the paper; on a CPU use 128 with
    --canonical-resolution 128, as the bundled models were trained: docs/training.md)."""
    min_images: int = 3
    """Fewest images per sample (K is drawn uniformly in [min_images, max_images])."""
    max_images: int = 6
    """Most images per sample."""
    pixel_samples: int = 2048
    """Pixels per sample where the loss is evaluated (one attention sample set)."""
    fresh_combination_prob: float = 0.75
    """Probability to synthesise each image from the stored basis renders instead of using a stored image."""
    drop_mask_prob: float = 0.5
    """Probability that the network gets no mask (all ones) so mask-free scenes are learned."""
    min_crop: float = 0.6
    """Smallest crop side as a fraction of the scene side (random crop + rescale augmentation)."""
    dihedral: bool = True
    """Apply one of the 8 mirror / 90-degree symmetries of the image plane, drawn at random, to the images and
    maps (normals turned with them). Exact for an orthographic camera: it is the mirrored / rotated scene."""


def _combine(basis: np.ndarray, kinds: np.ndarray, rng: np.random.Generator, vectors: np.ndarray | None = None):
    """One image as a random non-negative combination of basis renders following a PS-Mix configuration.
    Returns the image, and its light vector when ``vectors`` (B, 3) is given (else None)."""
    available = set(kinds.tolist())
    configs = [c for c in CONFIGURATIONS if set(c) <= available] or [(kinds[0],)]
    config = configs[rng.integers(len(configs))]
    out = np.zeros(basis.shape[1:], dtype=np.float32)
    vec = None if vectors is None else np.zeros(3, np.float32)
    for kind in config:
        idx = np.flatnonzero(kinds == kind)
        j = idx[rng.integers(len(idx))]
        weight = rng.uniform(0.3, 1.0) if kind == "env" else rng.uniform(0.5, 2.0)
        tint = rng.uniform(0.85, 1.15, size=3).astype(np.float32)  # light colour
        out += basis[j].astype(np.float32) * (weight * tint)
        if vec is not None:
            vec += vectors[j] * np.float32(weight * tint.mean())
    return out, vec


def _fixed_moving(basis: np.ndarray, kinds: np.ndarray, vectors: np.ndarray, k: int, rng: np.random.Generator):
    """Data v2: ``k`` images under one strong fixed light plus a weak light that moves from image to image."""
    fixed_pool = np.flatnonzero(np.isin(kinds, ["env", "directional", "area"]))
    j = int(fixed_pool[rng.integers(len(fixed_pool))])
    movers = np.flatnonzero(np.isin(kinds, ["directional", "point", "spot"]) & (np.arange(len(kinds)) != j))
    strong = rng.uniform(0.8, 1.5) if kinds[j] == "env" else rng.uniform(1.0, 2.0)
    images, vecs = [], []
    for _ in range(k):
        m = int(movers[rng.integers(len(movers))])
        w = strong * rng.uniform(0.08, 0.3)
        images.append(basis[j].astype(np.float32) * np.float32(strong) + basis[m].astype(np.float32) * np.float32(w))
        vecs.append((vectors[j] * strong + vectors[m] * w).astype(np.float32))
    return images, vecs


def _turn_vectors(v: np.ndarray, t: tuple[bool, bool, bool]) -> np.ndarray:
    """(N, 3) camera-space vectors under a symmetry of networks.dihedral (as its normal maps turn): transpose
    maps (x, y) to (-y, -x), mirroring the columns negates x, mirroring the rows negates y."""
    v = np.array(v, np.float32)
    transpose, flip_c, flip_r = t
    if transpose:
        v = v[:, [1, 0, 2]] * np.float32([-1, -1, 1])
    if flip_c:
        v[:, 0] *= -1
    if flip_r:
        v[:, 1] *= -1
    return v


def _resize(arr: np.ndarray, size: int, nearest: bool = False) -> np.ndarray:
    import cv2

    if arr.shape[0] == size and arr.shape[1] == size:
        return arr
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA if arr.shape[0] > size else cv2.INTER_LINEAR
    if arr.dtype == bool:
        return cv2.resize(arr.astype(np.uint8), (size, size), interpolation=cv2.INTER_NEAREST).astype(bool)
    return cv2.resize(arr, (size, size), interpolation=interp)


def load_scene(path: Path) -> dict[str, np.ndarray]:
    with np.load(path / "data.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def draw_sample(scene: dict[str, np.ndarray], spec: SampleSpec, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One training sample from a loaded scene.

    Returns images (K, 3, R, R) float32 linear (not yet normalised), input_mask (R, R) float32 (all ones when
    dropped), loss_mask (R, R) bool, normal (R, R, 3), base_color (R, R, 3), roughness (R, R), metallic (R, R),
    pixel_index (m,) int64 flat indices inside loss_mask (sampled with replacement if it has fewer than m pixels).
    """
    k = int(rng.integers(spec.min_images, spec.max_images + 1))
    basis, kinds = scene.get("basis"), scene.get("basis_kind")
    stored = scene["images"]
    vectors = scene.get("basis_light_vec")  # data v2 only
    stored_vec = scene.get("light_vec")
    imgs, vecs = [], []
    kinds_s = None if kinds is None else np.asarray(kinds).astype(str)
    if (vectors is not None and basis is not None and len(basis) and rng.random() < FIXED_MOVING_PROB
            and np.isin(kinds_s, ["directional", "point", "spot"]).sum() >= 2):
        imgs, vecs = _fixed_moving(basis, kinds_s, vectors.astype(np.float32), k, rng)
    for _ in range(k - len(imgs)):
        if basis is not None and len(basis) and rng.random() < spec.fresh_combination_prob:
            image, vec = _combine(basis, kinds_s, rng, None if vectors is None else vectors.astype(np.float32))
            imgs.append(image)
        else:
            j = rng.integers(len(stored))
            gain = rng.uniform(0.5, 1.5)
            imgs.append(stored[j].astype(np.float32) * gain)
            vec = None if stored_vec is None else stored_vec[j].astype(np.float32) * np.float32(gain)
        vecs.append(vec)
    h, w = scene["mask"].shape
    side = int(round(min(h, w) * rng.uniform(spec.min_crop, 1.0)))
    y0, x0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
    sl = (slice(y0, y0 + side), slice(x0, x0 + side))
    R = spec.resolution
    images = np.stack([_resize(np.ascontiguousarray(im[sl]), R) for im in imgs]).transpose(0, 3, 1, 2)
    gt_mask = _resize(np.ascontiguousarray(scene["mask"][sl]), R, nearest=True)
    normal = _resize(np.ascontiguousarray(scene["normal"][sl].astype(np.float32)), R, nearest=True)
    length = np.linalg.norm(normal, axis=2)
    loss_mask = gt_mask & (length > 0.5)
    normal = np.where(loss_mask[..., None], normal / np.maximum(length, 1e-6)[..., None], 0.0)
    out = {
        "images": np.ascontiguousarray(images, dtype=np.float32),
        "input_mask": np.ones((R, R), np.float32) if rng.random() < spec.drop_mask_prob else gt_mask.astype(np.float32),
        "loss_mask": loss_mask,
        "normal": normal.astype(np.float32),
        "base_color": _resize(np.ascontiguousarray(scene["base_color"][sl].astype(np.float32)), R, nearest=True),
        "roughness": _resize(np.ascontiguousarray(scene["roughness"][sl].astype(np.float32)), R, nearest=True),
        "metallic": _resize(np.ascontiguousarray(scene["metallic"][sl].astype(np.float32)), R, nearest=True),
        "light_vec": np.stack([np.zeros(3, np.float32) if v is None else v for v in vecs]).astype(np.float32),
        "light_known": np.array(vectors is not None),
    }
    if spec.dihedral:
        t = DIHEDRAL[int(rng.integers(len(DIHEDRAL)))]
        for key, value in out.items():
            if key == "light_known":
                continue
            if key == "light_vec":  # (K, 3) camera-space vectors turn with the image plane
                out[key] = _turn_vectors(value, t)
            elif key == "images":  # (K, 3, R, R): move the plane axes first, transform, move back
                out[key] = np.ascontiguousarray(transform_map(value.transpose(2, 3, 0, 1), t).transpose(2, 3, 0, 1))
            else:
                out[key] = transform_map(value, t, normal=(key == "normal"))
        loss_mask = out["loss_mask"]
    valid = np.flatnonzero(loss_mask.ravel())
    if len(valid) == 0:
        valid = np.arange(R * R)
    m = spec.pixel_samples
    out["pixel_index"] = rng.choice(valid, size=m, replace=len(valid) < m).astype(np.int64)
    return out


class SceneCache:
    """Keeps loaded scenes in memory (bounded: about 7 MB per 256^2 scene)."""

    def __init__(self, scenes: list[Path], max_items: int = 512):
        self.scenes = scenes
        self.max_items = max_items
        self._cache: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.scenes)

    def get(self, i: int) -> dict[str, np.ndarray]:
        if i not in self._cache:
            if len(self._cache) >= self.max_items:
                self._cache.pop(next(iter(self._cache)))
            self._cache[i] = load_scene(self.scenes[i])
        return self._cache[i]


MICRO_OFFSET = 1 << 20  # keeps a micro-batch's seed apart from every sample slot's (slots stay below it)


def draw_batch(cache: SceneCache, spec: SampleSpec, batch: int, seed: int, step: int, rank: int = 0, micro: int = 0,
               n_scenes: int | None = None):
    """A batch of ``batch`` samples with a common K (so they stack): dict of (B, ...) numpy arrays.

    A pure function of ``(seed, step, rank, micro)`` and the scenes it draws from: the first ``n_scenes`` of the
    cache (default: all of them; a growing dataset passes the count of each step). ``micro`` numbers the
    micro-batches of one optimiser step when gradients are accumulated (micro-batch 0 is the batch drawn without
    accumulation)."""
    n = len(cache) if n_scenes is None else int(n_scenes)
    if not 1 <= n <= len(cache):
        raise ValueError(f"draw_batch: {n} scenes asked for, the cache holds {len(cache)}")
    if batch >= MICRO_OFFSET:
        raise ValueError(f"batch {batch} is too large (at most {MICRO_OFFSET - 1})")
    key = [seed, step, rank] if micro == 0 else [seed, step, rank, MICRO_OFFSET + micro]
    rng = np.random.default_rng(key)
    k = int(rng.integers(spec.min_images, spec.max_images + 1))
    fixed = SampleSpec(**{**spec.__dict__, "min_images": k, "max_images": k})
    samples = []
    for slot in range(batch):
        srng = np.random.default_rng([seed, step, rank, slot] + ([micro] if micro else []))
        scene = cache.get(int(srng.integers(n)))
        samples.append(draw_sample(scene, fixed, srng))
    return {key: np.stack([s[key] for s in samples]) for key in samples[0]}
