"""Re-rendering a written synthetic object from its stored files alone: the ground-truth consistency check.

`GBufferField(camera, base_color, latent, mask, basis)` is a material field that knows the material only through
one view's stored G-buffers: a surface point is projected into that camera and takes the base colour and latent of
the pixel it falls in (or of the nearest covered pixel, for samples of silhouette pixels whose centre misses).
For points the camera sees, that is the object's material up to its variation inside one pixel.
`render_mean_variance` renders a view with per-pixel sample variances, so a stored image and a re-render can be
compared in units of their Monte Carlo noise (`consistency_z`).

Hits the view cannot see (other sides, reached by indirect bounces of a non-convex object) would get wrong
materials, so the check is exact for convex objects or with `max_bounces=1`. G-buffers are point samples at pixel
centres while an image averages each pixel's footprint (box filter), so the two agree only where the material is
smooth at the pixel scale: a colour pattern or region border that varies inside a pixel biases that pixel (on
24 px spheres with colour patterns of frequency 7.4 we measured 4-5% of pixels beyond 3 sigma and a mean z of
4.5-6 / sqrt(N), against 0.3-2.4% and 0.5-2.1 / sqrt(N) at frequency 1). The test (tests/test_synth.py) uses one
region and a pattern of low frequency.

Take `variance` in `consistency_z` from a render independent of `mean`: the sample variance of the same samples
correlates with their mean for skewed radiance (a sun), which biases z (measured +1.5 / sqrt(N)).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from neumatex_core.capture import load_capture
from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.imageio import read_image
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial
from neumatex_core.render.path_tracer import PathTracer
from neumatex_core.render.scene import Scene


class GBufferField(MaterialField):
    """Material from one view's G-buffers: base_color [H, W, 3], latent [H, W, 6], mask [H, W] bool."""

    def __init__(self, camera: Camera, base_color: torch.Tensor, latent: torch.Tensor, mask: np.ndarray,
                 basis: NeuralBasis) -> None:
        self.camera, self.basis = camera, basis
        h, w = mask.shape
        # Index of the nearest covered pixel, for every pixel (itself where covered).
        _, (iy, ix) = ndimage.distance_transform_edt(~mask, return_indices=True)
        nearest = torch.from_numpy((iy * w + ix).reshape(-1).astype(np.int64))
        self.base_color = base_color.reshape(-1, 3)[nearest]
        self.latent = latent.reshape(-1, latent.shape[-1])[nearest]
        self.w2c = torch.from_numpy(np.linalg.inv(camera.c2w)).float()

    def pixel(self, position: torch.Tensor) -> torch.Tensor:
        """[N] row-major pixel index (clamped to the image) of world points [N, 3]."""
        cam = self.camera
        p = position @ self.w2c[:3, :3].T.to(position.device) + self.w2c[:3, 3].to(position.device)
        z = (-p[:, 2]).clamp_min(1e-9)
        x = (cam.fl_x * p[:, 0] / z + cam.cx).floor().long().clamp(0, cam.width - 1)
        y = (-cam.fl_y * p[:, 1] / z + cam.cy).floor().long().clamp(0, cam.height - 1)
        return y * cam.width + x

    def at(self, si: SurfaceInteraction) -> NeuralMaterial:
        idx = self.pixel(si.position).cpu()
        device = si.position.device
        return NeuralMaterial(self.basis, self.base_color[idx].to(device), self.latent[idx].to(device))


def render_mean_variance(tracer: PathTracer, scene: Scene, camera: Camera, spp: int, seed: int,
                         chunk: int = 1 << 16) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean [H, W, 3], variance of one sample [H, W, 3], unbiased over the spp samples) of a view."""
    gen = torch.Generator().manual_seed(seed)
    o, d, _ = camera.generate_rays(spp=spp, generator=gen)
    with torch.no_grad():
        radiance = torch.cat([tracer.render_rays(scene, o[s:s + chunk], d[s:s + chunk], gen)
                              for s in range(0, o.shape[0], chunk)])  # fmt: skip
    samples = radiance.reshape(camera.height, camera.width, spp, 3).double()
    return samples.mean(2).float(), samples.var(2, unbiased=True).float()


@dataclass
class StoredView:
    """One preset view of a written object as stored: linear image [H, W, 3], mask [H, W], base colour and latent
    G-buffers, camera, the render seed, and the object's mesh and lighting (as a capture loader reads them)."""

    camera: Camera
    image: np.ndarray
    mask: np.ndarray
    base_color: np.ndarray
    latent: np.ndarray
    seed: int
    mesh: Mesh
    envmap: EnvironmentMap

    def field(self, basis: NeuralBasis) -> GBufferField:
        return GBufferField(self.camera, torch.from_numpy(self.base_color), torch.from_numpy(self.latent), self.mask,
                            basis)


def load_view(object_dir: Path, view: int) -> StoredView:
    """The stored preset view `view` of an object folder (read through the capture loader)."""
    capture = load_capture(object_dir)
    entry = json.loads((object_dir / "transforms.json").read_text())["frames"][view]
    meta = json.loads((object_dir / "meta.json").read_text())
    return StoredView(
        camera=capture.frames[view].camera,
        image=read_image(object_dir / entry["linear_path"])[:, :, :3],
        mask=np.asarray(capture.load_mask(view)),
        base_color=read_image(object_dir / entry["gbuffers"]["basecolor"]),
        latent=read_image(object_dir / entry["gbuffers"]["latent"]),
        seed=int(meta["spec"]["render_seed"]) + view,
        mesh=capture.load_mesh(),
        envmap=EnvironmentMap.from_file(capture.envmap_path, capture.envmap_to_world, capture.envmap_scale),
    )


def consistency_z(stored: np.ndarray, stored_spp: int, mean: torch.Tensor, variance: torch.Tensor, spp: int
                  ) -> np.ndarray:
    """Per pixel and channel z = (stored - re-rendered) / sqrt(var/stored_spp + var/spp): ~N(0, 1) when the two
    renders differ only by Monte Carlo noise. stored [H, W, 3] (stored_spp samples), mean [H, W, 3] (spp samples),
    variance [H, W, 3]: per-sample variance, best from a third, independent render (module docstring). Pixels
    without variance (pure background) are 0 where equal, infinite where not."""
    var = variance.numpy().astype(np.float64)
    sigma = np.sqrt(var / stored_spp + var / spp)
    diff = stored.astype(np.float64) - mean.numpy().astype(np.float64)
    return np.where(sigma > 0, diff / np.maximum(sigma, 1e-30), np.where(np.abs(diff) > 1e-6, np.inf, 0.0))
