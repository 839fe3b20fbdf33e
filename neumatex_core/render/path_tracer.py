"""Unidirectional path tracer with next-event estimation from the environment map.

Per bounce: light sampling (the map's piecewise-constant distribution, with a shadow ray) and BSDF sampling,
combined by multiple importance sampling with the balance heuristic; the BSDF-sampled direction continues
the path, and when it escapes, the map's radiance is added with the complementary MIS weight. Russian
roulette after `rr_depth` bounces. Differentiable with respect to material parameters only: sampling and
pdfs are detached, BSDF values carry gradients (the "detached" estimator of Zeltner et al. 2021). Every
random number comes from the caller's torch.Generator, so a seed fixes the image.

Bounce counting: `max_bounces` is the number of surface interactions on a path; 1 is direct lighting only
(Mitsuba's max_depth = max_bounces + 1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch

from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.raycast import Hits
from neumatex_core.geometry.surface import surface_interaction
from neumatex_core.render.scene import Scene


@dataclass(frozen=True)
class PathTracerConfig:
    """max_bounces: surface interactions per path (1 = direct only). rr_depth: bounces before Russian
    roulette starts. spp: samples per pixel. hide_background: camera rays that miss return black.
    chunk_rays: rays traced at once (bounds memory). strategy: how emitted light is gathered: "mis" (light and
    BSDF sampling, balance heuristic), "light" (next-event estimation only: with the same seed, two materials on
    the same geometry see the same light samples, so their images' noise is correlated; used to compare
    materials), "bsdf" (escaping BSDF-sampled rays only)."""

    max_bounces: int = 3
    rr_depth: int = 3
    spp: int = 16
    hide_background: bool = False
    chunk_rays: int = 1 << 18
    strategy: Literal["mis", "light", "bsdf"] = "mis"


def latin_hypercube(n: int, strata: int, dims: int, generator: torch.Generator) -> torch.Tensor:
    """[n, dims] numbers in [0, 1) on the generator's device: in each run of `strata` consecutive rows, each column
    is a random permutation of the strata's cells [k / strata, (k + 1) / strata), jittered within its cell, the
    columns permuted independently (Latin-hypercube sampling). Each row alone is uniform on [0, 1)^dims."""
    if n % strata:
        raise ValueError(f"Latin-hypercube runs of {strata} rows need a multiple of {strata} rows, got {n}")
    runs = n // strata
    device = generator.device
    # each run's column k: a permutation of the cells 0..strata-1, [runs, strata, dims]
    cells = torch.rand(runs, dims, strata, generator=generator, device=device).argsort(-1).transpose(1, 2)
    jitter = torch.rand(runs, strata, dims, generator=generator, device=device)
    return ((cells + jitter) / strata).reshape(n, dims)


def balance_heuristic(pdf_a: torch.Tensor, pdf_b: torch.Tensor) -> torch.Tensor:
    """MIS weight [N] of technique a: pdf_a / (pdf_a + pdf_b) (0 where both are 0)."""
    total = pdf_a + pdf_b
    return torch.where(total > 0, pdf_a / total.clamp_min(1e-30), torch.zeros_like(total))


class PathTracer:
    """Renders images or ray batches of a Scene. See the module docstring for the estimator."""

    def __init__(self, config: PathTracerConfig | None = None) -> None:
        self.config = config or PathTracerConfig()
        self.mis_weight: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] = balance_heuristic
        self.light_weight, self.bsdf_weight = {"mis": (None, None), "light": (1.0, 0.0), "bsdf": (0.0, 1.0)}[
            self.config.strategy]

    def render(
        self,
        scene: Scene,
        camera: Camera,
        seed: int = 0,
        spp: int | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> torch.Tensor:
        """Linear HDR image [H, W, 3] of `camera`, `spp` (default config.spp) jittered samples per pixel.

        Not differentiable across chunks' memory limits: use `render_rays` under autograd for inverse rendering.
        """
        spp = spp or self.config.spp
        device = scene.device
        gen = torch.Generator(device=device).manual_seed(seed)
        o, d, pix = camera.generate_rays(spp=spp, generator=gen, device=device)
        n_pix = camera.width * camera.height
        image = torch.zeros(n_pix, 3, device=device)
        chunk = max(spp, (self.config.chunk_rays // spp) * spp)
        total = o.shape[0]
        for start in range(0, total, chunk):
            sl = slice(start, min(start + chunk, total))
            radiance = self.render_rays(scene, o[sl], d[sl], gen)
            image = image.index_add(0, pix[sl], radiance)
            if progress is not None:
                progress(min(start + chunk, total), total)
        return (image / spp).reshape(camera.height, camera.width, 3)

    def render_rays(self, scene: Scene, origins: torch.Tensor, directions: torch.Tensor,
                    generator: torch.Generator, strata: int = 1) -> torch.Tensor:
        """Radiance [N, 3] along camera rays origins [N, 3], unit directions [N, 3] (one sample each). strata > 1:
        each run of `strata` consecutive rays (N a multiple of it; e.g. one pixel's samples, or half of them) takes
        Latin-hypercube random numbers for its first bounce's light and BSDF samples (`latin_hypercube`): each
        ray's numbers are uniform, so every ray's expectation is unchanged, and the run's mean is less noisy."""
        cfg = self.config
        first = latin_hypercube(origins.shape[0], strata, 5, generator) if strata > 1 else None
        device = origins.device
        n = origins.shape[0]
        radiance = torch.zeros(n, 3, device=device)
        throughput = torch.ones(n, 3, device=device)
        active = torch.arange(n, device=device)
        o, d = origins, directions
        prev_bsdf_pdf: torch.Tensor | None = None  # None: camera rays, whose escape is seen unweighted
        env = scene.envmap
        for depth in range(cfg.max_bounces + 1):
            if active.numel() == 0:
                break
            hits = scene.raycaster.intersect(o, d)
            miss = ~hits.valid
            if miss.any() and not (depth == 0 and cfg.hide_background):
                le = env.eval(d[miss])
                if prev_bsdf_pdf is None:
                    weight = torch.ones(le.shape[0], device=device)
                else:
                    weight = (self.mis_weight(prev_bsdf_pdf[miss], env.pdf(d[miss])) if self.bsdf_weight is None
                              else torch.full((le.shape[0],), self.bsdf_weight, device=device))
                radiance = radiance.index_add(0, active[miss], throughput[miss] * le * weight.unsqueeze(-1))
            if depth == cfg.max_bounces:
                break
            keep = hits.valid.nonzero().squeeze(-1)
            if keep.numel() == 0:
                break
            active, throughput, o, d = active[keep], throughput[keep], o[keep], d[keep]
            hits = Hits(hits.t[keep], hits.tri[keep], hits.bary[keep])
            si = surface_interaction(scene.mesh_tensors, hits, o, d)
            material = scene.material.at(si)
            wo = si.to_local(si.wo)
            rnd = torch.rand(keep.numel(), 6, generator=generator, device=device)
            if depth == 0 and first is not None:
                rnd[:, :5] = first[active]

            # Next-event estimation: a direction from the map, a shadow ray, MIS against BSDF sampling.
            light_dir, light_pdf, light_le = env.sample(rnd[:, 0:2])
            wi_l = si.to_local(light_dir)
            above = (wi_l[:, 2] > 0) & ((light_dir * si.geo_normal).sum(-1) > 0) & (light_pdf > 0)
            visible = above & ~scene.raycaster.occluded(si.spawn(light_dir), light_dir)
            f_l = material.eval(wi_l, wo) * wi_l[:, 2].clamp_min(0.0).unsqueeze(-1)
            w_l = (self.mis_weight(light_pdf, material.pdf(wi_l, wo)) if self.light_weight is None
                   else torch.full_like(light_pdf, self.light_weight))
            scale = torch.where(visible, w_l / light_pdf.clamp_min(1e-30), torch.zeros_like(w_l))
            radiance = radiance.index_add(0, active, throughput * f_l * light_le * scale.unsqueeze(-1))

            # BSDF sampling continues the path.
            wi, bsdf_pdf = material.sample(wo, rnd[:, 2], rnd[:, 3:5])
            wi_world = si.to_world(wi)
            ok = (bsdf_pdf > 0) & (wi[:, 2] > 0) & ((wi_world * si.geo_normal).sum(-1) > 0)
            f = material.eval(wi, wo) * wi[:, 2].clamp_min(0.0).unsqueeze(-1)
            throughput = throughput * torch.where(ok.unsqueeze(-1), f / bsdf_pdf.clamp_min(1e-30).unsqueeze(-1),
                                                  torch.zeros_like(f))
            if depth + 1 >= cfg.rr_depth:
                q = throughput.detach().amax(dim=-1).clamp(max=0.95)
                survive = rnd[:, 5] < q
                ok = ok & survive
                throughput = throughput / torch.where(survive, q, torch.ones_like(q)).unsqueeze(-1)
            keep = ok.nonzero().squeeze(-1)
            active, throughput = active[keep], throughput[keep]
            o, d = si.spawn(wi_world)[keep], wi_world[keep]
            prev_bsdf_pdf = bsdf_pdf[keep]
        return radiance
