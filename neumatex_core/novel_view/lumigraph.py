"""Preset views from arbitrary photographs on a known mesh: unstructured-lumigraph blending.

The LMRM reads the 23 preset views (docs/architecture.md section 7); a real capture has photos at other poses. For every
pixel of a preset view we find the surface point it sees (a G-buffer), project the point into every photo, keep
the photos that see it (in the frame, in front of the camera, inside the photo's mask when there is one, and not
occluded: a shadow ray from the point to the photo's centre), and blend the `k` photos whose viewing direction is
closest to the preset view's, weighted by the angular penalty of Buehler et al. (2001):
w_j = (1 - theta_j / theta_k)_+ / theta_j, normalised, where theta_k is the k-th smallest angle. A photo taken
from the preset pose itself therefore gets all the weight, so a capture of preset views comes out unchanged.

Inputs and outputs are linear radiance (photos are turned linear by the capture's tonemap inverse first).
Pixels that no photo sees are flagged in `observed` and left black; TTO never uses these synthesised views, it
fits the real photos.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.raycast import RayCaster
from neumatex_core.geometry.surface import RAY_EPSILON


@dataclass
class Photo:
    """A photo in linear radiance [H, W, 3] (float32), its camera, and an optional foreground mask [H, W]."""

    image: np.ndarray
    camera: Camera
    mask: np.ndarray | None = None


@dataclass
class PreparedViews:
    """images [V, R, R, 3] linear; mask [V, R, R] object coverage; observed [V, R, R] seen by some photo."""

    images: torch.Tensor
    mask: torch.Tensor
    observed: torch.Tensor
    cameras: list[Camera]


def _bilinear(image: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Sample image [H, W, C] at continuous pixel positions xy [N, 2] (pixel centres at +0.5), clamped edges."""
    h, w = image.shape[:2]
    x = (xy[:, 0] - 0.5).clamp(0, w - 1)
    y = (xy[:, 1] - 0.5).clamp(0, h - 1)
    x0, y0 = x.floor().long().clamp(max=w - 2 if w > 1 else 0), y.floor().long().clamp(max=h - 2 if h > 1 else 0)
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    fx, fy = (x - x0).unsqueeze(-1), (y - y0).unsqueeze(-1)
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def blend_views(mesh: Mesh, photos: Sequence[Photo], cameras: Sequence[Camera], k: int = 3,
                progress: Callable[[int, int], None] | None = None) -> PreparedViews:
    """Blend `photos` into the views of `cameras` (all in the mesh's frame); see the module docstring."""
    raycaster = RayCaster(mesh)
    images, masks, observed = [], [], []
    photo_t = [torch.as_tensor(np.ascontiguousarray(p.image[..., :3]), dtype=torch.float32) for p in photos]
    photo_m = [None if p.mask is None else torch.as_tensor(p.mask > 0.5) for p in photos]
    centres = torch.as_tensor(np.stack([p.camera.position for p in photos]), dtype=torch.float32)
    for v, cam in enumerate(cameras):
        gb = render_gbuffer(mesh, cam, raycaster)
        idx = gb.mask.reshape(-1).nonzero().squeeze(-1)
        points = gb.position.reshape(-1, 3)[idx]
        normals = gb.normal.reshape(-1, 3)[idx]
        to_view = torch.nn.functional.normalize(torch.as_tensor(cam.position, dtype=torch.float32) - points, dim=-1)
        m = points.shape[0]
        angles = torch.full((m, len(photos)), float("inf"))
        samples = torch.zeros(m, len(photos), 3)
        for j, photo in enumerate(photos):
            xy_np, front_np = photo.camera.project(points.numpy().astype(np.float64))
            xy = torch.as_tensor(xy_np, dtype=torch.float32)
            ok = torch.as_tensor(front_np) & (xy[:, 0] >= 0) & (xy[:, 1] >= 0)
            ok &= (xy[:, 0] < photo.camera.width) & (xy[:, 1] < photo.camera.height)
            to_photo = centres[j] - points
            dist = to_photo.norm(dim=-1)
            to_photo = to_photo / dist.clamp_min(1e-12).unsqueeze(-1)
            ok &= (to_photo * normals).sum(-1) > 0
            pm = photo_m[j]
            if pm is not None:
                px = xy[:, 0].long().clamp(0, photo.camera.width - 1)
                py = xy[:, 1].long().clamp(0, photo.camera.height - 1)
                ok &= pm[py, px]
            cand = ok.nonzero().squeeze(-1)
            if cand.numel():
                origins = points[cand] + normals[cand] * RAY_EPSILON * 10
                blocked = raycaster.occluded(origins, to_photo[cand], dist[cand] - 1e-3)
                cand = cand[~blocked]
            if cand.numel():
                cos = (to_photo[cand] * to_view[cand]).sum(-1).clamp(-1, 1)
                angles[cand, j] = torch.acos(cos)
                samples[cand, j] = _bilinear(photo_t[j], xy[cand])
        kk = min(k + 1, len(photos))  # the (k+1)-th angle is the threshold: k photos get weight
        best, order = torch.topk(angles, kk, dim=1, largest=False)
        seen = torch.isfinite(best[:, 0])
        theta_k = torch.where(torch.isfinite(best[:, -1]), best[:, -1], best.masked_fill(~torch.isfinite(best), 0)
                              .amax(1) * 1.0001 + 1e-6).unsqueeze(-1)  # fmt: skip
        weight = torch.where(torch.isfinite(best), (1 - best / theta_k).clamp_min(0) / best.clamp_min(1e-6),
                             torch.zeros_like(best))
        weight = torch.where(best <= 1e-6, torch.full_like(best, 1e9), weight)  # a photo from this very pose
        weight = weight / weight.sum(1, keepdim=True).clamp_min(1e-30)
        picked = torch.gather(samples, 1, order.unsqueeze(-1).expand(-1, -1, 3))
        color = (weight.unsqueeze(-1) * picked).sum(1)
        image = torch.zeros(cam.height * cam.width, 3)
        image[idx] = torch.where(seen.unsqueeze(-1), color, torch.zeros_like(color))
        seen_full = torch.zeros(cam.height * cam.width, dtype=torch.bool)
        seen_full[idx] = seen
        images.append(image.reshape(cam.height, cam.width, 3))
        masks.append(gb.mask)
        observed.append(seen_full.reshape(cam.height, cam.width))
        if progress is not None:
            progress(v + 1, len(cameras))
    return PreparedViews(torch.stack(images), torch.stack(masks), torch.stack(observed), list(cameras))
