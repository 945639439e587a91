"""Image files in and out, with explicit bit depth and colour encoding.

Readers return the stored numbers (``uint8``, ``uint16`` or ``float32``) plus a description; converting to
linear float is a separate, explicit step (:func:`to_linear_float`). Writers are atomic (:mod:`scenes.atomic`,
re-exported here: ``atomic_path``, ``write_text_atomic``, ``write_json_atomic``): they write a temporary file in the
destination folder and rename it into place, so a crash never leaves a half-written image.

Formats: PNG (8/16-bit), JPEG, TIFF (8/16-bit/float), OpenEXR (float, via the OpenEXR package; Mitsuba's EXR
I/O can deadlock, see platform notes), Radiance HDR (via OpenCV). OpenCV keeps 16-bit exact; imageio does not.
"""
from __future__ import annotations

import contextlib
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matcap.errors import MatcapError
from scenes.atomic import (  # noqa: F401  (the one atomic-write helper, re-exported for matcap's writers)
    atomic_path,
    json_text,
    write_bytes_atomic,
    write_json_atomic,
    write_text_atomic,
)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".hdr")


@dataclass(frozen=True)
class StoredImage:
    """An image as stored on disk.

    pixels: (H, W, 3) ``uint8`` / ``uint16`` / ``float32`` RGB (grey is repeated, alpha dropped).
    """

    pixels: np.ndarray
    path: str

    @property
    def kind(self) -> str:
        """``"8bit"``, ``"16bit"`` or ``"float"``."""
        return {np.dtype(np.uint8): "8bit", np.dtype(np.uint16): "16bit"}.get(self.pixels.dtype, "float")


def _cv2():
    import cv2  # local: keeps `matcap --help` fast

    return cv2


def _to_rgb3(arr: np.ndarray, path: str) -> np.ndarray:
    if arr.ndim == 2:
        arr = np.repeat(arr[:, :, None], 3, axis=2)
    elif arr.ndim == 3 and arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    elif arr.ndim == 3 and arr.shape[2] >= 3:
        arr = arr[:, :, :3]
    else:
        raise MatcapError(f"{path}: unsupported image layout {arr.shape}")
    return np.ascontiguousarray(arr)


@contextlib.contextmanager
def _native_output_captured():
    """Collect what a native library prints while reading: the OpenEXR core writes its own line to file descriptor
    2 and the Python binding prints a "Warning: ..." line to ``sys.stdout`` for a corrupt file, before the exception.
    Yields a list that receives the captured text (fd-level capture is skipped where fds cannot be duplicated)."""
    import ctypes
    import io
    import sys

    captured: list[str] = []
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    py_streams = sys.stdout, sys.stderr
    py_sink = io.StringIO()
    saved: list[int] | None = []
    try:
        for fd in (1, 2):
            saved.append(os.dup(fd))
    except OSError:  # no such descriptor (an embedding without stdout): capture at the Python level only
        for fd in saved:
            os.close(fd)
        saved = None
    sink = tempfile.TemporaryFile() if saved is not None else None
    if sink is not None:
        os.dup2(sink.fileno(), 1)
        os.dup2(sink.fileno(), 2)
    sys.stdout = sys.stderr = py_sink
    try:
        yield captured
    finally:
        sys.stdout, sys.stderr = py_streams
        if sink is not None:
            try:
                ctypes.CDLL(None).fflush(None)  # C stdio may still hold the text
            except (OSError, TypeError, AttributeError):  # no C library handle (Windows): nothing to flush
                pass
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            captured.append(sink.read().decode("utf-8", "replace"))
            sink.close()
        captured.append(py_sink.getvalue())


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an OpenEXR file as float32: (H, W, 3) for RGB(A) files, (H, W) for single-channel files."""
    import sys

    path = str(path)
    with _native_output_captured() as native:
        try:
            arr, error = _read_exr(path), None
        except MatcapError as exc:
            arr, error = None, exc
    if error is None:
        if "".join(native).strip():  # never hide what a successful read printed
            sys.stderr.write("".join(native))
        return arr
    # a broken file: the OpenEXR core's own line says more than the Python exception ("file has 0 parts")
    lines = [ln.strip() for ln in "".join(native).splitlines() if ln.strip()]
    detail = next((ln for ln in lines if "EXR_ERR" in ln), None)
    if detail is not None:
        detail = detail.split(": ", 1)[1] if detail.startswith(path + ": ") else detail
        detail = re.sub(r"^\((EXR_ERR_\w+)\)\s*", r"\1: ", detail)
        raise MatcapError(f"{path}: cannot read EXR, the file is corrupt or truncated ({detail})") from None
    raise error


def _read_exr(path: str) -> np.ndarray:
    import OpenEXR

    try:
        with OpenEXR.File(path) as f:
            channels = f.channels()
            if "RGB" in channels or "RGBA" in channels:
                arr = channels.get("RGB", channels.get("RGBA")).pixels
                arr = np.asarray(arr, dtype=np.float32)[:, :, :3]
            elif all(c in channels for c in "RGB"):
                arr = np.stack([np.asarray(channels[c].pixels, np.float32) for c in "RGB"], axis=2)
            elif "Y" in channels:
                arr = np.asarray(channels["Y"].pixels, np.float32)
            elif len(channels) == 1:
                arr = np.asarray(next(iter(channels.values())).pixels, np.float32)
                if arr.ndim == 3 and arr.shape[2] == 1:
                    arr = arr[:, :, 0]
            else:
                raise MatcapError(f"{path}: EXR channels {sorted(channels)} are not RGB or Y")
    except MatcapError:
        raise
    except Exception as exc:  # OpenEXR raises plain Exceptions for broken files
        raise MatcapError(f"{path}: cannot read EXR ({exc})") from None
    return np.ascontiguousarray(arr)


def read_image(path: str | os.PathLike) -> StoredImage:
    """Read an image file as stored (no colour conversion). Raises :class:`MatcapError` if unreadable."""
    path = str(path)
    suffix = Path(path).suffix.lower()
    if not os.path.isfile(path):
        raise MatcapError(f"{path}: no such file")
    if suffix == ".exr":
        arr = read_exr(path)
    else:
        cv2 = _cv2()
        if suffix == ".hdr":
            flags = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR
        elif suffix in (".jpg", ".jpeg"):
            flags = cv2.IMREAD_COLOR  # applies the EXIF orientation of phone photos (IMREAD_UNCHANGED would not)
        else:
            flags = cv2.IMREAD_UNCHANGED  # keeps 16 bits and alpha
        arr = cv2.imread(path, flags)
        if arr is None:
            raise MatcapError(f"{path}: cannot read image (corrupt or unsupported format)")
        if arr.ndim == 3 and arr.shape[2] >= 3:
            order = [2, 1, 0] + ([3] if arr.shape[2] == 4 else [])
            arr = arr[:, :, order]
    if arr.dtype not in (np.uint8, np.uint16):
        arr = arr.astype(np.float32)
    return StoredImage(_to_rgb3(arr, path), path)


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(H, W) of an image file as :func:`read_image` would return it, read from the file's header without
    decoding the pixels (JPEGs: after their EXIF orientation). None when the header cannot be read here (the
    caller then decodes, and :func:`read_image` reports what is wrong)."""
    path = str(path)
    suffix = Path(path).suffix.lower()
    try:
        if suffix == ".exr":
            import OpenEXR

            with _native_output_captured():
                with OpenEXR.File(path, header_only=True) as f:
                    lo, hi = f.header()["dataWindow"]
            return int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1)
        if suffix == ".hdr":
            with open(path, "rb") as fh:
                for _ in range(64):  # header lines, a blank line, then the resolution line
                    line = fh.readline(256).strip()
                    parts = line.split()
                    if len(parts) == 4 and parts[0] in (b"-Y", b"+Y") and parts[2] in (b"+X", b"-X"):
                        return int(parts[1]), int(parts[3])
                    if len(parts) == 4 and parts[0] in (b"-X", b"+X") and parts[2] in (b"+Y", b"-Y"):
                        return int(parts[3]), int(parts[1])  # rotated layouts
            return None
        from PIL import Image

        limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # only the header is read here
        try:
            with Image.open(path) as im:
                w, h = im.size
                orientation = im.getexif().get(0x0112, 1) if suffix in (".jpg", ".jpeg") else 1
        finally:
            Image.MAX_IMAGE_PIXELS = limit
        return (w, h) if orientation in (5, 6, 7, 8) else (h, w)
    except Exception:  # unreadable header: decoding will say why
        return None


def check_same_size(sizes: list[tuple[str, tuple[int, int]]], what: str = "images") -> tuple[int, int]:
    """The common (H, W) of named images, or a one-line error that names the odd ones out against the size most of
    them share (so an odd first image is blamed, not the second)."""
    from collections import Counter

    counts = Counter(size for _, size in sizes)
    common, n = counts.most_common(1)[0]
    odd = [(name, size) for name, size in sizes if size != common]
    if odd:
        shown = ", ".join(f"{name} is {w}x{h}" for name, (h, w) in odd[:3]) + (", ..." if len(odd) > 3 else "")
        raise MatcapError(f"{shown} but {n} of the {len(sizes)} {what} are {common[1]}x{common[0]}; all {what} must "
                          "share one size")
    return common


def check_finite(arr: np.ndarray, path: str) -> None:
    """Raise a one-line error if a float image holds NaN or Inf."""
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=-1).sum()) if arr.ndim == 3 else int((~np.isfinite(arr)).sum())
        raise MatcapError(f"{path}: {bad} pixel(s) are NaN or Inf")


def _colour():
    import warnings

    with warnings.catch_warnings():  # colour-science warns that matplotlib is absent; we do not plot with it
        warnings.simplefilter("ignore")
        import colour
    return colour


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function, decoding (IEC 61966-2-1), via colour-science."""
    colour = _colour()
    return np.asarray(colour.cctf_decoding(np.clip(x, 0.0, 1.0), function="sRGB"), dtype=np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function, encoding (IEC 61966-2-1), via colour-science."""
    colour = _colour()
    return np.asarray(colour.cctf_encoding(np.clip(x, 0.0, 1.0), function="sRGB"), dtype=np.float32)


def check_contrast(contrast: float) -> float:
    """A tone-curve contrast (:func:`tone_curve`) as a float, or a one-line :class:`MatcapError`."""
    try:
        value = float(contrast)
    except (TypeError, ValueError):
        raise MatcapError(f"tone-curve contrast must be a number, got {contrast!r}") from None
    if not (1.0 <= value <= 4.0):
        raise MatcapError(f"tone-curve contrast must be between 1 (none) and 4, got {contrast}")
    return value


def tone_curve(x: np.ndarray, contrast: float) -> np.ndarray:
    """The S-shaped tone curve a camera lays over sRGB-encoded values (0, 0.5 and 1 stay put):
    ``x^c / (x^c + (1 - x)^c)`` on ``x`` in [0, 1]; ``contrast`` c = 1 is the identity, larger is steeper
    mid-tones, flatter shadows and highlights. Its inverse is the same curve with 1 / c."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    if contrast == 1.0:
        return x
    xc, yc = x ** contrast, (1.0 - x) ** contrast
    return xc / np.maximum(xc + yc, 1e-300)


def undo_tone_curve(y: np.ndarray, contrast: float) -> np.ndarray:
    """Inverse of :func:`tone_curve`: stored (encoded) values back to plain sRGB-encoded ones."""
    return tone_curve(y, 1.0 / contrast)


def decode_8bit_table(decode_srgb: bool = True, contrast: float = 1.0) -> np.ndarray:
    """(256,) float32: linear value of every 8-bit code; sRGB-decoded after undoing a tone curve of ``contrast``
    (1: plain sRGB), or taken as linear (``decode_srgb`` False)."""
    table = np.arange(256, dtype=np.float32) / np.float32(255.0)  # float32, as decoding every pixel would be
    if not decode_srgb:
        return table
    if contrast != 1.0:
        table = undo_tone_curve(table, contrast)
    return srgb_to_linear(table).astype(np.float32)


def to_linear_float(img: StoredImage, decode_srgb_8bit: bool = True, contrast: float = 1.0) -> tuple[np.ndarray, str]:
    """Convert a stored image to linear float32 (H, W, 3).

    8-bit images are taken as sRGB-encoded and decoded unless ``decode_srgb_8bit`` is False; a camera tone curve of
    ``contrast`` > 1 (:func:`tone_curve`) is undone first. 16-bit and float images are taken as linear. Returns the
    array and a word for what was done (``"srgb-decoded"``, ``"srgb-decoded, tone curve C undone"``,
    ``"linear"``).
    """
    arr = img.pixels
    if arr.dtype == np.uint8:
        # a 256-entry table: the same values as decoding every pixel, without float64 temporaries several times
        # the photo's size (a 12,000 x 9,000 photo: 1.3 GB float32 out, nothing more)
        if decode_srgb_8bit:
            how = "srgb-decoded" if contrast == 1.0 else f"srgb-decoded, tone curve {contrast:.2f} undone"
            return decode_8bit_table(True, contrast)[arr], how
        return decode_8bit_table(False)[arr], "linear"
    if arr.dtype == np.uint16:
        x = arr.astype(np.float32)
        x /= np.float32(65535.0)
        return x, "linear"
    check_finite(arr, img.path)
    return arr.astype(np.float32), "linear"


# ----------------------------------------------------------------------------------------------- writing


def quantize(x: np.ndarray, bits: int) -> np.ndarray:
    """Round [0, 1] floats to unsigned integers of ``bits`` (8 or 16) bits."""
    top = (1 << bits) - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    return np.round(np.clip(np.nan_to_num(x), 0.0, 1.0) * top).astype(dtype)


def write_png(path: str | os.PathLike, x: np.ndarray, bits: int = 16) -> None:
    """Write (H, W), (H, W, 3) or (H, W, 4) values in [0, 1] as an 8- or 16-bit PNG, atomically.

    The values are written as given: encode sRGB before calling if the file should be sRGB.
    """
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    q = quantize(np.asarray(x, dtype=np.float32), bits)
    if q.ndim == 3:
        q = q[:, :, [2, 1, 0, 3][: q.shape[2]]] if q.shape[2] in (3, 4) else q
    with atomic_path(path) as tmp:
        if not _cv2().imwrite(tmp, q):
            raise MatcapError(f"{path}: cannot write PNG")


def write_exr(path: str | os.PathLike, x: np.ndarray, half: bool = False) -> None:
    """Write float (H, W) or (H, W, 3) data as OpenEXR (ZIP compression), atomically."""
    import OpenEXR

    arr = np.ascontiguousarray(np.asarray(x, dtype=np.float16 if half else np.float32))
    if arr.ndim == 2:
        channels = {"Y": arr}
    elif arr.ndim == 3 and arr.shape[2] == 3:
        channels = {"RGB": arr}
    else:
        raise ValueError(f"write_exr expects (H, W) or (H, W, 3), got {arr.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)
