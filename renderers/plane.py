"""The one flat-plane geometry + orthographic framing used to render material maps (pure dict builders).

World space = our camera space: x right, y up, z toward the camera. The plane lies in z = 0 and spans
x in [-1, 1], y in [-H/W, H/W]; the orthographic camera sits on +z looking down -z and frames exactly that
rectangle, so output pixel (row, col) sees map texel (row, col) when the film has the maps' size (other film
sizes resample the same framing). UV: u = column / W (left to right), v = row / H (top to bottom): a bitmap's
row 0 lands at the top of the image (the rectangle's own v runs bottom-up, hence ``PLANE_TO_UV``). The tangent
frame is dp/du = +x, dp/dv = +y, so OpenGL-convention (+Y) tangent-space normals equal our camera-space normals.

Reuse: ``plane_shape(width, height, bsdf)`` + ``ortho_sensor(width, height, spp)`` give a scene that shows
any Mitsuba BSDF dict exactly like the input photos (``renderers.relight`` builds its principled BSDF with them;
``matcap export`` can hand in a glTF material's textures the same way). Mitsuba is imported lazily.
"""
from __future__ import annotations

CAMERA_DISTANCE = 10.0  # orthographic: only needs to be in front of the plane


def plane_half_extent(width: int, height: int) -> tuple[float, float]:
    """World half-size (x, y) of the plane for a ``width`` x ``height`` image: (1, H/W)."""
    return 1.0, float(height) / float(width)


def plane_to_uv():
    """Texture transform for the rectangle so that bitmap row 0 is the top of the image."""
    import mitsuba as mi

    return mi.ScalarTransform4f().translate([0.0, 1.0, 0.0]) @ mi.ScalarTransform4f().scale([1.0, -1.0, 1.0])


def plane_shape(width: int, height: int, bsdf: dict) -> dict:
    """A ``rectangle`` in z = 0 facing +z, sized to frame a ``width`` x ``height`` image, carrying ``bsdf``."""
    import mitsuba as mi

    hx, hy = plane_half_extent(width, height)
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([hx, hy, 1.0]), "bsdf": bsdf}


def ortho_sensor(
    width: int, height: int, spp: int, *, seed: int = 0, rfilter: str = "box", sampler: str = "multijitter"
) -> dict:
    """Orthographic camera on +z looking down -z, up = +y, framing the plane of :func:`plane_shape` exactly.

    Mitsuba's orthographic view region is x in [-1, 1] and y in [-H/W, H/W] before ``to_world``, which is
    the plane's extent, so no extra scaling is needed. ``multijitter`` (stratified, jittered) sampling gives
    about half the noise of ``independent`` at the same cost (measured: docs/relight.md).
    """
    import mitsuba as mi

    return {
        "type": "orthographic",
        "to_world": mi.ScalarTransform4f().look_at(
            origin=[0.0, 0.0, CAMERA_DISTANCE], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0]
        ),
        "near_clip": 0.01,
        "far_clip": 10.0 * CAMERA_DISTANCE,
        "sampler": {"type": sampler, "sample_count": int(spp), "seed": int(seed)},
        "film": {
            "type": "hdrfilm",
            "width": int(width),
            "height": int(height),
            "pixel_format": "rgb",
            "rfilter": {"type": rfilter},
        },
    }
