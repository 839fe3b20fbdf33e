"""Surface interactions at ray hits and the local shading frame.

Two-sidedness (our documented choice; Mitsuba differs): both normals are flipped to the side the ray came
from, using the geometric normal. Where a smooth shading normal still faces away from the incoming ray
(low-poly silhouettes), we shade with the geometric normal instead of returning black as Mitsuba does;
comparisons against Mitsuba exclude those pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neumatex_core.geometry.raycast import Hits

RAY_EPSILON = 1e-4  # offset of spawned rays along the geometric normal (scene units; objects fit the unit sphere)


@dataclass
class SurfaceInteraction:
    """N ray hits.

    position [N, 3]; geo_normal [N, 3] unit, facing the incoming ray; shading_normal [N, 3] unit, on the same
    side; tri [N] int64 triangle id; bary [N, 2]; uv [N, 2] texture coordinates or None; wo [N, 3] unit
    direction back towards the ray origin (world space).
    """

    position: torch.Tensor
    geo_normal: torch.Tensor
    shading_normal: torch.Tensor
    tri: torch.Tensor
    bary: torch.Tensor
    uv: torch.Tensor | None
    wo: torch.Tensor

    def spawn(self, directions: torch.Tensor) -> torch.Tensor:
        """Origins [N, 3] for rays leaving the surface along `directions` without hitting it again."""
        side = torch.sign((directions * self.geo_normal).sum(-1, keepdim=True))
        side = torch.where(side == 0, torch.ones_like(side), side)
        return self.position + self.geo_normal * (RAY_EPSILON * side)

    def to_local(self, w: torch.Tensor) -> torch.Tensor:
        """World directions [N, 3] -> shading frame (+Z = shading normal)."""
        t, b = _tangent_frame(self.shading_normal)
        return torch.stack([(w * t).sum(-1), (w * b).sum(-1), (w * self.shading_normal).sum(-1)], dim=-1)

    def to_world(self, w: torch.Tensor) -> torch.Tensor:
        """Shading-frame directions [N, 3] -> world."""
        t, b = _tangent_frame(self.shading_normal)
        return w[:, 0:1] * t + w[:, 1:2] * b + w[:, 2:3] * self.shading_normal


def _tangent_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal tangents [N, 3] x2 of unit normals [N, 3] (Duff et al. 2017, branchless)."""
    sign = torch.where(n[:, 2] >= 0, torch.ones_like(n[:, 2]), -torch.ones_like(n[:, 2]))
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = torch.stack([1 + sign * n[:, 0] * n[:, 0] * a, sign * b, -sign * n[:, 0]], dim=-1)
    bt = torch.stack([b, sign + n[:, 1] * n[:, 1] * a, -n[:, 1]], dim=-1)
    return t, bt


def surface_interaction(
    mesh: dict[str, torch.Tensor], hits: Hits, origins: torch.Tensor, directions: torch.Tensor
) -> SurfaceInteraction:
    """Surface data at valid hits (call with hits/rays already restricted to hits: tri >= 0).

    mesh: tensors from `Mesh.torch()` (vertices, faces, face_normals, optional vertex_normals, uvs).
    """
    tri = hits.tri
    b1, b2 = hits.bary[:, 0:1], hits.bary[:, 1:2]
    b0 = 1 - b1 - b2
    face = mesh["faces"][tri]
    position = origins + hits.t.unsqueeze(-1) * directions
    ng = mesh["face_normals"][tri]
    wo = -directions
    flip = torch.where((ng * wo).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    ng = ng * flip
    if "vertex_normals" in mesh:
        vn = mesh["vertex_normals"]
        ns = b0 * vn[face[:, 0]] + b1 * vn[face[:, 1]] + b2 * vn[face[:, 2]]
        ns = ns / ns.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        ns = ns * flip
        facing_away = (ns * wo).sum(-1, keepdim=True) <= 0
        ns = torch.where(facing_away, ng, ns)
    else:
        ns = ng
    uv = None
    if "uvs" in mesh:
        tuv = mesh["uvs"]
        uv = b0 * tuv[face[:, 0]] + b1 * tuv[face[:, 1]] + b2 * tuv[face[:, 2]]
    return SurfaceInteraction(position, ng, ns, tri, hits.bary, uv, wo)
