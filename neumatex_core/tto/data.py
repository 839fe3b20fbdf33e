"""TTO's inputs: the photos as random pixel batches, and area-uniform surface samples for the anchor.

`PhotoSet` holds every photo's display values (what the capture's tonemap T makes of radiance), its camera in
the normalised frame and its own exposure multiplier (`Frame.exposure`: photo f shows T(exposure[f] * radiance));
`batch(n, spp, generator)` draws n foreground pixels uniformly over all photos and gives `spp` jittered rays through
each, so a step costs n * spp paths whatever the photos' size; `shuffled_batch` draws them in random reshuffling's
order instead (`shuffled_pixels`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from neumatex_core.capture import Capture
from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.raycast import RayCaster


@lru_cache(maxsize=4)
def _epoch_order(size: int, seed: int, epoch: int) -> torch.Tensor:
    """[size] int64 (CPU): epoch `epoch`'s random permutation of 0..size-1, a function of (seed, epoch) alone."""
    generator = torch.Generator().manual_seed(seed * 1_000_003 + 900_000_011 + epoch)
    return torch.randperm(size, generator=generator)


def shuffled_pixels(size: int, start: int, n: int, seed: int) -> torch.Tensor:
    """[n] int64 (CPU): the pixels at draw positions start..start + n - 1 of a sequence of random permutations of
    0..size-1, one after another (random reshuffling: each epoch of `size` draws takes every pixel once). A step's
    pixels depend only on (seed, its first position), so a stopped TTO resumes bit for bit."""
    parts, position, end = [], start, start + n
    while position < end:
        epoch, offset = divmod(position, size)
        take = min(end - position, size - offset)
        parts.append(_epoch_order(size, seed, epoch)[offset:offset + take])
        position += take
    return torch.cat(parts)


@dataclass
class RayBatch:
    """origins, directions [n * spp, 3] (samples of one pixel contiguous); target [n, 3] display values; frame [n]
    (int64) the photo of each pixel; exposure [n] its photo's given exposure multiplier (unitless, > 0); index [n]
    (int64) each pixel's place among the set's foreground pixels (`PhotoSet.colour`'s rows)."""

    origins: torch.Tensor
    directions: torch.Tensor
    target: torch.Tensor
    spp: int
    frame: torch.Tensor
    exposure: torch.Tensor
    index: torch.Tensor


class PhotoSet:
    """Photos (display values [H, W, 3] in [0, 1], one camera each, optional foreground masks [H, W]) on `mesh`;
    `exposure`: each photo's own exposure multiplier on top of the tonemap's (`Capture.exposures`; default all 1).

    Foreground = the mesh covers the pixel centre (a ray query) and, where a mask is given, the mask is set."""

    def __init__(self, images: Sequence[np.ndarray], cameras: Sequence[Camera], mesh: Mesh,
                 masks: Sequence[np.ndarray | None] | None = None, device: torch.device | str = "cpu",
                 exposure: Sequence[float] | None = None) -> None:
        if len(images) != len(cameras) or not images:
            raise ValueError(f"need one camera per photo, got {len(images)} photos and {len(cameras)} cameras")
        if exposure is not None and (len(exposure) != len(images) or not all(e > 0 for e in exposure)):
            raise ValueError(f"need one positive exposure per photo, got {list(exposure)} for {len(images)} photos")
        self.device = torch.device(device)
        self.cameras = list(cameras)
        self.exposure = torch.tensor([1.0] * len(images) if exposure is None else [float(e) for e in exposure],
                                     dtype=torch.float32, device=self.device)  # [F]
        caster = RayCaster(mesh)
        colours, pixels = [], []
        for f, (img, cam) in enumerate(zip(images, cameras, strict=True)):
            if img.shape[:2] != (cam.height, cam.width):
                raise ValueError(f"photo {f} is {img.shape[1]}x{img.shape[0]}, its camera {cam.width}x{cam.height}")
            fg = render_gbuffer(mesh, cam, caster).mask
            m = masks[f] if masks is not None else None
            if m is not None:
                fg = fg & torch.as_tensor(np.asarray(m, dtype=bool))
            yx = fg.nonzero()
            colours.append(torch.as_tensor(np.ascontiguousarray(img[..., :3]), dtype=torch.float32)[yx[:, 0], yx[:, 1]])
            pixels.append(torch.cat([torch.full((yx.shape[0], 1), f), yx[:, 1:2], yx[:, 0:1]], dim=1))
        self.colour = torch.cat(colours).to(self.device)  # [M, 3]
        self.pixel = torch.cat(pixels).to(self.device)  # [M, 3]: frame, x, y
        if self.pixel.shape[0] == 0:
            raise ValueError("the mesh covers no pixel of any photo")

    @classmethod
    def of_capture(cls, capture: Capture, mesh: Mesh, cameras: Sequence[Camera] | None = None,
                   device: torch.device | str = "cpu") -> PhotoSet:
        """Every frame of `capture` with its mask and its given exposure, on `mesh`, seen by the capture's cameras or
        by `cameras` (the same frames in another frame of reference, e.g. the pipeline's normalised one)."""
        frames = range(len(capture.frames))
        return cls([capture.load_image(i) for i in frames], capture.cameras if cameras is None else cameras, mesh,
                   [capture.load_mask(i) for i in frames], device, capture.exposures)  # fmt: skip

    @property
    def count(self) -> int:
        """Photos."""
        return len(self.cameras)

    @property
    def size(self) -> int:
        """Foreground pixels over all photos."""
        return int(self.pixel.shape[0])

    def subset(self, frames: Sequence[int]) -> PhotoSet:
        """The photos `frames` (in that order, renumbered 0..) as a set of their own, with the same foreground
        pixels, cameras and exposures (no ray queries again)."""
        keep = torch.as_tensor(list(frames), dtype=torch.long, device=self.device)
        if keep.numel() == 0 or int(keep.min()) < 0 or int(keep.max()) >= self.count:
            raise ValueError(f"photo subset {list(frames)} is empty or outside 0..{self.count - 1}")
        renumber = torch.full((self.count,), -1, dtype=torch.long, device=self.device)
        renumber[keep] = torch.arange(keep.numel(), device=self.device)
        frame = renumber[self.pixel[:, 0].long()]
        sel = frame >= 0
        out = PhotoSet.__new__(PhotoSet)
        out.device, out.cameras, out.exposure = self.device, [self.cameras[f] for f in frames], self.exposure[keep]
        out.colour = self.colour[sel]
        out.pixel = torch.cat([frame[sel].unsqueeze(-1).to(self.pixel.dtype), self.pixel[sel, 1:]], dim=1)
        return out

    def batch(self, n: int, spp: int, generator: torch.Generator) -> RayBatch:
        """n pixels drawn uniformly (with replacement) from all foreground pixels, spp jittered rays each."""
        return self.rays(torch.randint(0, self.size, (n,), generator=generator, device=self.device), spp, generator)

    def shuffled_batch(self, start: int, n: int, spp: int, seed: int, generator: torch.Generator) -> RayBatch:
        """The n pixels at draw positions start.. of `shuffled_pixels` (seeded by `seed`), spp jittered rays each."""
        return self.rays(shuffled_pixels(self.size, start, n, seed).to(self.device), spp, generator)

    def rays(self, idx: torch.Tensor, spp: int, generator: torch.Generator) -> RayBatch:
        """The foreground pixels idx [n] (int64, into 0..size-1), spp jittered rays each."""
        n = idx.shape[0]
        pix = self.pixel[idx]
        jitter = torch.rand(n * spp, 2, generator=generator, device=self.device)
        xy = pix[:, 1:].repeat_interleave(spp, dim=0).float() + jitter
        frame = pix[:, 0].repeat_interleave(spp)
        origins = torch.empty(n * spp, 3, device=self.device)
        directions = torch.empty(n * spp, 3, device=self.device)
        for f in torch.unique(frame).tolist():
            sel = (frame == f).nonzero().squeeze(-1)
            o, d = self.cameras[f].rays_for_pixels(xy[sel, 0], xy[sel, 1])
            origins[sel], directions[sel] = o, d
        return RayBatch(origins, directions, self.colour[idx], spp, pix[:, 0], self.exposure[pix[:, 0]], idx)

    def smoothed_colour(self, radius: int) -> torch.Tensor:
        """[M, 3] display values: each foreground pixel's mean over the foreground pixels of its photo within the
        (2 radius + 1)^2 window around it (radius 0: `colour` itself). A noisy photo's pixel value is correlated
        with its own noise; this mean much less so (what `photometric_loss` weighs a pixel by)."""
        if radius <= 0:
            return self.colour
        out = torch.empty_like(self.colour)
        for f, cam in enumerate(self.cameras):
            sel = (self.pixel[:, 0] == f).nonzero().squeeze(-1)
            x, y = self.pixel[sel, 1].long(), self.pixel[sel, 2].long()
            dense = torch.zeros(4, cam.height, cam.width, device=self.device)  # colour and coverage
            dense[:3, y, x] = self.colour[sel].T
            dense[3, y, x] = 1.0
            window = torch.nn.functional.avg_pool2d(dense.unsqueeze(0), 2 * radius + 1, stride=1, padding=radius)[0]
            out[sel] = (window[:3, y, x] / window[3, y, x]).T  # the pixel itself is covered: no division by 0
        return out
