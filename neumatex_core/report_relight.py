"""Relit renders for the extraction report: the asset under a shared environment map other than the capture's.

The map is looked up in the shared data ($NEUMATEX_SHARED/data/envmaps, else ../shared/data/envmaps beside the
repository); without one the report simply has no relit section.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from neumatex_core.lighting.envmap import EnvironmentMap

RELIGHT_PREFERENCE = ("studio.exr", "sunrise.exr", "forest.exr", "city.exr")


def relight_map_path(capture_envmap: Path | None = None) -> Path | None:
    """A shared map for relighting: the first of RELIGHT_PREFERENCE present whose bytes differ from the capture's."""
    from neumatex_core.synth.config import default_shared

    folder = default_shared() / "envmaps"
    own = capture_envmap.read_bytes() if capture_envmap is not None and capture_envmap.is_file() else None
    for name in RELIGHT_PREFERENCE:
        path = folder / name
        if path.is_file() and (own is None or path.stat().st_size != len(own) or path.read_bytes() != own):
            return path
    return None


def relit_images(render_views: Callable[[EnvironmentMap], list[tuple[int, np.ndarray]]], envmap_path: Path,
                 device: str) -> list[tuple[str, np.ndarray]]:
    """(caption, display image [H, W, 3] in [0, 1]) per (view index, image) render_views makes under the map."""
    envmap = EnvironmentMap.from_file(envmap_path, device=device)
    return [(f"relit under {envmap_path.stem}, view {v}", img) for v, img in render_views(envmap)]
