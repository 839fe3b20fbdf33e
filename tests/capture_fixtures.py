"""Helpers that write tiny, valid captures (and zips of them) for tests.

`write_capture(tmp_path / "cap")` gives a folder with transforms.json (global intrinsics), an icosphere mesh
(radius 0.8, OBJ), PNG photos from the first `n_frames` preset views, optional PNG masks (the sphere's
silhouette) and a constant 32x16 EXR environment map. Tests break one thing at a time with
`read_transforms` / `write_transforms` or by overwriting a file.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from neumatex_core.geometry.camera import Camera, preset_views
from neumatex_core.imageio import write_image

SPHERE_RADIUS = 0.8


def sphere_silhouette(camera: Camera, radius: float = SPHERE_RADIUS) -> np.ndarray:
    """bool [H, W]: pixels whose centre ray hits the origin-centred sphere of `radius`."""
    xs, ys = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    d_cam = np.stack([(xs - camera.cx) / camera.fl_x, -(ys - camera.cy) / camera.fl_y, -np.ones_like(xs)], -1)
    d = d_cam @ camera.c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = camera.position
    b = d @ o
    disc = b**2 - (o @ o - radius**2)
    return np.asarray((disc > 0) & (-b - np.sqrt(np.maximum(disc, 0)) > 0))


def frame_entry(i: int, camera: Camera, masks: bool, per_frame_intrinsics: bool) -> dict[str, Any]:
    entry: dict[str, Any] = {"file_path": f"images/{i:03d}.png", "transform_matrix": camera.c2w.tolist()}
    if masks:
        entry["mask_path"] = f"masks/{i:03d}.png"
    if per_frame_intrinsics:
        entry.update(
            fl_x=camera.fl_x, fl_y=camera.fl_y, cx=camera.cx, cy=camera.cy, w=camera.width, h=camera.height
        )
    return entry


def write_capture(
    root: str | Path,
    n_frames: int = 4,
    resolution: int = 32,
    masks: bool = False,
    per_frame_intrinsics: bool = False,
    envmap_size: tuple[int, int] = (32, 16),
    envmap_value: float = 1.0,
    mesh_name: str = "mesh.obj",
    seed: int = 0,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write a valid capture into the folder `root` (created) and return it.

    Photos are grey with noise, brighter inside the sphere's silhouette, 8-bit sRGB PNGs of
    resolution x resolution; `extra` entries are merged into transforms.json's top level.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    cams = preset_views(resolution)[:n_frames]
    trimesh.creation.icosphere(subdivisions=2, radius=SPHERE_RADIUS).export(root / mesh_name)
    w, h = envmap_size
    write_image(root / "envmap.exr", np.full((h, w, 3), envmap_value, np.float32))
    for i, cam in enumerate(cams):
        sil = sphere_silhouette(cam)
        img = 0.3 + 0.4 * sil[:, :, None] + 0.05 * rng.standard_normal((resolution, resolution, 3))
        write_image(root / f"images/{i:03d}.png", img.astype(np.float32))
        if masks:
            write_image(root / f"masks/{i:03d}.png", sil[:, :, None].astype(np.float32))
    c0 = cams[0]
    transforms: dict[str, Any] = {} if per_frame_intrinsics else {
        "fl_x": c0.fl_x, "fl_y": c0.fl_y, "cx": c0.cx, "cy": c0.cy, "w": c0.width, "h": c0.height,
    }  # fmt: skip
    transforms.update(
        mesh=mesh_name,
        envmap="envmap.exr",
        frames=[frame_entry(i, c, masks, per_frame_intrinsics) for i, c in enumerate(cams)],
    )
    transforms.update(extra or {})
    write_transforms(root, transforms)
    return root


def read_transforms(root: str | Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((Path(root) / "transforms.json").read_text())
    return data


def write_transforms(root: str | Path, data: dict[str, Any]) -> None:
    (Path(root) / "transforms.json").write_text(json.dumps(data, indent=2))


def zip_capture(folder: str | Path, zip_path: str | Path | None = None, top_level: str | None = None) -> Path:
    """Zip the capture folder (files at the zip's top level, or inside `top_level/`); returns the zip path."""
    folder = Path(folder)
    zip_path = Path(zip_path) if zip_path is not None else folder.with_suffix(".zip")
    with zipfile.ZipFile(zip_path, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                rel = path.relative_to(folder).as_posix()
                zf.write(path, f"{top_level}/{rel}" if top_level else rel)
    return zip_path
