"""Input preparation shared by training and inference, so both see the same numbers."""
from __future__ import annotations

import torch


def normalize_images(images: torch.Tensor, mask: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Scale each image by the maximum, over mask pixels, of its per-pixel RGB mean (SDM-UniPS test-time rule).

    images: (..., N, 3, H, W) linear RGB; mask: (..., 1, H, W) or (..., H, W) in {0, 1}, shared by the N images.
    Returns images of the same shape. An image that is black inside the mask is left at 0.
    """
    if images.dim() < 4 or images.shape[-3] != 3:
        raise ValueError(f"images must be (..., N, 3, H, W), got {tuple(images.shape)}")
    if mask.dim() == images.dim() - 2:
        mask = mask.unsqueeze(-3)
    m = mask.unsqueeze(-4).to(images.dtype)  # (..., 1, 1, H, W)
    mean_rgb = images.mean(dim=-3, keepdim=True) * m  # (..., N, 1, H, W)
    peak = mean_rgb.amax(dim=(-2, -1), keepdim=True)  # (..., N, 1, 1, 1)
    return images / (peak + eps)
