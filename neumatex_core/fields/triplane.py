"""The feature triplane (docs/architecture.md section 5): three axis-aligned feature planes over the cube [-1, 1]^3.

A point p = (x, y, z) reads one bilinearly interpolated C-vector from each plane and the three are concatenated:

    features(p) = [XY(x, y), YZ(y, z), XZ(x, z)]   -> [3C]

Plane k is stored as planes[k] [C, R, R]; its first coordinate indexes the columns (width), the second the rows
(height), as in `torch.nn.functional.grid_sample` (align_corners=False: coordinate -1 is the outer edge of the
first texel; points outside the cube read the border texels). Objects are normalised into the unit sphere, so
every surface point lies inside the cube. Gradients flow to `planes` (the LMRM predicts them, TTO optimises them).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

PLANE_AXES = ((0, 1), (1, 2), (0, 2))  # XY, YZ, XZ: which coordinates of p address plane k (width, height)
_PLANE_COORDS = [a for axes in PLANE_AXES for a in axes]  # PLANE_AXES flattened, for one gather


class Triplane(nn.Module):
    """Learnable planes [3, C, R, R]. `features(points [N, 3]) -> [N, 3C]` (see the module docstring)."""

    def __init__(self, channels: int = 16, resolution: int = 64, init_std: float = 0.1,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        planes = torch.randn(3, channels, resolution, resolution, generator=generator) * init_std
        self.planes = nn.Parameter(planes)

    @classmethod
    def from_planes(cls, planes: torch.Tensor) -> Triplane:
        """A triplane holding a copy of `planes` [3, C, R, R] (e.g. an LMRM prediction or a loaded asset)."""
        if planes.dim() != 4 or planes.shape[0] != 3 or planes.shape[2] != planes.shape[3]:
            raise ValueError(f"triplane planes must be [3, C, R, R], got {tuple(planes.shape)}")
        tp = cls(int(planes.shape[1]), int(planes.shape[2]), init_std=0.0)
        with torch.no_grad():
            tp.planes.copy_(planes.to(tp.planes.dtype))
        return tp.to(planes.device)

    @property
    def channels(self) -> int:
        return int(self.planes.shape[1])

    @property
    def resolution(self) -> int:
        return int(self.planes.shape[2])

    @property
    def feature_dim(self) -> int:
        """3C: the width of `features`."""
        return 3 * self.channels

    def features(self, points: torch.Tensor) -> torch.Tensor:
        """Bilinear features [N, 3C] at world points [N, 3] (in [-1, 1]^3; outside reads the border)."""
        if points.dim() != 2 or points.shape[-1] != 3:
            raise ValueError(f"points must be [N, 3], got {tuple(points.shape)}")
        p = points.to(self.planes.dtype)
        # one gather of the six coordinates, not three indexings and a stack: a seventh of the time, the same grid
        coords = p.index_select(1, torch.tensor(_PLANE_COORDS, device=p.device))  # [N, 6]
        grid = coords.reshape(-1, 3, 2).transpose(0, 1).contiguous().unsqueeze(1)  # [3, 1, N, 2]
        out = F.grid_sample(self.planes, grid, mode="bilinear", padding_mode="border", align_corners=False)
        return out[:, :, 0, :].permute(2, 0, 1).reshape(points.shape[0], -1)  # [3, C, N] -> [N, 3C]

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.features(points)


def coarse_projection(maps: torch.Tensor, factor: int) -> torch.Tensor:
    """U U^T maps for feature maps [..., C, H, W], U the bilinear upsampling from a grid `factor` times coarser
    (at least 1 x 1): the part of a gradient that moves texels in smooth blocks of about factor x factor, a positive
    semi-definite preconditioner (a descent direction stays one). A gradient constant over a block comes back about
    factor^2 times larger, one that alternates from texel to texel about cancels."""
    h, w = maps.shape[-2:]
    grid = maps.reshape(-1, *maps.shape[-3:])  # [N, C, H, W]
    coarse = torch.zeros(*grid.shape[:2], max(1, round(h / factor)), max(1, round(w / factor)),
                         dtype=maps.dtype, device=maps.device, requires_grad=True)  # fmt: skip
    with torch.enable_grad():
        up = F.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=False)
        (adjoint,) = torch.autograd.grad((up * grid.detach()).sum(), coarse)
    return F.interpolate(adjoint, size=(h, w), mode="bilinear", align_corners=False).reshape(maps.shape)


def neighbour_variation(planes: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between neighbouring texels of feature maps [..., H, W] (both axes), a scalar: zero
    for constant planes. TTO's smoothness term (TTOConfig.lambda_smooth) on a triplane's planes [3, C, R, R] or a
    texture moved to [C, H, W]."""
    dx = planes[..., :, 1:] - planes[..., :, :-1]
    dy = planes[..., 1:, :] - planes[..., :-1, :]
    return 0.5 * (dx.square().mean() + dy.square().mean())
