"""Spatially varying ground-truth materials for synthetic objects.

An object's surface is split into 1..MAX_REGIONS regions, either by 3D noise (region = the argmax of one fractal
noise field per region at the surface point, plus a per-region bias that varies their areas) or by mesh parts (the
primitive of a union, or, for one-part meshes, the nearest of `n_regions` random face centroids: Voronoi cells on
the surface). Each region draws a family of the prior (`materials.prior.FAMILIES`), its 22 layered-material
parameters and two base colours; the Lambertian base colour rho_d at a point blends the two by a 3D procedural
pattern t in [0, 1] (fractal noise, or marble: a sine of one axis perturbed by noise).

The ground-truth neural material of a region is the basis encoder's latent of its parameters (docs/architecture.md
section 3); `ProceduralMaterialField` returns NeuralMaterial(basis, rho_d, latent) at surface points (what the synthetic
images show), or the analytic LayeredMaterial(params, rho_d) for the out-of-basis renders.

PBR G-buffer (for LMRM PBR pre-training): per region, the PBR material closest to the neural one is fitted by
`assets.pbr_fit.fit_targets` (the asset package's fallback fit: log-space cosine-weighted BSDF over fixed direction
pairs plus directional albedo) at PBR_LEVELS blends t = 0, 1/(L-1), ..., 1; a point's PBR parameters interpolate
linearly between the two levels around its t. The neural material is affine in rho_d and rho_d in t, so the
interpolation error is second order in the level spacing.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
import torch

from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.layered import PARAMETER_NAMES, LayeredMaterial
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial
from neumatex_core.materials.prior import FAMILIES, sample_base_color, sample_parameters
from neumatex_core.synth.noise import PerlinNoise

MAX_REGIONS = 4
PBR_LEVELS = 9
PBR_TARGET_COSINE = 6  # cosine directions per view of the PBR targets' fit (`pbr_lut`; pbr_fit.fit_directions)


@dataclass(frozen=True)
class RegionMaterial:
    """One region: family, normalised layered parameters (22, `PARAMETER_NAMES` order), base colours at t=0, 1."""

    family: str
    params: tuple[float, ...]
    color0: tuple[float, float, float]
    color1: tuple[float, float, float]


@dataclass(frozen=True)
class MaterialSpec:
    """mode: how regions are placed ("noise" or "parts"); seeds and frequencies of the region and colour noise;
    pattern: "fbm" or "marble"; contrast: gain of the colour pattern."""

    mode: str
    regions: tuple[RegionMaterial, ...]
    region_seed: int
    region_frequency: float
    color_seed: int
    color_frequency: float
    pattern: str
    contrast: float

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["regions"] = [{**asdict(r), "params": dict(zip(PARAMETER_NAMES, r.params, strict=True))}
                          for r in self.regions]  # fmt: skip
        return out


def sample_material_spec(rng: np.random.Generator) -> MaterialSpec:
    """A random MaterialSpec: 1..MAX_REGIONS regions (1 with probability 0.2), noise or parts placement."""
    n_regions = 1 if rng.uniform() < 0.2 else int(rng.integers(2, MAX_REGIONS + 1))
    g = torch.Generator().manual_seed(int(rng.integers(2**62)))
    regions = []
    for _ in range(n_regions):
        family = str(rng.choice(FAMILIES))
        params = sample_parameters(family, 1, g)[0]
        colors = sample_base_color(family, 2, g)
        regions.append(RegionMaterial(family, tuple(round(float(x), 6) for x in params),
                                      tuple(round(float(x), 6) for x in colors[0]),  # type: ignore[arg-type]
                                      tuple(round(float(x), 6) for x in colors[1])))  # type: ignore[arg-type]
    return MaterialSpec(
        mode="noise" if rng.uniform() < 0.6 else "parts",
        regions=tuple(regions),
        region_seed=int(rng.integers(2**31)),
        region_frequency=round(float(rng.uniform(0.8, 2.5)), 4),
        color_seed=int(rng.integers(2**31)),
        color_frequency=round(float(rng.uniform(1.5, 8.0)), 4),
        pattern="marble" if rng.uniform() < 0.3 else "fbm",
        contrast=round(float(rng.uniform(1.0, 3.0)), 4),
    )


def face_regions(spec: MaterialSpec, mesh: Mesh, parts: np.ndarray) -> np.ndarray | None:
    """[F] region per face for mode "parts" (None for "noise"): the part label modulo the region count when the
    mesh has several parts, else Voronoi cells of random face centroids."""
    n = len(spec.regions)
    if spec.mode != "parts" or n == 1:
        return None
    if len(np.unique(parts)) > 1:
        return (parts % n).astype(np.int64)
    rng = np.random.default_rng(np.random.SeedSequence([spec.region_seed, 0xFACE]))
    centroids = mesh.vertices[mesh.faces].mean(axis=1).astype(np.float64)
    seeds = centroids[rng.choice(len(centroids), size=n, replace=False)]
    d2 = ((centroids[:, None, :] - seeds[None, :, :]) ** 2).sum(-1)
    return d2.argmin(axis=1).astype(np.int64)


class ProceduralMaterialField(MaterialField):
    """The ground-truth material of one object (see the module docstring).

    kind "neural" (default) returns NeuralMaterial, "layered" the analytic LayeredMaterial. face_region: [F] region
    per face for mode "parts" (from `face_regions`), None for mode "noise".
    """

    def __init__(self, spec: MaterialSpec, basis: NeuralBasis, face_region: np.ndarray | None = None,
                 kind: Literal["neural", "layered"] = "neural", device: torch.device | str = "cpu") -> None:
        self.spec, self.basis, self.kind = spec, basis, kind
        self.device = torch.device(device)
        self.params = torch.tensor([r.params for r in spec.regions], dtype=torch.float32, device=self.device)
        self.color0 = torch.tensor([r.color0 for r in spec.regions], dtype=torch.float32, device=self.device)
        self.color1 = torch.tensor([r.color1 for r in spec.regions], dtype=torch.float32, device=self.device)
        with torch.no_grad():
            self.latents = basis.encode(self.params.to(next(basis.parameters()).device)).to(self.device)
        self.face_region = None if face_region is None else torch.from_numpy(face_region).to(self.device)
        n = len(spec.regions)
        self._region_noise = [PerlinNoise(spec.region_seed + k) for k in range(n)] if n > 1 else []
        self._region_bias = torch.linspace(-0.15, 0.15, n, device=self.device) if n > 1 else None
        self._color_noise = PerlinNoise(spec.color_seed)
        rng = np.random.default_rng(np.random.SeedSequence([spec.color_seed, 0xC0]))
        axis = rng.standard_normal(3)
        self._marble_axis = torch.tensor(axis / np.linalg.norm(axis), dtype=torch.float32, device=self.device)
        self._pbr_lut: torch.Tensor | None = None

    # -- where what is -------------------------------------------------------------------------------------
    def region(self, position: torch.Tensor, tri: torch.Tensor) -> torch.Tensor:
        """[N] int64 region of surface points position [N, 3] on triangles tri [N]."""
        n = len(self.spec.regions)
        if n == 1:
            return torch.zeros(position.shape[0], dtype=torch.int64, device=position.device)
        if self.face_region is not None:
            return self.face_region.to(position.device)[tri]
        p = position * self.spec.region_frequency
        assert self._region_bias is not None
        fields = torch.stack([nz.fbm(p, octaves=3) for nz in self._region_noise], dim=-1)
        return (fields + self._region_bias.to(position.device)).argmax(dim=-1)

    def blend(self, position: torch.Tensor) -> torch.Tensor:
        """[N] base-colour blend t in [0, 1] at points [N, 3]."""
        s = self.spec
        p = position * s.color_frequency
        if s.pattern == "marble":
            wave = torch.sin(p @ self._marble_axis.to(position.device) * 2.0 + 6.0 * self._color_noise.fbm(p / 2, 4))
            return (0.5 + 0.5 * wave).clamp(0.0, 1.0)
        return (0.5 + 0.5 * s.contrast * self._color_noise.fbm(p, 4)).clamp(0.0, 1.0)

    def base_color(self, region: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        c0, c1 = self.color0.to(t.device)[region], self.color1.to(t.device)[region]
        return c0 + t.unsqueeze(-1) * (c1 - c0)

    # -- MaterialField -------------------------------------------------------------------------------------
    def at(self, si: SurfaceInteraction) -> NeuralMaterial | LayeredMaterial:
        region = self.region(si.position, si.tri)
        rho = self.base_color(region, self.blend(si.position))
        if self.kind == "layered":
            return LayeredMaterial(self.params.to(rho.device)[region], rho)
        return NeuralMaterial(self.basis, rho, self.latents.to(rho.device)[region])

    # -- G-buffers -----------------------------------------------------------------------------------------
    def pbr_lut(self) -> torch.Tensor:
        """[R, PBR_LEVELS, 5] best-matching PBR (base colour, roughness, metallic) per region and blend level."""
        if self._pbr_lut is None:
            from neumatex_core.assets.pbr_fit import PBRFitConfig, fit_neural

            # The data's PBR targets keep the fit they were made with (6 cosine directions per view, Karis'
            # split-sum albedo), whatever the assets' fallback uses now (design note 101), so that data made
            # today matches data made before.
            cfg = PBRFitConfig(cosine_directions=PBR_TARGET_COSINE, albedo="split_sum")

            n = len(self.spec.regions)
            t = torch.linspace(0.0, 1.0, PBR_LEVELS, device=self.device)
            region = torch.arange(n, device=self.device).repeat_interleave(PBR_LEVELS)
            values = torch.cat([self.base_color(region, t.repeat(n)), self.latents[region]], dim=-1)
            params, _ = fit_neural(self.basis, values, cfg)
            self._pbr_lut = params.reshape(n, PBR_LEVELS, 5)
        return self._pbr_lut

    def gbuffer(self, position: torch.Tensor, tri: torch.Tensor) -> dict[str, torch.Tensor]:
        """Ground truth at surface points [N, 3] on triangles [N]: base_color [N, 3], latent [N, 6], params
        [N, 22], pbr [N, 5] (base colour, roughness, metallic), region [N]."""
        with torch.no_grad():
            region = self.region(position, tri)
            t = self.blend(position)
            x = t * (PBR_LEVELS - 1)
            lo = x.floor().long().clamp(0, PBR_LEVELS - 2)
            w = (x - lo).unsqueeze(-1)
            lut = self.pbr_lut().to(position.device)
            pbr = lut[region, lo] * (1 - w) + lut[region, lo + 1] * w
            return {"base_color": self.base_color(region, t), "latent": self.latents.to(position.device)[region],
                    "params": self.params.to(position.device)[region], "pbr": pbr, "region": region}  # fmt: skip
