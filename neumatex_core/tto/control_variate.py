"""A control variate for the TTO's photo renders (`TTOConfig.control_variate`; docs/design-notes.md item 57).

Started from the ground truth, the TTO's steady state is set by the fresh Monte Carlo noise of its own renders: with
photos 8 times less noisy it keeps only 1.1 dB more, and neither fewer texels nor a Gauss-Newton step change it
(item 57). Two renders of the same rays with the same random numbers under two nearby materials are almost
perfectly correlated (benchmark object 0, 4096 pixels at 8 spp: the difference of two such renders varies 40-1500
times less than one render's noise, for feature perturbations of 0.2 down to 0.02), so each step's render r(theta)
is replaced by

    r_cv = r(theta) - r(theta_0) + R(theta_0),

r(theta_0) the same rays and random numbers under a frozen reference material theta_0 (detached), R(theta_0) that
reference's radiance of every foreground photo pixel rendered once at `cv_spp` samples. E[r_cv] = E[r(theta)], so the
photo loss keeps its expectation, while the fresh noise of the residual is only that of the difference; R's own
noise is fixed until the reference is refreshed, like the photos' noise. The gradient still flows through r(theta)
alone. The reference is the field at the start of the steps the variate covers (the settling phase, or every
`cv_refresh` steps from there).
"""

from __future__ import annotations

import copy

import torch

from neumatex_core.render.path_tracer import PathTracer
from neumatex_core.render.scene import Scene
from neumatex_core.tto.data import PhotoSet
from neumatex_core.tto.params import Parametrisation

CHUNK_PIXELS = 2048  # pixels traced at once when the reference's radiance of every photo pixel is rendered


def clone_generator(generator: torch.Generator) -> torch.Generator:
    """A generator in the same state as `generator` (the same random numbers from here on)."""
    twin = torch.Generator(device=generator.device)
    twin.set_state(generator.get_state())
    return twin


class ControlVariate:
    """The frozen reference material theta_0 (`params`: a copy of the TTO's parametrisation that this object owns and
    freezes; its field in a scene sharing the main scene's mesh, BVH and map) and its radiance R [P, 3] (linear,
    before exposure) of the photos' P foreground pixels, rendered at `spp` samples by `tracer` with `generator`."""

    def __init__(self, params: Parametrisation, scene: Scene, photos: PhotoSet, tracer: PathTracer, spp: int,
                 generator: torch.Generator) -> None:
        self.params = params
        self.params.tensor.requires_grad_(False)
        for p in self.params.decoder_parameters():
            p.requires_grad_(False)
        self.scene = copy.copy(scene)
        self.scene.material = self.params.field()
        self.tracer = tracer
        device = photos.device
        out = torch.empty(photos.size, 3, device=device)
        with torch.no_grad():
            for start in range(0, photos.size, CHUNK_PIXELS):
                idx = torch.arange(start, min(start + CHUNK_PIXELS, photos.size), device=device)
                batch = photos.rays(idx, spp, generator)
                radiance = tracer.render_rays(self.scene, batch.origins, batch.directions, generator)
                out[idx] = radiance.reshape(-1, spp, 3).mean(1)
        self.reference = out

    def radiance(self, radiance: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor, index: torch.Tensor,
                 spp: int, generator: torch.Generator) -> torch.Tensor:
        """r_cv [n * spp, 3] of the samples `radiance` [n * spp, 3] of the rays origins, directions [n * spp, 3] of
        pixels `index` [n], rendered with the random numbers of `generator` (a clone of the state they were rendered
        from): each sample less the reference's sample of the same ray and random numbers, plus the reference's
        radiance of its pixel."""
        with torch.no_grad():
            base = self.tracer.render_rays(self.scene, origins, directions, generator)
        return radiance - base + self.reference[index].repeat_interleave(spp, dim=0)
