"""Helpers for the browser viewer's tests and benchmark: a sphere asset, headless Chromium with software WebGL2
(SwiftShader through ANGLE, Debian's /usr/bin/chromium: nothing is downloaded), reading the viewer's images back."""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator

import numpy as np

from neumatex_core.assets import MaterialAsset
from neumatex_core.geometry.camera import Camera, camera_from_fov, look_at
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.materials.neural_basis import NeuralBasis

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# WebGL2 in software: ANGLE on SwiftShader's Vulkan. No GPU watchdog: a software frame of a neural shader is slow.
CHROMIUM_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                 "--disable-gpu-watchdog"]  # fmt: skip


def sphere_mesh(subdivisions: int = 3, radius: float = 0.9) -> Mesh:
    """An icosphere with exact sphere normals (convex: no self-shadowing, which a rasteriser cannot show)."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(s.vertices, np.float32)
    return Mesh(v, np.asarray(s.faces, np.int64), v / np.linalg.norm(v, axis=1, keepdims=True))


def sphere_asset(basis: NeuralBasis, resolution: int = 64, steps: int = 60, subdivisions: int = 3) -> MaterialAsset:
    from asset_fixtures import make_asset

    return make_asset(sphere_mesh(subdivisions), basis, name="sphere", resolution=resolution, steps=steps)


def view_camera(size: int, distance: float = 2.6, azimuth_deg: float = 30.0, elevation_deg: float = 25.0) -> Camera:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    return camera_from_fov(look_at(eye, np.zeros(3), np.array([0.0, 1.0, 0.0])), size, size, 45.0)


@contextlib.contextmanager
def viewer_page(url: str, viewport: int = 1100) -> Iterator[object]:
    """A Playwright page on the viewer at `url`, its bundle loaded (raises with the page's error otherwise)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": viewport, "height": viewport})
            page.goto(url)
            try:
                page.evaluate("() => window.neumatexViewer.ready")
            except Exception as exc:
                raise RuntimeError(f"viewer failed: {page.evaluate('() => window.neumatexViewer.error')}") from exc
            yield page
        finally:
            browser.close()


def set_camera(page, camera: Camera) -> None:
    """Put the torch camera into the page (same size, row-major c2w, intrinsics in pixels)."""
    page.evaluate("([w, h]) => window.neumatexViewer.resize(w, h)", [camera.width, camera.height])
    page.evaluate("([m, fx, fy, cx, cy]) => window.neumatexViewer.setCamera(m, fx, fy, cx, cy)",
                  [np.asarray(camera.c2w, float).ravel().tolist(), camera.fl_x, camera.fl_y, camera.cx, camera.cy])


def read_display(page) -> np.ndarray:
    """The canvas as the page shows it: [H, W, 3] 8-bit sRGB codes / 255, row 0 at the top."""
    out = page.evaluate("() => window.neumatexViewer.readDisplay()")
    px = np.asarray(out["data"], np.uint8).reshape(out["height"], out["width"], 4)[::-1, :, :3]
    return px.astype(np.float32) / 255.0


def read_linear(page) -> np.ndarray:
    """The viewer's accumulated linear radiance [H, W, 3] (float32 mean over its frames), row 0 at the top."""
    out = page.evaluate("() => window.neumatexViewer.readLinear()")
    return np.asarray(out["data"], np.float32).reshape(out["height"], out["width"], 4)[::-1, :, :3].copy()
