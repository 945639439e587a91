"""Test-time augmentation (networks.inference.predict_views): transform bookkeeping and equivalences."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from networks.config import get_config
from networks.dihedral import DIHEDRAL, transform_images, transform_map, untransform_map
from networks.inference import predict, predict_views
from networks.model import SDMUniPS

torch.set_num_threads(1)


def _dome_predictor(images: torch.Tensor, mask: torch.Tensor, progress=None, **_) -> dict[str, np.ndarray]:
    """A geometry-equivariant stand-in for a network: the normals of a hemisphere on the mask's disk, in camera
    coordinates (x right, y up), plus a 'roughness' equal to the first image's red channel."""
    m = mask.numpy().astype(bool)
    rows, cols = np.nonzero(m)
    cy, cx = rows.mean(), cols.mean()
    r = np.sqrt(m.sum() / np.pi)
    yy, xx = np.mgrid[: m.shape[0], : m.shape[1]]
    nx, ny = (xx - cx) / r, -(yy - cy) / r
    nz = np.sqrt(np.clip(1 - nx**2 - ny**2, 0, None))
    n = np.stack([nx, ny, nz], -1)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True) * m[..., None]
    if progress is not None:
        progress(int(m.sum()), int(m.sum()))
    return {"normal": n.astype(np.float32), "roughness": images[0, 0].numpy().astype(np.float32)}


def _off_centre_disk(side=40):
    yy, xx = np.mgrid[:side, :side]
    return torch.from_numpy((xx - 14.0) ** 2 + (yy - 23.0) ** 2 < 9.0**2)


@pytest.mark.parametrize("views", [2, 4, 8])
def test_views_bring_every_transform_back_to_the_original_frame(views):
    mask = _off_centre_disk()
    images = torch.rand(3, 3, 40, 40, generator=torch.Generator().manual_seed(0))
    direct = _dome_predictor(images, mask)
    calls = []
    out = predict_views(_dome_predictor, images, mask, views=views, progress=lambda d, t: calls.append((d, t)))
    inside = mask.numpy()
    # every view, once undone, predicts the same dome: the average equals the direct prediction
    assert np.abs(out["normal"][inside] - direct["normal"][inside]).max() < 1e-5
    assert np.abs(out["roughness"] - direct["roughness"]).max() < 1e-6
    assert calls[-1] == (views * int(inside.sum()), views * int(inside.sum()))


def test_each_single_transform_is_undone_exactly():
    mask = _off_centre_disk()
    images = torch.zeros(2, 3, 40, 40)
    direct = _dome_predictor(images, mask)["normal"]
    for t in DIHEDRAL:
        res = _dome_predictor(transform_images(images, t), transform_images(mask, t))["normal"]
        back = untransform_map(res, t, normal=True)
        assert np.abs(back - direct).max() < 1e-5, t
        # the forward map transform (training augmentation) agrees with the geometry of the transformed scene
        assert np.abs(transform_map(direct, t, normal=True) - res).max() < 1e-5, t


def test_map_transform_round_trips_exactly():
    a = np.random.default_rng(0).normal(size=(5, 7, 3)).astype(np.float32)
    for t in DIHEDRAL:
        assert np.array_equal(untransform_map(transform_map(a, t, normal=True), t, normal=True), a), t
        assert np.array_equal(untransform_map(transform_map(a[..., 0], t), t), a[..., 0]), t


def test_one_view_is_plain_predict_and_bad_views_raise():
    torch.manual_seed(0)
    model = SDMUniPS(get_config("tiny", "brdf")).eval()
    g = torch.Generator().manual_seed(1)
    images = torch.rand(3, 3, 64, 64, generator=g)
    mask = torch.rand(64, 64, generator=g) > 0.3
    a = predict(model, images, mask)
    b = predict_views(lambda x, m, **kw: predict(model, x, m, **kw), images, mask, views=1)
    for k in a:
        assert np.array_equal(a[k], b[k])
    c = predict_views(lambda x, m, **kw: predict(model, x, m, **kw), images, mask, views=4)
    n = np.linalg.norm(c["normal"][mask.numpy()], axis=-1)
    assert np.allclose(n, 1.0, atol=1e-5)
    assert set(c) == set(a) and c["roughness"].shape == (64, 64)
    with pytest.raises(ValueError, match="views must be 1, 2, 4 or 8, got 3"):
        predict_views(predict, images, mask, views=3)
