"""Geometry G-buffers of a camera view: position, normal, coverage mask, triangle id."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.raycast import Hits, RayCaster
from neumatex_core.geometry.surface import surface_interaction


@dataclass
class GBuffer:
    """Per-pixel geometry at pixel centres of one view.

    position [H, W, 3] world (zero where uncovered); normal [H, W, 3] unit shading normal facing the camera;
    mask [H, W] bool coverage; triangle [H, W] int64 (-1 where uncovered); depth [H, W] ray distance (inf).
    """

    position: torch.Tensor
    normal: torch.Tensor
    mask: torch.Tensor
    triangle: torch.Tensor
    depth: torch.Tensor


def render_gbuffer(mesh: Mesh, camera: Camera, raycaster: RayCaster | None = None,
                   device: torch.device | str = "cpu") -> GBuffer:
    """Trace one ray through each pixel centre and record what it hits."""
    raycaster = raycaster or RayCaster(mesh)
    o, d, _ = camera.generate_rays(spp=1, device=device, jitter=False)
    hits = raycaster.intersect(o, d)
    h, w = camera.height, camera.width
    valid = hits.valid
    position = torch.zeros(h * w, 3, device=device)
    normal = torch.zeros(h * w, 3, device=device)
    if valid.any():
        idx = valid.nonzero().squeeze(-1)
        sub = Hits(hits.t[idx], hits.tri[idx], hits.bary[idx])
        si = surface_interaction(mesh.torch(device), sub, o[idx], d[idx])
        position[idx] = si.position
        normal[idx] = si.shading_normal
    return GBuffer(
        position.reshape(h, w, 3), normal.reshape(h, w, 3), valid.reshape(h, w),
        hits.tri.reshape(h, w), hits.t.reshape(h, w),
    )
