"""Equirectangular HDR environment map: radiance lookup, importance sampling and its exact pdf.

Mapping (same as Mitsuba 3's `envmap` emitter, so renders can be compared pixel for pixel): a world
direction d (pointing away from the scene) is taken to the map's frame by the inverse of `to_world`, then
u = atan2(x, -z) / (2 pi) (wrapped to [0, 1)), v = acos(y) / pi. The lookup is bilinear with texel columns
at pixel centres (wrapping in u) and texel rows at v = j / (H - 1), exactly as Mitsuba places them.

Sampling is piecewise constant over an H x W grid of (u, v) bins, each with probability proportional to
the bin's luminance times sin(theta); inside a bin (u, v) is uniform, so the solid-angle pdf of a direction
is p_bin * W * H / (2 pi^2 sin(theta)). The pdf is exact for the sampler, which is all MIS needs.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from neumatex_core.imageio import ImageError, is_float_image, read_image

LUMINANCE = (0.2126, 0.7152, 0.0722)
# Negative values smaller than this fraction of the map's mean |radiance| are float noise of the map's authoring
# (the shared CC0 maps have them, down to -0.0022 against a mean of 0.8, i.e. 0.27%): they pass and are clamped
# to zero on load. Larger ones are errors. The one threshold of check_envmap_pixels and every loader.
NEGATIVE_NOISE_FRACTION = 1e-2
LDR_ENVMAP = ("is an 8- or 16-bit (display-encoded, low dynamic range) image; the environment map must be linear "
              "HDR with floating-point pixels: save it as EXR or Radiance HDR")  # fmt: skip


class EnvmapError(ValueError):
    """An environment map that cannot be used; the message names the file and the reason."""


def check_envmap_pixels(pixels: np.ndarray) -> list[str]:
    """Reasons a float [H, W, C] map cannot light a scene: not 2:1, NaN, infinite, negative beyond the noise
    tolerance (NEGATIVE_NOISE_FRACTION), all black."""
    h, w, c = pixels.shape
    out = []
    if c not in (1, 3, 4):
        out.append(f"environment map has {c} channels; expected 1, 3 (RGB) or 4 (RGBA)")
    if w != 2 * h:
        out.append(f"environment map is {w}x{h} pixels; an equirectangular map is exactly twice as wide as tall")
    rgb = pixels[:, :, : min(c, 3)]
    if np.isfinite(rgb).all():  # the common case in one pass over the map, without copies (it runs per upload)
        mean = float(np.abs(rgb).mean(dtype=np.float64))
        low, high = float(rgb.min()), float(rgb.max())
        if low < -NEGATIVE_NOISE_FRACTION * mean:
            n_neg = int((rgb < -NEGATIVE_NOISE_FRACTION * mean).any(axis=2).sum())
            out.append(f"{n_neg} pixels have negative values (down to {low:.3g}); radiance cannot be negative")
        if high <= 0.0:
            out.append("environment map is black everywhere: it would light nothing")
        return out
    rgb = rgb.astype(np.float64)
    finite = np.isfinite(rgb)
    n_nan = int(np.isnan(rgb).any(axis=2).sum())
    n_inf = int(np.isinf(rgb).any(axis=2).sum())
    if n_nan:
        out.append(f"{n_nan} pixels are NaN (not a number)")
    if n_inf:
        out.append(f"{n_inf} pixels are infinite")
    values = np.where(finite, rgb, 0.0)
    mean = float(np.abs(values[finite]).mean()) if finite.any() else 0.0
    n_neg = int((values < -NEGATIVE_NOISE_FRACTION * mean).any(axis=2).sum())
    if n_neg:
        out.append(f"{n_neg} pixels have negative values (down to {values.min():.3g}); radiance cannot be negative")
    if finite.any() and float(values.max()) <= 0.0:
        out.append("environment map is black everywhere: it would light nothing")
    return out


def read_envmap(path: str | Path) -> tuple[np.ndarray | None, list[str]]:
    """The map's pixels [H, W, C] and every reason it cannot light a scene: unreadable, not HDR (an 8- or 16-bit
    file is display-encoded, not linear radiance), then `check_envmap_pixels`. Pixels are None when unreadable.
    Reasons do not repeat the file's name."""
    try:
        if not is_float_image(path):
            return None, [LDR_ENVMAP]
        pixels = read_image(path)
    except ImageError as exc:
        return None, [str(exc).replace(f"{path}: ", "")]
    return pixels, check_envmap_pixels(pixels)


def load_envmap_radiance(path: str | Path) -> np.ndarray:
    """[H, W, 3] float32 linear radiance of a usable map, float-noise negatives clamped to 0; raises EnvmapError
    naming the file with every reason otherwise."""
    pixels, problems = read_envmap(path)
    if problems or pixels is None:
        raise EnvmapError(f"{path}: " + "; ".join(problems))
    return np.maximum(envmap_rgb(pixels), 0.0)


def envmap_rgb(pixels: np.ndarray) -> np.ndarray:
    """[H, W, 3] float32 RGB of a 1-, 3- or 4-channel map (grey repeated, alpha dropped)."""
    if pixels.shape[2] == 1:
        return np.repeat(pixels, 3, axis=2).astype(np.float32)
    return np.ascontiguousarray(pixels[:, :, :3], dtype=np.float32)


class EnvironmentMap:
    """An environment emitter.

    radiance: [H, W, 3] linear RGB (float32) texels. to_world: [3, 3] rotation from the map's frame to the
    world (Mitsuba's `to_world`). scale: radiance multiplier.
    """

    def __init__(
        self,
        radiance: torch.Tensor | np.ndarray,
        to_world: np.ndarray | None = None,
        scale: float = 1.0,
        device: torch.device | str = "cpu",
    ) -> None:
        data = torch.as_tensor(np.asarray(radiance, dtype=np.float32)[:, :, :3], device=device)
        self.device = torch.device(device)
        self.height, self.width = int(data.shape[0]), int(data.shape[1])
        # Float noise below zero (NEGATIVE_NOISE_FRACTION) is clamped; the map is otherwise used as given.
        self.texels = data.clamp_min(0.0) * float(scale)
        rot = np.eye(3) if to_world is None else np.asarray(to_world, dtype=np.float64)
        self.to_world = torch.as_tensor(rot, dtype=torch.float32, device=device)
        self._build_distribution()

    @classmethod
    def from_file(
        cls, path: str | Path, to_world: np.ndarray | None = None, scale: float = 1.0,
        device: torch.device | str = "cpu",
    ) -> EnvironmentMap:
        """Load an EXR/HDR equirectangular map; raises EnvmapError naming the file if it is unusable."""
        return cls(load_envmap_radiance(path), to_world, scale, device)

    @classmethod
    def constant(cls, radiance: tuple[float, float, float] = (1.0, 1.0, 1.0), device: torch.device | str = "cpu",
                 height: int = 8) -> EnvironmentMap:
        """A uniform white-furnace style map of the given radiance."""
        texels = np.broadcast_to(np.asarray(radiance, np.float32), (height, 2 * height, 3)).copy()
        return cls(texels, device=device)

    # -- mapping ---------------------------------------------------------------------------------------
    def direction_to_uv(self, directions: torch.Tensor) -> torch.Tensor:
        """World unit directions [N, 3] -> map coordinates [N, 2] (u in [0, 1), v in [0, 1])."""
        local = directions @ self.to_world  # inverse rotation = transpose
        u = torch.atan2(local[:, 0], -local[:, 2]) * (0.5 / math.pi)
        u = u - torch.floor(u)
        u = torch.where(u >= 1.0, u - 1.0, u)  # a u of -1e-9 (x = -0.0 on the seam) rounds to 1.0 in float32
        v = torch.acos(local[:, 1].clamp(-1.0, 1.0)) / math.pi
        return torch.stack([u, v], dim=-1)

    def uv_to_direction(self, uv: torch.Tensor) -> torch.Tensor:
        """Map coordinates [N, 2] -> world unit directions [N, 3]."""
        phi = 2 * math.pi * uv[:, 0]
        theta = math.pi * uv[:, 1]
        st = torch.sin(theta)
        local = torch.stack([st * torch.sin(phi), torch.cos(theta), -st * torch.cos(phi)], dim=-1)
        return local @ self.to_world.T

    def lookup_uv(self, uv: torch.Tensor) -> torch.Tensor:
        """Bilinear radiance [N, 3] at map coordinates [N, 2] (Mitsuba texel placement)."""
        h, w = self.height, self.width
        x = uv[:, 0] - 0.5 / w
        x = (x - torch.floor(x)) * w  # in [0, w): columns at pixel centres, wrapping
        y = uv[:, 1].clamp(0.0, 1.0) * (h - 1)  # rows at v = j / (h - 1)
        x0 = torch.clamp(x.floor().long(), 0, w - 1)
        y0 = torch.clamp(y.floor().long(), 0, h - 2)
        fx = (x - x0).unsqueeze(-1)
        fy = (y - y0).unsqueeze(-1)
        x1 = (x0 + 1) % w
        # gathers of rows of the flattened map: half the time of indexing texels[y, x] with two index tensors, and
        # the same values (docs/design-notes.md item 47)
        t = self.texels.reshape(h * w, 3)
        row0 = y0 * w
        row1 = row0 + w
        top = t.index_select(0, row0 + x0) * (1 - fx) + t.index_select(0, row0 + x1) * fx
        bottom = t.index_select(0, row1 + x0) * (1 - fx) + t.index_select(0, row1 + x1) * fx
        return top * (1 - fy) + bottom * fy

    def eval(self, directions: torch.Tensor) -> torch.Tensor:
        """Radiance [N, 3] arriving from world directions [N, 3] (the direction a ray leaves the scene)."""
        return self.lookup_uv(self.direction_to_uv(directions))

    # -- importance sampling ---------------------------------------------------------------------------
    def _build_distribution(self) -> None:
        h, w = self.height, self.width
        # Bin importance: mean luminance of the lookup at 2x2 points inside each bin, times sin(theta).
        lum_w = torch.tensor(LUMINANCE, device=self.device)
        acc = torch.zeros(h, w, device=self.device)
        jj, ii = torch.meshgrid(torch.arange(h, device=self.device), torch.arange(w, device=self.device),
                                indexing="ij")
        for du in (0.25, 0.75):
            for dv in (0.25, 0.75):
                uv = torch.stack([(ii + du) / w, (jj + dv) / h], dim=-1).reshape(-1, 2).float()
                acc += (self.lookup_uv(uv) @ lum_w).reshape(h, w)
        sin_theta = torch.sin(math.pi * (torch.arange(h, device=self.device) + 0.5) / h)
        weight = acc * 0.25 * sin_theta[:, None]
        total = float(weight.sum())
        if total <= 0:  # a black map: sample uniformly so pdfs stay defined
            weight = sin_theta[:, None].expand(h, w).clone()
            total = float(weight.sum())
        prob = (weight / total).double().reshape(-1)
        self._cdf = torch.cumsum(prob, 0)
        self._cdf = self._cdf / self._cdf[-1].clone()
        self.bin_prob = prob.reshape(h, w).float()

    def sample(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Draw directions from uniform numbers u [N, 2].

        Returns world directions [N, 3], their solid-angle pdf [N] and the radiance [N, 3] from them.
        """
        h, w = self.height, self.width
        u0 = u[:, 0].double().contiguous()
        # One search over the flattened H*W bins (row-major); the remainder of u0 inside the chosen bin,
        # rescaled to [0, 1), places the point along u, and u1 along v.
        k = torch.searchsorted(self._cdf, u0, right=True).clamp(0, h * w - 1)
        lo = torch.where(k > 0, self._cdf[(k - 1).clamp_min(0)], torch.zeros_like(u0))
        width = (self._cdf[k] - lo).clamp_min(1e-300)
        fu = ((u0 - lo) / width).clamp(0.0, 1.0 - 1e-7).float()
        row, col = k // w, k % w
        uv = torch.stack([(col.float() + fu) / w, (row.float() + u[:, 1].clamp(0.0, 1.0 - 1e-7)) / h], dim=-1)
        directions = self.uv_to_direction(uv)
        return directions, self._pdf_uv(uv), self.lookup_uv(uv)

    def _pdf_uv(self, uv: torch.Tensor) -> torch.Tensor:
        h, w = self.height, self.width
        col = torch.clamp((uv[:, 0] * w).long(), 0, w - 1)
        row = torch.clamp((uv[:, 1] * h).long(), 0, h - 1)
        sin_theta = torch.sin(math.pi * uv[:, 1])
        p = self.bin_prob.reshape(-1).index_select(0, row * w + col) * (w * h) / (2 * math.pi * math.pi)
        return torch.where(sin_theta > 1e-7, p / sin_theta.clamp_min(1e-7), torch.zeros_like(p))

    def pdf(self, directions: torch.Tensor) -> torch.Tensor:
        """Solid-angle pdf [N] with which `sample` draws world directions [N, 3]."""
        return self._pdf_uv(self.direction_to_uv(directions))

    def to(self, device: torch.device | str) -> EnvironmentMap:
        """This map on another device (texels already scaled and clamped)."""
        return EnvironmentMap(self.texels.cpu().numpy(), self.to_world.cpu().numpy(), 1.0, device)
