"""Rendering an asset: any of its representations, under any environment map, from any cameras; preview images."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import numpy as np
import torch

from neumatex_core.assets.asset import MaterialAsset, Source
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.device import side_by_side
from neumatex_core.geometry.camera import Camera, preset_views
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene

PREVIEW_VIEWS = (0, 4, 8, 12)  # four orbit views, 85 degrees apart


def asset_scene(asset: MaterialAsset, envmap: EnvironmentMap, source: Source = "auto") -> Scene:
    """A scene of the asset's mesh and the chosen representation of its material under `envmap`."""
    return Scene(asset.mesh, envmap, asset.field(source), device=envmap.device)


def render_asset(asset: MaterialAsset, envmap: EnvironmentMap, cameras: Sequence[Camera],
                 config: PathTracerConfig | None = None, source: Source = "auto", seed: int = 0,
                 progress: Callable[[int, int], None] | None = None) -> list[torch.Tensor]:
    """Linear HDR images [H, W, 3], camera i with seed + i; identical for identical assets, device and seed."""
    scene = asset_scene(asset, envmap, source)
    tracer = PathTracer(config or PathTracerConfig())
    images = []
    with torch.no_grad():
        for i, cam in enumerate(cameras):
            images.append(tracer.render(scene, cam, seed=seed + i))
            if progress is not None:
                progress(i + 1, len(cameras))
    return images


def render_neural_and_pbr(asset: MaterialAsset, envmap: EnvironmentMap, cameras: Sequence[Camera],
                          config: PathTracerConfig | None = None,
                          seed: int = 0) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """`render_asset` of the asset's own field ("auto") and of its PBR fallback, side by side where there are torch
    threads for both (`side_by_side`; docs/design-notes.md item 47): the same images as one after the other."""
    neural, pbr = side_by_side([partial(render_asset, asset, envmap, cameras, config, source, seed)
                                for source in ("auto", "pbr")], envmap.device)  # fmt: skip
    return neural, pbr


def make_previews(asset: MaterialAsset, envmap: EnvironmentMap, resolution: int = 256, spp: int = 64,
                  views: Sequence[int] = PREVIEW_VIEWS, tonemap: Tonemap | None = None) -> dict[str, np.ndarray]:
    """Display images of preset orbit views of the neural field and of the PBR fallback; stored in the asset."""
    presets = preset_views(resolution)
    cams = [presets[i] for i in views]
    tm = tonemap or Tonemap()
    cfg = PathTracerConfig(spp=spp, max_bounces=3)
    previews: dict[str, np.ndarray] = {}
    for label, images in zip(("neural", "pbr"), render_neural_and_pbr(asset, envmap, cams, cfg), strict=True):
        for v, img in zip(views, images, strict=True):
            previews[f"{label}_view{v:02d}"] = tm.apply(img).cpu().numpy()
    asset.previews = previews
    return previews
