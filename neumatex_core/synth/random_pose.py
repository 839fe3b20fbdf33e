"""A random-pose variant of a synthetic object, as a studio capture would look (docs/benchmark.md, "Random-pose
captures"): `photos` 8-bit sRGB JPEGs from random poses around the object, each with its own exposure and a mild
lens distortion, rendered from the object's exact ground truth (`truth_field`, as `neumatex references` does).

    neumatex synth-random-pose data/benchmark-test --objects first:2 [--photos 100 --resolution R --spp S]

writes `<object>/random_pose/` as a capture folder (docs/capture-format.md): transforms.json (frames[].exposure,
the lens's OpenCV k1 k2 at the top level), images/NNN.jpg, masks/NNN.png (coverage of the distorted photo),
mesh.obj and the map (hard links to the object's), settings.json (what decided the files; compared on resume:
an object whose settings match is skipped, others are refused). transforms.json is written last.

Poses: directions uniform on the sphere, distance the preset distance times U(0.9, 1.15), aimed at a point within
0.1 of the origin, rolled by up to 5 degrees, the preset field of view. Exposure 2^U(-0.5, 0.5) per photo (the JPEG
stores T_i(x) = sRGB(clip(exposure_i x)), so the loader's `tonemap_of(i)` inverts it). The lens (one per object):
k1 U(-0.06, 0.06), k2 U(-0.02, 0.02) by default (`--lens`). A photo is rendered as a pinhole image on a canvas
padded to cover every ray the distorted sensor sees, then resampled (bilinear, linear radiance) at the distorted
pixel positions; the mask likewise (nearest). Poses, exposures and the lens depend only on the object's photo seed,
so transforms.json is deterministic; the pixels are too (seeded path tracer, one torch thread).
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neumatex_core.atomic import replaced_atomically, write_json_atomic
from neumatex_core.capture.distortion import Distortion, opencv_matrix
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.config import option
from neumatex_core.geometry.camera import PRESET_DISTANCE, PRESET_FOV_DEG, Camera, camera_from_fov, look_at
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.imageio import write_image

FORMAT = 1
POSE_SALT = 0x52A9  # SeedSequence([spec.photo_seed, POSE_SALT]): poses, exposures, lens
RENDER_SALT = 0x52AA  # SeedSequence([spec.render_seed, RENDER_SALT, k]): photo k's path-tracer seed
JPEG_QUALITY = 92


@dataclass
class RandomPoseConfig:
    """`neumatex synth-random-pose`: a random-pose capture (JPEG photos with per-photo exposure and lens
    distortion) of synthetic objects, rendered from their exact ground truth into <object>/random_pose/."""

    data: str = option("", "dataset folder of synthetic objects, e.g. data/benchmark-test", positional=True)
    objects: str = option("all", "'all', 'first:N', 'every:K' (objects 0, K, 2K, ...) or comma-separated ids")
    photos: int = option(100, "photos per object")
    resolution: int = option(0, "photo size in pixels (0: the object's own resolution)")
    spp: int = option(32, "samples per pixel")
    max_bounces: int = option(3, "surface interactions per path")
    exposure_stops: float = option(0.5, "per-photo exposure jitter: 2^U(-s, s)")
    lens: float = option(0.06, "lens distortion: k1 from U(-lens, lens), k2 from U(-lens / 3, lens / 3)")
    threads: int = option(1, "torch threads")


def random_pose_cameras(rng: np.random.Generator, n: int, resolution: int) -> list[Camera]:
    """`n` pinhole cameras around the unit sphere (see the module docstring)."""
    cams = []
    for _ in range(n):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        eye = d * PRESET_DISTANCE * rng.uniform(0.9, 1.15)
        target = rng.uniform(-0.1, 0.1, 3)
        up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.99 else np.array([0.0, 0.0, 1.0])
        c2w = look_at(eye, target, up)
        roll = math.radians(rng.uniform(-5.0, 5.0))
        r = np.array([[math.cos(roll), -math.sin(roll), 0.0], [math.sin(roll), math.cos(roll), 0.0], [0, 0, 1.0]])
        c2w[:3, :3] = c2w[:3, :3] @ r
        cams.append(camera_from_fov(c2w, resolution, resolution, PRESET_FOV_DEG))
    return cams


def distort_maps(camera: Camera, distortion: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the distorted photo: where its ray meets the pinhole `camera`'s image plane (x, y [H, W]
    float64, our pixel convention: pixel (i, j)'s centre at (i + 0.5, j + 0.5))."""
    import cv2

    h, w = camera.height, camera.width
    jj, ii = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    pts = np.stack([ii.ravel(), jj.ravel()], axis=1)[:, None, :]  # OpenCV pixel coordinates of the centres
    und = cv2.undistortPoints(pts, opencv_matrix(camera), distortion.opencv(),
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))[:, 0, :]
    x = camera.fl_x * und[:, 0] + camera.cx
    y = camera.fl_y * und[:, 1] + camera.cy
    return x.reshape(h, w), y.reshape(h, w)


def padded(camera: Camera, pad: int) -> Camera:
    """The same pinhole with `pad` more pixels on every side."""
    return Camera(camera.c2w, camera.fl_x, camera.fl_y, camera.cx + pad, camera.cy + pad, camera.width + 2 * pad,
                  camera.height + 2 * pad)


def distorted_photo(render: Any, camera: Camera, distortion: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """(linear radiance [H, W, 3], coverage [H, W] bool) of the distorted photo: `render(pinhole)` returns a padded
    pinhole's (linear [H', W', 3], coverage [H', W']), resampled at the distorted pixels' positions."""
    import cv2

    x, y = distort_maps(camera, distortion)
    reach = max(-x.min(), -y.min(), x.max() - camera.width, y.max() - camera.height, 0.0)
    pad = int(math.ceil(reach)) + 2
    linear, cover = render(padded(camera, pad))
    mx, my = (x + pad - 0.5).astype(np.float32), (y + pad - 0.5).astype(np.float32)
    img = np.stack([cv2.remap(np.ascontiguousarray(linear[:, :, c], np.float32), mx, my, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE) for c in range(3)], axis=2)
    mask = cv2.remap(cover.astype(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE) > 0
    return img.astype(np.float32), mask


def write_jpeg(path: Path, display: np.ndarray, quality: int = JPEG_QUALITY) -> None:
    """display [H, W, 3] in [0, 1] -> 8-bit JPEG (4:4:4, so colours keep full resolution)."""
    from PIL import Image

    pixels = (np.clip(display, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    Image.fromarray(pixels).save(path, quality=quality, subsampling=0, optimize=False)


def _link(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def settings(object_dir: Path, cfg: RandomPoseConfig) -> dict[str, Any]:
    meta = json.loads((object_dir / "meta.json").read_text())
    resolution = cfg.resolution or int(meta["content"]["resolution"])
    return {"format": FORMAT, "object": meta["id"], "object_tree_sha256": meta.get("tree_sha256", ""),
            "basis_sha256": meta["basis"]["sha256"], "photos": cfg.photos, "resolution": resolution, "spp": cfg.spp,
            "max_bounces": cfg.max_bounces, "exposure_stops": cfg.exposure_stops, "lens": cfg.lens,
            "jpeg_quality": JPEG_QUALITY}


def write_random_pose(object_dir: str | Path, cfg: RandomPoseConfig) -> bool:
    """Write (or keep) `object_dir`/random_pose/; True when it was made, False when it was already there."""
    from neumatex_core.capture import load_capture
    from neumatex_core.eval.references import harness_envmap, object_spec_from_json, truth_field
    from neumatex_core.geometry.mesh import load_mesh
    from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
    from neumatex_core.render.scene import Scene

    object_dir = Path(object_dir)
    out = object_dir / "random_pose"
    want = settings(object_dir, cfg)
    have = json.loads((out / "settings.json").read_text()) if (out / "settings.json").is_file() else None
    if (out / "transforms.json").is_file() and have is not None:
        if have == want:
            return False
        raise ValueError(f"{out} was made with other settings ({have}); delete it to remake it")
    if out.exists() and have != want:
        shutil.rmtree(out)  # an interrupted run with other settings: start the object again
    # else an interrupted run with these settings: its finished photos are kept (each photo's pixels depend only on
    # the object's seeds and its index, so the capture is the same as one made in one go)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "settings.json", want)
    meta = json.loads((object_dir / "meta.json").read_text())
    spec = object_spec_from_json(meta["spec"])
    field = truth_field(object_dir)
    top = json.loads((object_dir / "transforms.json").read_text())
    mesh = load_mesh(object_dir / "mesh.obj")  # what truth_field and the object's renders use
    with load_capture(object_dir) as cap:
        env = harness_envmap(cap)
    scene = Scene(mesh, env, field)
    tracer = PathTracer(PathTracerConfig(max_bounces=cfg.max_bounces, spp=cfg.spp))
    rng = np.random.default_rng(np.random.SeedSequence([spec.photo_seed, POSE_SALT]))
    cams = random_pose_cameras(rng, cfg.photos, want["resolution"])
    exposures = [float(2.0 ** rng.uniform(-cfg.exposure_stops, cfg.exposure_stops)) for _ in cams]
    k1, k2 = rng.uniform(-1.0, 1.0, 2) * np.array([cfg.lens, cfg.lens / 3])
    lens = Distortion(k1=round(float(k1), 6), k2=round(float(k2), 6))
    for name in ("mesh.obj", top["envmap"]):
        if not (out / name).is_file():
            _link(object_dir / name, out / name)
    (out / "images").mkdir(exist_ok=True)
    (out / "masks").mkdir(exist_ok=True)
    frames = []
    for k, (cam, exposure) in enumerate(zip(cams, exposures, strict=True)):
        frames.append({"file_path": f"images/{k:03d}.jpg", "mask_path": f"masks/{k:03d}.png", "exposure": exposure,
                       "transform_matrix": cam.c2w.tolist()})  # fmt: skip
        if (out / frames[-1]["file_path"]).is_file():  # made before an interruption (written last, atomically)
            continue
        seed = int(np.random.SeedSequence([spec.render_seed, RENDER_SALT, k]).generate_state(1)[0])

        def render(pinhole: Camera, seed: int = seed) -> tuple[np.ndarray, np.ndarray]:
            with torch.no_grad():
                image = tracer.render(scene, pinhole, seed=seed).cpu().numpy()
            return image, render_gbuffer(mesh, pinhole, scene.raycaster).mask.numpy()

        linear, mask = distorted_photo(render, cam, lens)
        with replaced_atomically(out / frames[-1]["mask_path"]) as tmp:
            write_image(tmp, mask.astype(np.float32)[:, :, None])
        with replaced_atomically(out / frames[-1]["file_path"]) as tmp:  # the photo last: its file marks it done
            write_jpeg(tmp, Tonemap(exposure=exposure).apply_numpy(linear))
    cam0 = cams[0]
    transforms = {"camera_model": "OPENCV", "fl_x": cam0.fl_x, "fl_y": cam0.fl_y, "cx": cam0.cx, "cy": cam0.cy,
                  "w": cam0.width, "h": cam0.height, "k1": lens.k1, "k2": lens.k2, "p1": 0.0, "p2": 0.0,
                  "mesh": "mesh.obj", "envmap": top["envmap"], "envmap_to_world": top["envmap_to_world"],
                  "envmap_scale": top["envmap_scale"], "tonemap": top["tonemap"], "frames": frames}  # fmt: skip
    write_json_atomic(out / "transforms.json", transforms)
    return True


def run_random_pose(cfg: RandomPoseConfig) -> int:
    """The CLI command: every selected object of cfg.data; prints what was made."""
    import time

    from neumatex_core.eval.suite import select_objects

    torch.set_num_threads(cfg.threads)
    data = Path(cfg.data)
    made, kept = [], 0
    t0 = time.perf_counter()
    for obj in select_objects(data, cfg.objects):
        if write_random_pose(data / obj, cfg):
            made.append(obj)
            print(f"{obj}: wrote {data / obj / 'random_pose'} ({cfg.photos} photos)", flush=True)
        else:
            kept += 1
    print(f"made {len(made)} random-pose captures, {kept} already there, in {time.perf_counter() - t0:.1f} s")
    return 0
