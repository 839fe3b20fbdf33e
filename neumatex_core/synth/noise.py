"""3D procedural noise for synthesis: Perlin gradient noise and fractal sums of it, vectorised in torch.

`PerlinNoise(seed)` is Ken Perlin's improved noise (2002): a seeded permutation of 256 lattice hashes, the 12
cube-edge gradients, quintic fade. `noise(p)` takes points [N, 3] (any device) and returns [N] values in about
[-1, 1], zero at lattice points; `fbm(p, octaves)` sums octaves of doubling frequency and halving amplitude,
normalised by the total amplitude. Everything is elementwise float32 arithmetic and integer gathers, so a seed
gives the same values on every run (shapes displace vertices with it, materials place regions and colours).
"""

from __future__ import annotations

import numpy as np
import torch

_GRADIENTS = torch.tensor(
    [[1, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0], [1, 0, 1], [-1, 0, 1], [1, 0, -1], [-1, 0, -1],
     [0, 1, 1], [0, -1, 1], [0, 1, -1], [0, -1, -1], [1, 1, 0], [-1, 1, 0], [0, -1, 1], [0, -1, -1]],
    dtype=torch.float32,
)  # fmt: skip
_CORNERS = [(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]


class PerlinNoise:
    """Seeded 3D gradient noise; `offset` shifts the lattice so that different seeds are not zero at the same
    points."""

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5E1D]))
        perm = rng.permutation(256)
        self.perm = torch.from_numpy(np.concatenate([perm, perm]).astype(np.int64))
        self.offset = torch.from_numpy(rng.uniform(0.0, 64.0, 3).astype(np.float32))

    def noise(self, points: torch.Tensor) -> torch.Tensor:
        """[N] noise values (about [-1, 1]) at points [N, 3]."""
        device = points.device
        perm, grads = self.perm.to(device), _GRADIENTS.to(device)
        p = points.float() + self.offset.to(device)
        cell = torch.floor(p)
        f = p - cell
        i = cell.long() & 255
        fade = f * f * f * (f * (f * 6 - 15) + 10)
        values = []
        for dx, dy, dz in _CORNERS:
            h = perm[perm[perm[i[:, 0] + dx] + i[:, 1] + dy] + i[:, 2] + dz] & 15
            d = f - torch.tensor([dx, dy, dz], dtype=torch.float32, device=device)
            values.append((grads[h] * d).sum(-1))
        u, v, w = fade[:, 0], fade[:, 1], fade[:, 2]

        def lerp(a: torch.Tensor, b: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            return a + t * (b - a)

        # _CORNERS order: index = 4 dx + 2 dy + dz
        x00 = lerp(values[0], values[4], u)
        x01 = lerp(values[1], values[5], u)
        x10 = lerp(values[2], values[6], u)
        x11 = lerp(values[3], values[7], u)
        return lerp(lerp(x00, x10, v), lerp(x01, x11, v), w)

    def fbm(self, points: torch.Tensor, octaves: int = 4, lacunarity: float = 2.0, gain: float = 0.5) -> torch.Tensor:
        """[N] fractal sum of `octaves` noise octaves at points [N, 3], divided by the total amplitude."""
        total = torch.zeros(points.shape[0], device=points.device)
        amplitude, frequency, norm = 1.0, 1.0, 0.0
        for _ in range(octaves):
            total = total + amplitude * self.noise(points * frequency)
            norm += amplitude
            amplitude *= gain
            frequency *= lacunarity
        return total / norm


def fbm_numpy(seed: int, points: np.ndarray, octaves: int = 4) -> np.ndarray:
    """float32 [N] `PerlinNoise(seed).fbm` at numpy points [N, 3] (for mesh displacement)."""
    with torch.no_grad():
        out = PerlinNoise(seed).fbm(torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)), octaves)
    return out.numpy()
