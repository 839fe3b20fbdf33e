"""Pinhole cameras in the nerfstudio convention and the preset views.

Convention (docs/architecture.md section 2): OpenGL camera axes (+X right, +Y up, -Z forward), a 4x4 camera-to-world
matrix, intrinsics fl_x, fl_y, cx, cy in pixels for an image of w x h pixels; pixel (i, j) covers
[i, i+1] x [j, j+1] with j counted downwards from the top row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

PRESET_ORBIT_VIEWS = 17
PRESET_ELEVATION_DEG = 20.0
PRESET_DISTANCE = 3.2  # a unit-sphere object subtends asin(1/3.2) = 18.2 deg, inside the 20 deg half-fov
PRESET_FOV_DEG = 40.0


@dataclass(frozen=True)
class Camera:
    """One pinhole camera.

    c2w: [4, 4] float camera-to-world matrix (rotation columns are the camera's +X, +Y, +Z in world space).
    fl_x, fl_y, cx, cy: intrinsics in pixels. width, height: image size in pixels.
    """

    c2w: np.ndarray
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def position(self) -> np.ndarray:
        return np.asarray(self.c2w[:3, 3], dtype=np.float64)

    @property
    def fov_x_deg(self) -> float:
        return math.degrees(2 * math.atan(self.width / (2 * self.fl_x)))

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for an image of another size (intrinsics scaled)."""
        sx, sy = width / self.width, height / self.height
        return Camera(self.c2w, self.fl_x * sx, self.fl_y * sy, self.cx * sx, self.cy * sy, width, height)

    def normalized(self, centre: np.ndarray, scale: float) -> Camera:
        """The camera in a frame where world points p become (p - centre) * scale (see Mesh.normalized)."""
        c2w = np.array(self.c2w, dtype=np.float64)
        c2w[:3, 3] = (c2w[:3, 3] - np.asarray(centre, dtype=np.float64)) * scale
        return Camera(c2w, self.fl_x, self.fl_y, self.cx, self.cy, self.width, self.height)

    def generate_rays(
        self,
        spp: int = 1,
        generator: torch.Generator | None = None,
        device: torch.device | str = "cpu",
        jitter: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rays through every pixel, `spp` per pixel, uniformly jittered inside the pixel (box filter).

        Returns origins [P*spp, 3], unit directions [P*spp, 3] (world space, float32) and the pixel index
        [P*spp] (row-major, P = width*height) each ray belongs to; samples of one pixel are contiguous.
        """
        h, w = self.height, self.width
        jj, ii = torch.meshgrid(
            torch.arange(h, dtype=torch.float32, device=device),
            torch.arange(w, dtype=torch.float32, device=device),
            indexing="ij",
        )
        pix = torch.arange(h * w, device=device).repeat_interleave(spp)
        px = ii.reshape(-1).repeat_interleave(spp)
        py = jj.reshape(-1).repeat_interleave(spp)
        if jitter:
            offset = torch.rand((px.shape[0], 2), generator=generator, device=device)
        else:
            offset = torch.full((px.shape[0], 2), 0.5, device=device)
        return (*self.rays_for_pixels(px + offset[:, 0], py + offset[:, 1]), pix)

    def rays_for_pixels(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through continuous image positions x [N], y [N] (pixels, y downwards).

        Returns origins [N, 3] and unit directions [N, 3] in world space.
        """
        device = x.device
        d_cam = torch.stack([(x - self.cx) / self.fl_x, -(y - self.cy) / self.fl_y, -torch.ones_like(x)], dim=-1)
        rot = torch.as_tensor(np.asarray(self.c2w[:3, :3]), dtype=torch.float32, device=device)
        d = d_cam @ rot.T
        d = d / d.norm(dim=-1, keepdim=True)
        o = torch.as_tensor(self.position, dtype=torch.float32, device=device).expand_as(d)
        return o.contiguous(), d

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [N, 3] to pixel positions [N, 2]; also returns [N] bool "in front of camera"."""
        w2c = np.linalg.inv(np.asarray(self.c2w, dtype=np.float64))
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = -p[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        x = self.fl_x * p[:, 0] / zs + self.cx
        y = -self.fl_y * p[:, 1] / zs + self.cy
        return np.stack([x, y], axis=1), front


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """[4, 4] OpenGL camera-to-world matrix of a camera at `eye` looking at `target` (-Z forward)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


def camera_from_fov(c2w: np.ndarray, width: int, height: int, fov_x_deg: float) -> Camera:
    """A centred pinhole camera with square pixels and the given horizontal field of view."""
    fl = width / (2 * math.tan(math.radians(fov_x_deg) / 2))
    return Camera(np.asarray(c2w, dtype=np.float64), fl, fl, width / 2, height / 2, width, height)


def preset_views(
    resolution: int = 256,
    distance: float = PRESET_DISTANCE,
    fov_deg: float = PRESET_FOV_DEG,
) -> list[Camera]:
    """The 23 preset views: 17 evenly spaced on a 360-degree orbit at 20 degrees elevation, then the 6
    canonical views (+X, -X, +Y, -Y, +Z, -Z), all looking at the origin. Square images of `resolution`."""
    cams: list[Camera] = []
    el = math.radians(PRESET_ELEVATION_DEG)
    for k in range(PRESET_ORBIT_VIEWS):
        az = 2 * math.pi * k / PRESET_ORBIT_VIEWS
        eye = distance * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        cams.append(
            camera_from_fov(look_at(eye, np.zeros(3), np.array([0.0, 1.0, 0.0])), resolution, resolution, fov_deg)
        )
    for axis, up in (
        ([1, 0, 0], [0, 1, 0]),
        ([-1, 0, 0], [0, 1, 0]),
        ([0, 1, 0], [0, 0, -1]),
        ([0, -1, 0], [0, 0, 1]),
        ([0, 0, 1], [0, 1, 0]),
        ([0, 0, -1], [0, 1, 0]),
    ):
        eye = distance * np.asarray(axis, dtype=np.float64)
        cams.append(camera_from_fov(look_at(eye, np.zeros(3), np.asarray(up, float)), resolution, resolution, fov_deg))
    return cams
