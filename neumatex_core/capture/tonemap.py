"""The capture's tonemap T: linear HDR radiance -> display values, as an LDR photo stores them.

T(x) = OETF(clip(exposure * x, 0, 1)), with OETF the piecewise sRGB transfer function (IEC 61966-2-1) or the
identity. Photometric losses and render PSNR are taken after T (docs/architecture.md section 2). The torch version is
differentiable: the clip is a clamp and the sRGB power law never sees a zero base, so gradients stay finite.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, TypeVar

import numpy as np
import torch

Transfer = Literal["srgb", "linear"]
ArrayT = TypeVar("ArrayT", torch.Tensor, np.ndarray)

SRGB_LINEAR_LIMIT = 0.0031308  # linear value where the sRGB curve switches from the line to the power law
SRGB_DISPLAY_LIMIT = 0.04045  # the same point in display values (12.92 * 0.0031308, rounded by the standard)
_POW_EPS = 1e-12  # smallest base handed to a fractional power (d/dx x^(1/2.4) is infinite at 0)


def srgb_oetf(x: torch.Tensor) -> torch.Tensor:
    """sRGB encoding of linear values in [0, 1] (any shape) -> display values in [0, 1]."""
    power = 1.055 * torch.clamp(x, min=_POW_EPS) ** (1.0 / 2.4) - 0.055
    return torch.where(x <= SRGB_LINEAR_LIMIT, 12.92 * x, power)


def srgb_eotf(y: torch.Tensor) -> torch.Tensor:
    """sRGB decoding of display values in [0, 1] (any shape) -> linear values in [0, 1]."""
    power = torch.clamp((y + 0.055) / 1.055, min=_POW_EPS) ** 2.4
    return torch.where(y <= SRGB_DISPLAY_LIMIT, y / 12.92, power)


def srgb_oetf_numpy(x: np.ndarray) -> np.ndarray:
    """numpy twin of `srgb_oetf` (same dtype as the input when floating point)."""
    x = np.asarray(x)
    power = 1.055 * np.power(np.maximum(x, _POW_EPS), 1.0 / 2.4) - 0.055
    return np.where(x <= SRGB_LINEAR_LIMIT, 12.92 * x, power).astype(_float_dtype(x), copy=False)


def srgb_eotf_numpy(y: np.ndarray) -> np.ndarray:
    """numpy twin of `srgb_eotf`."""
    y = np.asarray(y)
    power = np.power(np.maximum((y + 0.055) / 1.055, _POW_EPS), 2.4)
    return np.where(y <= SRGB_DISPLAY_LIMIT, y / 12.92, power).astype(_float_dtype(y), copy=False)


def _float_dtype(a: np.ndarray) -> np.dtype:
    return a.dtype if np.issubdtype(a.dtype, np.floating) else np.dtype(np.float32)


@dataclass(frozen=True)
class Tonemap:
    """Exposure scale (unitless multiplier on linear radiance, > 0) and display transfer function."""

    exposure: float = 1.0
    transfer: Transfer = "srgb"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"tonemap exposure must be a finite positive number, got {self.exposure}")
        if self.transfer not in ("srgb", "linear"):
            raise ValueError(f"tonemap transfer must be 'srgb' or 'linear', got {self.transfer!r}")

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Linear HDR radiance [..., 3] -> display values [..., 3] in [0, 1] (differentiable)."""
        y = torch.clamp(x * self.exposure, 0.0, 1.0)
        return srgb_oetf(y) if self.transfer == "srgb" else y

    def apply_numpy(self, x: np.ndarray) -> np.ndarray:
        """numpy twin of `apply`: linear HDR [..., 3] -> display [..., 3] in [0, 1]."""
        x = np.asarray(x)
        y = np.clip(x * self.exposure, 0.0, 1.0).astype(_float_dtype(x), copy=False)
        return srgb_oetf_numpy(y) if self.transfer == "srgb" else y

    def display_to_linear(self, y: ArrayT) -> ArrayT:
        """Inverse of `apply` on display values [..., 3] in [0, 1] (torch tensor or numpy array).

        Values are clipped to [0, 1] first; the result is linear radiance in [0, 1 / exposure]. Radiance that
        `apply` clipped (above 1 / exposure) cannot be recovered.
        """
        if isinstance(y, torch.Tensor):
            yt = torch.clamp(y, 0.0, 1.0)
            return (srgb_eotf(yt) if self.transfer == "srgb" else yt) / self.exposure
        yn = np.clip(np.asarray(y), 0.0, 1.0)
        lin = srgb_eotf_numpy(yn) if self.transfer == "srgb" else yn
        return (lin / self.exposure).astype(_float_dtype(yn), copy=False)
