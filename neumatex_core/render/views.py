"""Rendering a set of views to files: the `neumatex render` job, reusable by scripts and the demo."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from neumatex_core.geometry.camera import Camera, camera_from_fov, look_at
from neumatex_core.imageio import write_image
from neumatex_core.render.path_tracer import PathTracer
from neumatex_core.render.scene import Scene


@dataclass
class RenderedView:
    """One rendered view: linear HDR image [H, W, 3], its display version [H, W, 3] and file paths."""

    index: int
    linear: np.ndarray
    display: np.ndarray
    exr_path: Path
    png_path: Path


def render_views(
    scene: Scene,
    cameras: Sequence[Camera],
    tracer: PathTracer,
    out_dir: Path,
    tonemap: Callable[[torch.Tensor], torch.Tensor],
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> list[RenderedView]:
    """Render every camera (seed + index for each), writing view_XX.exr (linear) and view_XX.png (tonemapped)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for i, cam in enumerate(cameras):
        with torch.no_grad():
            image = tracer.render(scene, cam, seed=seed + i)
        display = tonemap(image).cpu().numpy()
        exr, png = out_dir / f"view_{i:02d}.exr", out_dir / f"view_{i:02d}.png"
        write_image(exr, image.cpu().numpy())
        write_image(png, display)
        results.append(RenderedView(i, image.cpu().numpy(), display, exr, png))
        if progress is not None:
            progress(i + 1, len(cameras))
    return results


def contact_sheet(images: Sequence[np.ndarray], columns: int = 6, pad: int = 2) -> np.ndarray:
    """Tile display images [H, W, 3] (same size) into one [rows*H, columns*W, 3] sheet on white."""
    h, w = images[0].shape[:2]
    rows = (len(images) + columns - 1) // columns
    sheet = np.ones((rows * (h + pad) + pad, columns * (w + pad) + pad, 3), dtype=np.float32)
    for k, img in enumerate(images):
        r, c = divmod(k, columns)
        y, x = pad + r * (h + pad), pad + c * (w + pad)
        sheet[y:y + h, x:x + w] = img[:, :, :3]
    return sheet


def sphere_camera(resolution: int, elevation_deg: float = 20.0, distance: float = 3.2) -> Camera:
    """A camera framing the unit sphere (the sphere fills ~80% of the frame), from the preset elevation."""
    el = math.radians(elevation_deg)
    eye = distance * np.array([0.0, math.sin(el), math.cos(el)])
    fov = 2 * math.degrees(math.asin(1.0 / distance)) / 0.8
    return camera_from_fov(look_at(eye, np.zeros(3), np.array([0.0, 1.0, 0.0])), resolution, resolution, fov)
