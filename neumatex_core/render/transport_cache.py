"""Cached light transport: the radiance of fixed camera rays as a function of the material at their first hit.

During TTO the geometry and the lighting are fixed and only the material changes (docs/design-notes.md, "cached
light transport"). So the expensive part of a path-traced estimate, the ray queries and the incident radiance,
is computed once per cache and each optimiser step only re-evaluates the material:

    cache = TransportCache.build(scene, origins, directions, generator, TransportCacheConfig(directions=32))
    radiance = cache.radiance(field)            # [N, 3] linear RGB, differentiable in the field's parameters

For every camera ray that hits the object, `directions` incident directions wi_k are drawn once from a mixture
that does not depend on the material being optimised: the environment map's importance sampling (share
`light_share`), the build-time material's own BSDF sampling (`bsdf_share`; frozen into the cache) and a cosine
lobe (the rest, so every direction above the surface has a positive pdf). For each direction the incident radiance
L_k is estimated once: the map's radiance where the ray escapes, and where it hits the object, the radiance leaving
that point, path traced (`indirect_bounces` more interactions) with the build-time material, detached. Then for any
material f at the hit

    L_o = lambert(wo) / pi * sum_k w_k  +  sum_k glossy(wi_k, wo) w_k,     w_k = L_k cos(theta_k) / (K p_mix(wi_k))

the one-sample mixture estimator (Veach's balance heuristic over the K samples), unbiased for the first
interaction for every material whose f is non-zero only where p_mix is. The Lambertian sum is a per-hit constant,
so a step costs one glossy evaluation per cached direction and no ray query. What it gives up: the indirect
radiance is the build-time material's (rebuild the cache every few hundred steps, as TTO does), and the samples are
fixed between rebuilds, so one cache is a fixed, slightly noisy objective (its noise averages out over rebuilds).

`tests/test_transport_cache.py` checks it against the path tracer (`render/path_tracer.py`), which stays the
reference: the same expectation per pixel within Monte Carlo noise, for direct and multi-bounce transport.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neumatex_core.geometry.raycast import Hits
from neumatex_core.geometry.surface import RAY_EPSILON, SurfaceInteraction, surface_interaction
from neumatex_core.materials.base import cosine_pdf, cosine_sample
from neumatex_core.materials.field import MaterialField
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene


@dataclass(frozen=True)
class TransportCacheConfig:
    """directions: incident directions K per hit; light_share / bsdf_share: mixture weights of environment and
    build-time BSDF sampling (the rest is cosine; both >= 0, sum < 1); indirect_bounces: surface interactions
    after the first (0: direct lighting with visibility only); chunk_rays: rays traced at once."""

    directions: int = 32
    light_share: float = 0.4
    bsdf_share: float = 0.4
    indirect_bounces: int = 2
    chunk_rays: int = 1 << 17

    def check(self) -> None:
        if self.directions < 1:
            raise ValueError(f"transport cache directions must be >= 1, got {self.directions}")
        if min(self.light_share, self.bsdf_share) < 0 or self.light_share + self.bsdf_share >= 1:
            raise ValueError("transport cache light_share and bsdf_share must be >= 0 with a sum below 1 (the cosine "
                             f"lobe keeps every direction reachable), got {self.light_share} and {self.bsdf_share}")
        if self.indirect_bounces < 0:
            raise ValueError(f"transport cache indirect_bounces must be >= 0, got {self.indirect_bounces}")


def select_interaction(si: SurfaceInteraction, index: torch.Tensor) -> SurfaceInteraction:
    """The rows `index` of a SurfaceInteraction."""
    return SurfaceInteraction(si.position[index], si.geo_normal[index], si.shading_normal[index], si.tri[index],
                              si.bary[index], None if si.uv is None else si.uv[index], si.wo[index])  # fmt: skip


@dataclass
class TransportCache:
    """The cached transport of N camera rays; H of them hit the object.

    slot [N]: the hit row of each ray (-1: the ray misses); background [N, 3]: the map's radiance of missing rays
    (0 for hits); si: the H hits; wo [H, 3] local viewer direction; wi [H, K, 3] local incident directions;
    weight [H, K, 3] = L_k cos / (K p_mix) (0 for directions below the surface); lambert_weight [H, 3] = the sum of
    the weights / pi."""

    slot: torch.Tensor
    background: torch.Tensor
    si: SurfaceInteraction
    wo: torch.Tensor
    wi: torch.Tensor
    weight: torch.Tensor
    lambert_weight: torch.Tensor

    @property
    def n_rays(self) -> int:
        return int(self.slot.shape[0])

    @classmethod
    @torch.no_grad()
    def build(cls, scene: Scene, origins: torch.Tensor, directions: torch.Tensor, generator: torch.Generator,
              config: TransportCacheConfig | None = None) -> TransportCache:
        """Trace the camera rays origins, directions [N, 3] of `scene` (its material field is the build-time
        material: BSDF sampling and indirect radiance) and cache their transport (see the module docstring)."""
        cfg = config or TransportCacheConfig()
        cfg.check()
        device = origins.device
        n, k = origins.shape[0], cfg.directions
        hits = scene.raycaster.intersect(origins, directions)
        valid = hits.valid
        background = torch.zeros(n, 3, device=device)
        if bool((~valid).any()):
            background[~valid] = scene.envmap.eval(directions[~valid])
        hit_rows = valid.nonzero().squeeze(-1)
        slot = torch.full((n,), -1, dtype=torch.long, device=device)
        slot[hit_rows] = torch.arange(hit_rows.numel(), device=device)
        h_hits = Hits(hits.t[hit_rows], hits.tri[hit_rows], hits.bary[hit_rows])
        si = surface_interaction(scene.mesh_tensors, h_hits, origins[hit_rows], directions[hit_rows])
        wo = si.to_local(si.wo)
        h = hit_rows.numel()
        rep = torch.arange(h, device=device).repeat_interleave(k)
        si_k = select_interaction(si, rep)
        wo_k = wo[rep]
        material_k = scene.material.at(si_k)
        u = torch.rand(h * k, 4, generator=generator, device=device)
        # Draw from the mixture: a technique per sample, then its direction (local and world).
        light_dir, _, _ = scene.envmap.sample(u[:, 1:3])
        bsdf_local, _ = material_k.sample(wo_k, u[:, 3], u[:, 1:3])
        cos_local = cosine_sample(u[:, 1:3])
        use_light = u[:, 0] < cfg.light_share
        use_bsdf = ~use_light & (u[:, 0] < cfg.light_share + cfg.bsdf_share)
        local = torch.where(use_bsdf.unsqueeze(-1), bsdf_local, cos_local)
        world = si_k.to_world(local)
        world = torch.where(use_light.unsqueeze(-1), light_dir, world)
        world = world / world.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        local = si_k.to_local(world)
        cosine_share = 1 - cfg.light_share - cfg.bsdf_share
        p_mix = (cfg.light_share * scene.envmap.pdf(world) + cfg.bsdf_share * material_k.pdf(local, wo_k)
                 + cosine_share * cosine_pdf(local))  # fmt: skip
        ok = (local[:, 2] > 0) & ((world * si_k.geo_normal).sum(-1) > 0) & (p_mix > 0)
        incident = _incident_radiance(scene, si_k, world, ok, generator, cfg)
        weight = incident * (local[:, 2].clamp_min(0.0) / (k * p_mix.clamp_min(1e-30))).unsqueeze(-1)
        weight = torch.where(ok.unsqueeze(-1), weight, torch.zeros_like(weight))
        weight = weight.reshape(h, k, 3)
        return cls(slot, background, si, wo, local.reshape(h, k, 3), weight, weight.sum(1) / torch.pi)

    def radiance(self, field: MaterialField, rays: torch.Tensor | None = None) -> torch.Tensor:
        """Radiance [R, 3] of the cached rays `rays` [R] (default: all N) under `field` (the material at the first
        hit; differentiable in its parameters)."""
        rays = torch.arange(self.n_rays, device=self.slot.device) if rays is None else rays
        slot = self.slot[rays]
        hit = (slot >= 0).nonzero().squeeze(-1)
        s = slot[hit]
        k = self.wi.shape[1]
        material = field.at(select_interaction(self.si, s))
        wo = self.wo[s]
        lambert = material.lambert(wo) * self.lambert_weight[s]
        rep = torch.arange(s.numel(), device=s.device).repeat_interleave(k)
        glossy = material.select(rep).eval_glossy(self.wi[s].reshape(-1, 3), wo[rep])
        glossy = (glossy * self.weight[s].reshape(-1, 3)).reshape(-1, k, 3).sum(1)
        return self.background[rays].index_add(0, hit, lambert + glossy)


def _incident_radiance(scene: Scene, si: SurfaceInteraction, world: torch.Tensor, ok: torch.Tensor,
                       generator: torch.Generator, cfg: TransportCacheConfig) -> torch.Tensor:
    """[M, 3] radiance arriving at the hits `si` from directions `world` [M, 3] (0 where not `ok`): the map where
    the ray escapes, else the path-traced radiance leaving the point it hits (cfg.indirect_bounces interactions)."""
    out = torch.zeros(world.shape[0], 3, device=world.device)
    rows = ok.nonzero().squeeze(-1)
    if rows.numel() == 0:
        return out
    side = torch.sign((world[rows] * si.geo_normal[rows]).sum(-1, keepdim=True))
    origins = si.position[rows] + si.geo_normal[rows] * (RAY_EPSILON * side)
    tracer = PathTracer(PathTracerConfig(max_bounces=cfg.indirect_bounces, rr_depth=max(cfg.indirect_bounces, 1)))
    for start in range(0, rows.numel(), cfg.chunk_rays):
        sl = slice(start, start + cfg.chunk_rays)
        out[rows[sl]] = tracer.render_rays(scene, origins[sl], world[rows][sl], generator)
    return out
