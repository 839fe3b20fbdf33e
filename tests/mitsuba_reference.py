"""Mitsuba 3 reference renders of our scenes (test-only; the torch path tracer is checked against these).

Everything is built from our own objects so both renderers see identical data:

- geometry: `mi.Mesh` filled through `mi.traverse` from `Mesh.vertices` / `Mesh.faces`, with
  `Mesh.vertex_normals` as Mitsuba vertex normals when present, otherwise flat face normals;
- lighting: Mitsuba's `envmap` emitter built from `EnvironmentMap.texels` (already clamped and scaled) as an
  `mi.Bitmap`, with `to_world` from `EnvironmentMap.to_world`;
- camera: a `perspective` sensor with `to_world = c2w @ diag(-1, 1, -1, 1)` (Mitsuba's camera looks down +Z
  with +X to the left of the image, ours down -Z with +X to the right), horizontal `fov` from fl_x and the
  width, the principal point offset from cx, cy; an `hdrfilm` with a box filter and no border samples (each
  sample is uniformly jittered inside its own pixel, exactly like `Camera.generate_rays`);
- materials: `{"kind": "diffuse", "base_color": (r, g, b)}` -> `diffuse`; `{"kind": "conductor",
  "roughness": r}` -> `roughconductor` (GGX, alpha = r^2, Fresnel = 1, white), both inside `twosided`;
- integrator: `path` with max_depth = bounces + 1 (Mitsuba counts the segment that reaches the emitter: its
  max_depth 2 is direct lighting only, our 1 bounce), Russian roulette pushed out of reach, emitters visible.

Known behaviour difference (docs/architecture.md section 4, "Measured pitfalls"): pixels where an interpolated (smooth)
shading normal faces away from the camera while the geometric normal faces it (silhouettes of low-poly
meshes). What Mitsuba does there depends on the BSDF wrapper (measured, see test_mitsuba_conventions.py):
a single-sided BSDF returns black; inside `twosided` (what these references use) Mitsuba shades the "back
side", i.e. mirrors w_i and w_o through the shading tangent plane, which is the same as shading with the
shading normal flipped to the camera side by its own sign (-n_s), light from behind the geometric surface
included. Either way it is not what a renderer that orients normals by the geometric normal computes, so
comparisons exclude those pixels, found with `shading_normal_backfacing_mask` (pixel centres, both normals
first flipped to the camera side by the geometric normal). Flat-shaded meshes have no such pixels.

Mitsuba's llvm variants need a libLLVM that can select `fminimum` (Debian's libLLVM 15 aborts with "LLVM
ERROR: Cannot select: fminimum"); `load_mitsuba` points DRJIT_LIBLLVM_PATH at libLLVM 19 when it is there.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.lighting.envmap import EnvironmentMap

VARIANT = "llvm_ad_rgb"
LIBLLVM_19 = Path("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")
RR_DEPTH_OFF = 100  # Russian roulette starts after this many segments: never, for our bounce counts

_MI: Any = None

# Mitsuba's camera frame (+X left, +Y up, +Z forward) seen from ours (+X right, +Y up, -Z forward).
_FLIP_XZ = np.diag([-1.0, 1.0, -1.0, 1.0])


def load_mitsuba() -> Any:
    """The `mitsuba` module with the `llvm_ad_rgb` variant set (cached)."""
    global _MI
    if _MI is None:
        if "DRJIT_LIBLLVM_PATH" not in os.environ and LIBLLVM_19.is_file():
            os.environ["DRJIT_LIBLLVM_PATH"] = str(LIBLLVM_19)
        import mitsuba as mi

        mi.set_variant(VARIANT)
        _MI = mi
    return _MI


def mitsuba_mesh(mesh: Mesh, bsdf: Any = None) -> Any:
    """A Mitsuba mesh with our vertices, faces and (optional) vertex normals; `bsdf` a loaded Mitsuba BSDF."""
    mi = load_mitsuba()
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    smooth = mesh.vertex_normals is not None
    m = mi.Mesh(
        "neumatex_mesh",
        vertex_count=int(mesh.vertices.shape[0]),
        face_count=int(mesh.faces.shape[0]),
        props=props,
        has_vertex_normals=smooth,
        has_vertex_texcoords=False,
    )
    params = mi.traverse(m)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(mesh.vertices, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel())
    if smooth:
        assert mesh.vertex_normals is not None
        normals = np.ascontiguousarray(mesh.vertex_normals, dtype=np.float32)
        params["vertex_normals"] = mi.Float(normals.ravel())
    params.update()
    return m


def mitsuba_bsdf_dict(material: dict[str, Any]) -> dict[str, Any]:
    """The Mitsuba BSDF (as a load_dict dictionary, wrapped in `twosided` unless the material dict says
    `"twosided": False`) for one of our material dicts."""
    kind = material.get("kind")
    inner: dict[str, Any]
    if kind == "diffuse":
        r, g, b = (float(c) for c in material["base_color"])
        inner = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [r, g, b]}}
    elif kind == "conductor":
        rough = float(material["roughness"])
        inner = {
            "type": "roughconductor",
            "distribution": "ggx",
            "alpha": rough * rough,  # UE4 / Disney mapping
            "material": "none",  # Fresnel = 1: white metal, our Schlick F with F0 = 1
            "specular_reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
        }
    else:
        raise ValueError(f"unknown material kind {kind!r} (expected 'diffuse' or 'conductor')")
    if not material.get("twosided", True):  # only for tests of Mitsuba's own behaviour
        return inner
    return {"type": "twosided", "bsdf": inner}


def mitsuba_envmap_dict(envmap: EnvironmentMap) -> dict[str, Any]:
    """Mitsuba `envmap` emitter from our map's (clamped, scaled) texels and rotation."""
    mi = load_mitsuba()
    texels = np.ascontiguousarray(envmap.texels.detach().cpu().numpy(), dtype=np.float32)
    to_world = np.eye(4)
    to_world[:3, :3] = envmap.to_world.detach().cpu().numpy().astype(np.float64)
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(texels, mi.Bitmap.PixelFormat.RGB),
        "to_world": mi.ScalarTransform4f(to_world),
    }


def mitsuba_scene(mesh: Mesh, envmap: EnvironmentMap, material: dict[str, Any]) -> Any:
    """A Mitsuba scene: our mesh with `material`, lit by our environment map (no sensor, no integrator)."""
    mi = load_mitsuba()
    bsdf = mi.load_dict(mitsuba_bsdf_dict(material))
    return mi.load_dict(
        {"type": "scene", "mesh": mitsuba_mesh(mesh, bsdf), "emitter": mitsuba_envmap_dict(envmap)}
    )


def mitsuba_sensor_dict(camera: Camera, spp: int, seed: int = 0) -> dict[str, Any]:
    """Perspective sensor dictionary reproducing `camera` (rays and pixel footprints) exactly."""
    mi = load_mitsuba()
    w, h = int(camera.width), int(camera.height)
    if not math.isclose(camera.fl_x, camera.fl_y, rel_tol=1e-6):
        raise ValueError(
            f"Mitsuba's perspective sensor needs square pixels; fl_x={camera.fl_x} fl_y={camera.fl_y}"
        )
    fov_x = math.degrees(2.0 * math.atan(w / (2.0 * camera.fl_x)))
    to_world = np.asarray(camera.c2w, dtype=np.float64) @ _FLIP_XZ
    return {
        "type": "perspective",
        "fov": fov_x,
        "fov_axis": "x",
        # Offsets are fractions of the film width / height; a positive offset moves the principal point
        # left / up in the image, hence (centre - c) (measured: the tests check an off-centre camera).
        "principal_point_offset_x": (w / 2.0 - camera.cx) / w,
        "principal_point_offset_y": (h / 2.0 - camera.cy) / h,
        "near_clip": 1e-3,
        "far_clip": 1e5,
        "to_world": mi.ScalarTransform4f(to_world),
        "film": {
            "type": "hdrfilm",
            "width": w,
            "height": h,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "sample_border": False,
        },
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
    }


def mitsuba_sensor(camera: Camera, spp: int, seed: int = 0) -> Any:
    """Loaded Mitsuba perspective sensor matching `camera` (see `mitsuba_sensor_dict`)."""
    return load_mitsuba().load_dict(mitsuba_sensor_dict(camera, spp, seed))


def mitsuba_integrator(max_bounces: int) -> Any:
    """`path` integrator for `max_bounces` bounces (our count), no Russian roulette, emitters shown."""
    if max_bounces < 1:
        raise ValueError("max_bounces must be >= 1")
    return load_mitsuba().load_dict(
        {"type": "path", "max_depth": int(max_bounces) + 1, "rr_depth": RR_DEPTH_OFF, "hide_emitters": False}
    )


class MitsubaRenderer:
    """One scene, sensor and integrator kept loaded; repeated renders reuse Mitsuba's compiled kernels."""

    def __init__(
        self, mesh: Mesh, envmap: EnvironmentMap, camera: Camera, material: dict[str, Any], max_bounces: int,
        spp: int,
    ) -> None:
        self.mi = load_mitsuba()
        self.scene = mitsuba_scene(mesh, envmap, material)
        self.sensor = mitsuba_sensor(camera, spp)
        self.integrator = mitsuba_integrator(max_bounces)
        self.spp = int(spp)

    def render(self, seed: int) -> np.ndarray:
        """[H, W, 3] float32 linear radiance (box-filtered mean of `spp` samples per pixel)."""
        img = self.mi.render(
            self.scene, sensor=self.sensor, integrator=self.integrator, spp=self.spp, seed=int(seed)
        )
        return np.array(img, dtype=np.float32)[:, :, :3]


def render_mitsuba(
    mesh: Mesh, envmap: EnvironmentMap, camera: Camera, material: dict[str, Any], max_bounces: int,
    spp: int, seed: int = 0,
) -> np.ndarray:
    """Mitsuba's render of our scene: [H, W, 3] float32 linear radiance."""
    return MitsubaRenderer(mesh, envmap, camera, material, max_bounces, spp).render(seed)


def render_mitsuba_batches(
    mesh: Mesh, envmap: EnvironmentMap, camera: Camera, material: dict[str, Any], max_bounces: int,
    n_batches: int, spp_per_batch: int, seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """`n_batches` independent renders (seeds seed, seed+1, ...): per-pixel mean [H, W, 3] and the standard
    error of that mean [H, W, 3] from the spread of the batches (needs n_batches >= 2)."""
    if n_batches < 2:
        raise ValueError("need at least 2 batches to estimate a standard error")
    renderer = MitsubaRenderer(mesh, envmap, camera, material, max_bounces, spp_per_batch)
    batches = np.stack([renderer.render(seed + k) for k in range(n_batches)]).astype(np.float64)
    mean = batches.mean(axis=0)
    stderr = batches.std(axis=0, ddof=1) / math.sqrt(n_batches)
    return mean.astype(np.float32), stderr.astype(np.float32)


def mitsuba_forward_paths_per_second(
    mesh: Mesh, envmap: EnvironmentMap, camera: Camera, material: dict[str, Any], max_bounces: int, spp: int,
) -> float:
    """Camera paths per second of Mitsuba's path tracer on this scene (one warm-up render excluded, which
    holds the JIT compilation; the timed render includes the conversion to numpy)."""
    renderer = MitsubaRenderer(mesh, envmap, camera, material, max_bounces, spp)
    renderer.render(seed=0)
    start = time.perf_counter()
    renderer.render(seed=1)
    elapsed = time.perf_counter() - start
    return camera.width * camera.height * spp / max(elapsed, 1e-12)


def mitsuba_ray_queries_per_second(mesh: Mesh, n_rays: int, seed: int = 0) -> float:
    """Closest-hit queries per second (`ray_intersect_preliminary`) on random rays from a sphere of radius 3
    towards random points of the unit ball; numpy in and out included, warm-up (JIT) excluded."""
    mi = load_mitsuba()
    scene = mi.load_dict({"type": "scene", "mesh": mitsuba_mesh(mesh)})
    rng = np.random.default_rng(seed)

    def rays() -> tuple[np.ndarray, np.ndarray]:
        o = rng.normal(size=(n_rays, 3))
        o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
        t = rng.normal(size=(n_rays, 3))
        t = t / np.linalg.norm(t, axis=1, keepdims=True) * rng.uniform(0, 1, (n_rays, 1)) ** (1 / 3)
        d = t - o
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        return o.astype(np.float32), d.astype(np.float32)

    def query(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        pi = scene.ray_intersect_preliminary(ray)
        return np.array(pi.t), np.array(pi.prim_index)

    query(*rays())  # warm-up: compiles the kernel
    o, d = rays()
    start = time.perf_counter()
    query(o, d)
    elapsed = time.perf_counter() - start
    return n_rays / max(elapsed, 1e-12)


def shading_normal_backfacing_mask(mesh: Mesh, camera: Camera) -> np.ndarray:
    """[H, W] bool: pixels whose centre ray hits the mesh where the interpolated shading normal faces away
    from the camera although the geometric normal faces it (both first flipped to the camera side by the
    geometric normal); Mitsuba renders those black. All False for flat shading."""
    from neumatex_core.geometry.raycast import RayCaster

    h, w = camera.height, camera.width
    if mesh.vertex_normals is None:
        return np.zeros((h, w), dtype=bool)
    jj, ii = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                            indexing="ij")
    o, d = camera.rays_for_pixels(ii.reshape(-1) + 0.5, jj.reshape(-1) + 0.5)
    hits = RayCaster(mesh).intersect(o, d)
    valid = hits.valid.numpy()
    tri = hits.tri.numpy()[valid]
    b = hits.bary.numpy()[valid].astype(np.float64)
    dirs = d.numpy()[valid].astype(np.float64)
    ng = mesh.face_normals()[tri].astype(np.float64)
    vn = mesh.vertex_normals.astype(np.float64)[mesh.faces[tri]]  # [N, 3 vertices, 3]
    ns = (1.0 - b[:, 0:1] - b[:, 1:2]) * vn[:, 0] + b[:, 0:1] * vn[:, 1] + b[:, 1:2] * vn[:, 2]
    ns = ns / np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-30)
    side = np.where(np.sum(ng * -dirs, axis=1) < 0.0, -1.0, 1.0)[:, None]
    ns = ns * side
    mask = np.zeros(h * w, dtype=bool)
    mask[np.flatnonzero(valid)] = np.sum(ns * -dirs, axis=1) <= 0.0
    return mask.reshape(h, w)
