"""Compact, portable packs of a `matcap synth` dataset, to move training data to another machine (a GPU box
with a small upload limit, say) and unpack it there into the ordinary layout that training reads.

    python -m networks.datapack pack DATA OUT_DIR [--max-mb 40] [--start N] [--count N] [--quality 95]
    python -m networks.datapack unpack PACK.npz [PACK.npz ...] --out DATA                 # scene_*/data.npz

About 8x smaller than the scenes' ``data.npz`` (~0.25 MB a scene at 128^2): the basis renders are stored as 8-bit
gamma-2.2 codes with one scale per render (99.9th percentile), normals, base color, roughness and metallic as
8-bit codes, and the 10 stored images not at all: unpacking recomputes them from the basis renders, the stored
combination weights and exposures exactly as `matcap synth` made them (clipped to [0, 1]). The quantisation is
below what training can see (normals within 0.5 degrees). numpy only, except ``--quality Q``: the basis codes
as lossy WebP images (opencv), ~3x smaller again (~55 KB a scene at 128^2 and quality 95, mean code error ~1.2 of
255), for when the upload, not the data, is the limit.
"""
from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np

from scenes.atomic import atomic_path

GAMMA = 2.2
REQUIRED = ("basis", "basis_kind", "weights", "exposure", "normal", "mask", "object_mask", "base_color", "roughness",
            "metallic")


def encode_scene(scene: dict[str, np.ndarray], quality: int = 0) -> dict[str, np.ndarray]:
    """The arrays of one scene's data.npz -> compact arrays (see module docstring). ``quality`` 1-100 stores the
    8-bit basis codes as lossy WebP images of that quality (opencv) instead of losslessly."""
    basis = scene["basis"].astype(np.float32)
    scale = np.percentile(basis.reshape(len(basis), -1), 99.9, axis=1).astype(np.float32) + 1e-8
    codes = np.round(255.0 * np.clip(basis / scale[:, None, None, None], 0.0, 1.0) ** (1.0 / GAMMA)).astype(np.uint8)

    def unit8(x):
        return np.round(np.clip(np.asarray(x, np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)

    stored = {"basis": codes}
    if quality:
        if not 1 <= quality <= 100:
            raise ValueError(f"quality must be 0 (lossless) or 1-100, got {quality}")
        import cv2

        blobs = []
        for render in codes:
            ok, enc = cv2.imencode(".webp", np.ascontiguousarray(render[..., ::-1]), [cv2.IMWRITE_WEBP_QUALITY, quality])
            if not ok:
                raise ValueError("WebP encoding failed")
            blobs.append(enc.ravel())
        stored = {"basis_webp": np.concatenate(blobs),
                  "basis_webp_offsets": np.cumsum([0] + [len(b) for b in blobs]).astype(np.int64),
                  "basis_shape": np.asarray(codes.shape, np.int64)}
    return {
        **stored, "basis_scale": scale, "basis_kind": np.asarray(scene["basis_kind"]),
        "weights": scene["weights"].astype(np.float32), "exposure": scene["exposure"].astype(np.float32),
        "normal": unit8((scene["normal"].astype(np.float32) + 1.0) * 0.5),
        "mask": scene["mask"].astype(bool), "object_mask": scene["object_mask"].astype(bool),
        "base_color": unit8(scene["base_color"]), "roughness": unit8(scene["roughness"]),
        "metallic": unit8(scene["metallic"]),
    }


def decode_scene(packed: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Compact arrays -> the arrays of a data.npz (float16 maps, recomputed images)."""
    if "basis_webp" in packed:
        import cv2

        data, offsets = packed["basis_webp"], packed["basis_webp_offsets"]
        codes = np.stack([cv2.imdecode(data[a:b], cv2.IMREAD_COLOR)[..., ::-1] for a, b in zip(offsets, offsets[1:])])
        if codes.shape != tuple(packed["basis_shape"]):
            raise ValueError(f"WebP basis decoded to {codes.shape}, expected {tuple(packed['basis_shape'])}")
    else:
        codes = packed["basis"]
    basis = (codes.astype(np.float32) / 255.0) ** GAMMA * packed["basis_scale"][:, None, None, None]
    raw = np.tensordot(packed["weights"], basis, axes=1)
    images = np.clip(raw * packed["exposure"][:, None, None, None], 0.0, 1.0)
    mask = packed["mask"].astype(bool)
    normal = packed["normal"].astype(np.float32) / 255.0 * 2.0 - 1.0
    length = np.linalg.norm(normal, axis=2, keepdims=True)
    normal = np.where(mask[..., None] & (length > 0.5), normal / np.maximum(length, 1e-6), 0.0)
    return {
        "basis": basis.astype(np.float16), "basis_kind": packed["basis_kind"], "normal": normal.astype(np.float16),
        "mask": mask, "object_mask": packed["object_mask"].astype(bool),
        "base_color": (packed["base_color"] / 255.0).astype(np.float16),
        "roughness": (packed["roughness"] / 255.0).astype(np.float16),
        "metallic": (packed["metallic"] / 255.0).astype(np.float16),
        "images": images.astype(np.float16), "weights": packed["weights"], "exposure": packed["exposure"],
    }


def _scene_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def pack(data: str | Path, out_dir: str | Path, max_mb: float = 40.0, start: int = 0,
         count: int | None = None, quality: int = 0) -> list[Path]:
    """Pack scenes ``start .. start + count`` of a dataset (in list order) into files of at most ``max_mb``
    (``quality``: see :func:`encode_scene`)."""
    from networks.data import list_scenes

    scenes = list_scenes(data)[start:None if count is None else start + count]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written, current, size = [], {}, 0

    def flush():
        nonlocal current, size
        if not current:
            return
        path = out_dir / f"pack_{len(written):03d}.npz"
        with atomic_path(path) as tmp, open(tmp, "wb") as f:  # an uncompressed npz of compressed npz blobs
            np.savez(f, **{k: np.frombuffer(v, np.uint8) for k, v in current.items()})
        written.append(path)
        current, size = {}, 0

    for path in scenes:
        with np.load(path / "data.npz", allow_pickle=False) as z:
            missing = [k for k in REQUIRED if k not in z.files]
            if missing:
                raise ValueError(f"{path / 'data.npz'} lacks {', '.join(missing)} (not a `matcap synth` scene)")
            arrays = encode_scene({k: z[k] for k in z.files}, quality)
        try:
            group = json.loads((path / "spec.json").read_text()).get("lighting_group") or ""
        except (OSError, json.JSONDecodeError):
            group = ""
        blob = _scene_bytes({**arrays, "lighting_group": np.asarray(group)})
        if current and size + len(blob) > max_mb * 1e6:
            flush()
        current[path.name] = blob
        size += len(blob)
    flush()
    return written


def unpack(packs: list[str | Path], out: str | Path) -> int:
    """Write every scene of ``packs`` as ``out/NAME/data.npz`` (+ spec.json with its lighting group)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n = 0
    for pack_path in packs:
        with np.load(pack_path, allow_pickle=False) as z:
            for name in z.files:
                with np.load(io.BytesIO(z[name].tobytes()), allow_pickle=False) as s:
                    arrays = {k: s[k] for k in s.files}
                group = str(arrays.pop("lighting_group"))
                folder = out / name
                folder.mkdir(parents=True, exist_ok=True)
                np.savez(folder / "data.npz", **decode_scene(arrays))
                spec = {"lighting_group": group} if group else {}
                (folder / "spec.json").write_text(json.dumps(spec))
                n += 1
    return n


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m networks.datapack", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("pack", help="write packs of a dataset's scenes")
    a.add_argument("data", help="a `matcap synth` dataset folder")
    a.add_argument("out_dir", help="folder for the packs (created)")
    a.add_argument("--max-mb", type=float, default=40.0,
                   help="start a new pack before one would exceed this many MB (default 40)")
    a.add_argument("--start", type=int, default=0, help="first scene to pack, in the dataset's order (default 0)")
    a.add_argument("--count", type=int, default=None, help="pack at most this many scenes (default: all from --start)")
    a.add_argument("--quality", type=int, default=0,
                   help="store basis renders as lossy WebP of this quality (1-100; ~3x smaller at 95); 0 = lossless")
    b = sub.add_parser("unpack", help="unpack packs into a dataset folder training reads")
    b.add_argument("packs", nargs="+", help="pack files (.npz) written by `pack`")
    b.add_argument("--out", required=True, help="dataset folder to write scene_*/ into")
    args = p.parse_args(argv)
    try:
        if args.cmd == "pack":
            for path in pack(args.data, args.out_dir, args.max_mb, args.start, args.count, args.quality):
                print(f"{path} {path.stat().st_size / 1e6:.1f} MB")
        else:
            print(f"unpacked {unpack(args.packs, args.out)} scenes into {args.out}")
    except (OSError, ValueError, KeyError) as exc:
        print(f"networks.datapack: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
