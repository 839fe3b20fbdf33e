"""Image metrics. PSNR is taken over covered (foreground) pixels only, on display values in [0, 1]
(docs/architecture.md section 2): render PSNR after the capture's tonemap, PSNR_BaseColor on rho_d, PSNR_Latents
on (l+1)/2.
"""

from __future__ import annotations

import math

import torch


def masked_mse(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Mean squared difference of images a, b [H, W, C] over pixels where mask [H, W] (bool) is set (all if None)."""
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    diff = (a.double() - b.double()) ** 2
    if mask is not None:
        if not bool(mask.any()):
            raise ValueError("mask covers no pixel")
        diff = diff[mask]
    return float(diff.mean())


def psnr_of_mse(mse: float, peak: float = 1.0) -> float:
    """PSNR in dB of a mean squared error; inf for none."""
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None, peak: float = 1.0) -> float:
    """PSNR in dB of a against b [H, W, C] over the masked pixels; inf for identical images."""
    return psnr_of_mse(masked_mse(a, b, mask), peak)
