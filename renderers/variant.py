"""Pick the Mitsuba variant once per process: ``llvm_ad_rgb`` where it works, else ``scalar_rgb``.

``llvm_ad_rgb`` needs libLLVM >= 17 (Debian: ``apt-get install libllvm19``); older LLVMs abort renders with
"Cannot select: fminimum". We probe it in a child process so an abort cannot take the caller down.
"""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import warnings

_PROBE = r"""
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"},
    "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4, "height": 4}},
    "shape": {"type": "rectangle"}, "light": {"type": "constant"}})
img = mi.render(scene, spp=1)
print(float(mi.TensorXf(img).numpy().mean()))
"""

_chosen: str | None = None
_llvm_ok: bool | None = None
VARIANTS = ("llvm_ad_rgb", "scalar_rgb")


def llvm_works() -> bool:
    """Whether ``llvm_ad_rgb`` renders in this environment (probed once per process, in a child process)."""
    global _llvm_ok
    if _llvm_ok is None:
        try:
            _llvm_ok = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, timeout=120).returncode == 0
        except (subprocess.TimeoutExpired, OSError):
            _llvm_ok = False
    return _llvm_ok


def choose_variant(prefer: str | None = None, quiet: bool = False) -> str:
    """Set and return the Mitsuba variant. ``prefer`` or the environment variable ``MATCAP_MITSUBA_VARIANT``
    (``llvm_ad_rgb`` or ``scalar_rgb``) force one; otherwise ``llvm_ad_rgb`` where it works, else ``scalar_rgb``."""
    global _chosen
    import mitsuba as mi

    if _chosen is not None:
        return _chosen
    forced = prefer or os.environ.get("MATCAP_MITSUBA_VARIANT")
    if forced:
        if forced not in mi.variants():
            raise ValueError(f"MATCAP_MITSUBA_VARIANT={forced!r} is not a Mitsuba variant here "
                             f"(available: {', '.join(mi.variants())})")
        mi.set_variant(forced)
        _chosen = forced
        return forced
    ok = llvm_works()
    _chosen = "llvm_ad_rgb" if ok else "scalar_rgb"
    if not ok and not quiet:
        warnings.warn(
            "Mitsuba's llvm_ad_rgb variant does not work here (needs libLLVM >= 17, e.g. `apt-get install libllvm19`); "
            "rendering with the slower scalar_rgb variant.",
            stacklevel=2,
        )
    mi.set_variant(_chosen)
    return _chosen


@contextlib.contextmanager
def one_thread():
    """Dr.Jit (and so Mitsuba) on one thread inside the block, its thread count restored after. With several, an
    llvm variant's film adds up a pixel's samples in the order the threads happen to finish, so the same render
    differs in its last bits from run to run on a busy machine; on one thread it is the same every time."""
    import drjit as dr

    was = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(was)


def interrupted_by(exc: BaseException) -> bool:
    """Whether a ``KeyboardInterrupt`` is among ``exc`` and the exceptions it was raised from (``__cause__`` /
    ``__context__``): Dr.Jit reports an interrupt inside its custom operations (``mi.render``) as RuntimeError."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False


def render_array(scene, integrator=None, *, spp: int, seed: int = 0, sensor=None):
    """``mi.render`` evaluated into a float32 numpy array (H, W, C); Ctrl-C raises ``KeyboardInterrupt``.

    During a render Mitsuba takes SIGINT itself: it cancels the integrator, logs "winding down" and returns a
    partially rendered image, and Python never sees the interrupt. A partial image must not be used (or saved as
    training data), so when the integrator reports that it was cancelled this raises ``KeyboardInterrupt``.
    ``sensor``: render through this sensor instead of the scene's own.
    """
    import mitsuba as mi
    import numpy as np

    integrator = integrator if integrator is not None else scene.integrator()
    try:
        kwargs = {} if sensor is None else {"sensor": sensor}
        image = np.array(mi.render(scene, integrator=integrator, spp=int(spp), seed=int(seed), **kwargs),
                         dtype=np.float32)
    except RuntimeError as exc:
        if interrupted_by(exc):  # a signal handler raised while Dr.Jit ran Python code: Dr.Jit wraps the interrupt
            raise KeyboardInterrupt("rendering interrupted") from exc
        raise
    if integrator.should_stop():
        raise KeyboardInterrupt("rendering interrupted")
    return image
