"""Baking a material field into UV textures: rasterise texels in UV space to surface points, evaluate, dilate.

Rasterisation is conservative: every texel whose centre lies within `margin` texels of a triangle in UV space gets
a surface point, the nearest point of the nearest such triangle (its centre's barycentrics, clamped onto the
triangle when the centre is outside). Texels inside a triangle win over border texels, nearer triangles over
farther ones. So the texels a bilinear lookup touches along a chart's boundary hold the field's values on that
chart's own edge, not a neighbour's, and seams stay invisible. Texels farther from every chart are filled by
dilation (the mean of already filled 8-neighbours, ring by ring), then with the mean of the texture; renders never
read them, but engines' mip maps do.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from neumatex_core.geometry.mesh import Mesh

RASTER_MARGIN = 1.5  # texels: more than the 1-texel reach of a bilinear lookup past a chart's edge
DILATE_RINGS = 8


@dataclass
class TexelSamples:
    """Surface points of the covered texels of a [resolution, resolution] UV layout.

    index [M] flat texel indices (row * resolution + col); points [M, 3] object-space positions; triangle [M];
    inside [M] bool (centre inside its triangle, else a clamped border texel)."""

    resolution: int
    index: np.ndarray
    points: np.ndarray
    triangle: np.ndarray
    inside: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """[R, R] bool: texels with a surface point."""
        m = np.zeros(self.resolution * self.resolution, dtype=bool)
        m[self.index] = True
        return m.reshape(self.resolution, self.resolution)


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2D points p [K, 2], triangles (a, b, c) [K, 2] -> (barycentrics [K, 3] of the closest point, distance [K])."""
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    ok = np.abs(den) > 1e-18
    safe = np.where(ok, den, 1.0)
    l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / safe
    l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / safe
    l0 = 1 - l1 - l2
    inside = ok & (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
    bary = np.stack([l0, l1, l2], axis=1)
    dist = np.zeros(p.shape[0])
    out = ~inside
    if out.any():
        best_d = np.full(p.shape[0], np.inf)
        best_b = np.zeros_like(bary)
        for i, j, s, e in ((0, 1, a, b), (1, 2, b, c), (2, 0, c, a)):  # edges as (start vertex, end vertex)
            d = e - s
            t = np.clip(((p - s) * d).sum(1) / np.maximum((d * d).sum(1), 1e-30), 0.0, 1.0)
            q = s + t[:, None] * d
            dist_e = np.linalg.norm(p - q, axis=1)
            better = dist_e < best_d
            best_d = np.where(better, dist_e, best_d)
            eb = np.zeros_like(bary)
            eb[:, i], eb[:, j] = 1 - t, t
            best_b = np.where(better[:, None], eb, best_b)
        bary = np.where(out[:, None], best_b, bary)
        dist = np.where(out, best_d, 0.0)
    return bary, dist


def rasterize_uv(mesh: Mesh, resolution: int, margin: float = RASTER_MARGIN, max_candidates: int = 1 << 22
                 ) -> TexelSamples:
    """Surface points for every texel within `margin` texels of a triangle (see the module docstring)."""
    if mesh.uvs is None:
        raise ValueError("baking needs a mesh with uvs (assets.uv_unwrap.unwrap)")
    r = int(resolution)
    tri_uv = mesh.uvs[mesh.faces].astype(np.float64)  # [F, 3, 2]
    px = np.stack([tri_uv[..., 0] * r - 0.5, (1 - tri_uv[..., 1]) * r - 0.5], axis=-1)  # texel centres at integers
    lo = np.clip(np.floor(px.min(axis=1) - margin), 0, r - 1).astype(np.int64)
    hi = np.clip(np.ceil(px.max(axis=1) + margin), 0, r - 1).astype(np.int64)
    n_xy = hi - lo + 1
    counts = n_xy[:, 0] * n_xy[:, 1]
    idx_parts, pts_parts, tri_parts, dist_parts, inside_parts = [], [], [], [], []
    # candidates (texel, triangle) in batches of whole triangles, bounded in memory
    starts = np.concatenate([[0], np.cumsum(counts)])
    f0 = 0
    n_faces = len(counts)
    while f0 < n_faces:
        f1 = int(np.searchsorted(starts, starts[f0] + max_candidates, side="right")) - 1
        f1 = min(max(f1, f0 + 1), n_faces)
        tri = np.repeat(np.arange(f0, f1), counts[f0:f1])
        local = np.arange(len(tri)) - np.repeat(starts[f0:f1] - starts[f0], counts[f0:f1])
        ix = lo[tri, 0] + local % n_xy[tri, 0]
        iy = lo[tri, 1] + local // n_xy[tri, 0]
        p = np.stack([ix, iy], axis=1).astype(np.float64)
        bary, dist = _closest_on_triangles(p, px[tri, 0], px[tri, 1], px[tri, 2])
        keep = dist <= margin
        tri, bary, dist = tri[keep], bary[keep], dist[keep]
        corners = mesh.vertices[mesh.faces[tri]].astype(np.float64)  # [K, 3, 3]
        idx_parts.append(iy[keep] * r + ix[keep])
        pts_parts.append((bary[:, :, None] * corners).sum(1))
        tri_parts.append(tri)
        dist_parts.append(dist)
        inside_parts.append(dist == 0)
        f0 = f1
    index = np.concatenate(idx_parts)
    dist = np.concatenate(dist_parts)
    order = np.lexsort((dist, index))  # per texel: nearest triangle first (stable: lowest triangle id on ties)
    index = index[order]
    first = np.ones(len(index), dtype=bool)
    first[1:] = index[1:] != index[:-1]
    sel = order[first]
    return TexelSamples(r, index[first], np.concatenate(pts_parts)[sel].astype(np.float32),
                        np.concatenate(tri_parts)[sel], np.concatenate(inside_parts)[sel])  # fmt: skip


def dilate(texture: torch.Tensor, mask: torch.Tensor, rings: int = DILATE_RINGS) -> torch.Tensor:
    """Fill texels outside mask [H, W] of texture [H, W, C]: `rings` rounds of the mean of filled 8-neighbours,
    then the mean of the filled texels."""
    tex = torch.where(mask.unsqueeze(-1), texture, torch.zeros_like(texture))
    filled = mask.clone()
    kernel = torch.ones(1, 1, 3, 3, dtype=tex.dtype, device=tex.device)
    for _ in range(rings):
        if bool(filled.all()):
            break
        w = filled.to(tex.dtype)[None, None]
        num = torch.nn.functional.conv2d((tex * filled.unsqueeze(-1)).permute(2, 0, 1).unsqueeze(1), kernel,
                                         padding=1)[:, 0].permute(1, 2, 0)  # fmt: skip
        den = torch.nn.functional.conv2d(w, kernel, padding=1)[0, 0]
        grow = (~filled) & (den > 0)
        tex = torch.where(grow.unsqueeze(-1), num / den.clamp_min(1).unsqueeze(-1), tex)
        filled = filled | grow
    if not bool(filled.all()) and bool(filled.any()):
        mean = tex[filled].mean(0)
        tex = torch.where(filled.unsqueeze(-1), tex, mean.expand_as(tex))
    return tex


def bake(samples: TexelSamples, fn: Callable[[torch.Tensor], torch.Tensor], channels: int,
         chunk: int = 1 << 16, device: torch.device | str = "cpu") -> torch.Tensor:
    """Texture [R, R, channels] of fn(points [n, 3]) -> [n, channels] at the texel samples, dilated."""
    r = samples.resolution
    points = torch.from_numpy(samples.points).to(device)
    values = []
    with torch.no_grad():
        for s in range(0, points.shape[0], chunk):
            values.append(fn(points[s:s + chunk]).float())
    flat = torch.zeros(r * r, channels, device=device)
    flat[torch.from_numpy(samples.index).to(device)] = torch.cat(values)
    mask = torch.from_numpy(samples.mask).to(device)
    return dilate(flat.reshape(r, r, channels), mask)
