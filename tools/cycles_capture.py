"""Blender Cycles captures in the NeuMatEx capture format (docs/capture-format.md): an outside renderer in the loop.

Runs under `.venv-cycles/bin/python` (`make cycles-env`: bpy from PyPI and its numpy; no torch, no neumatex_core).
The cameras come from a JSON file written in the main venv (`neumatex_core.synth.cycles.write_cameras_json`: the 23
preset views of `preset_views(resolution)` and seeded random views, exactly as the project computes them), so this
script only converts conventions and renders:

    .venv/bin/python -m neumatex_core.synth.cycles --mesh M.obj --envmap E.exr --preset coat --out DIR  # both steps
    .venv-cycles/bin/python tools/cycles_capture.py --mesh M.obj --envmap E.exr --cameras cams.json \
        --preset coat --out DIR [--spp 256 --views all --random 8 --relight C.exr F.exr@90 --threads 1]

(file paths here; the main-venv entry also takes the bare names of shared meshes and maps).

Output (the layout of a synthetic object, neumatex_core/synth/writer.py):

```
DIR/
  transforms.json      the 23 preset views, or those of --views (frame keys view, linear_path; envmap_to_world,
                       envmap_scale, tonemap; intrinsics per frame and, from the first, at the top level)
  mesh.obj             the mesh normalised into the unit sphere (bounding-box centre, farthest vertex at radius 1:
                       Mesh.normalized), positions and triangles only; every render used exactly these float32 values
  envmap.exr           the map, byte for byte
  images/000.png ...   tonemapped (exposure 1, sRGB OETF), 8-bit;  linear/000.exr ...: Cycles' linear float32 RGB
  masks/000.png ...    coverage at pixel centres (white = object)
  photos/              a capture of the random views (same mesh and lighting)
  relight/<j>/         a capture of the 17 orbital views (views 0..16; those of --views) under held-out map j
  cycles.json          Blender version, Principled BSDF preset and inputs, render settings, conventions, timings
```

Conventions (each is checked against our path tracer by bench/cycles_agreement.py):

- Axes. Our world is +Y up, Blender's +Z up. A point p of ours is placed at A p in Blender, with
  A = [[1, 0, 0], [0, 0, -1], [0, 1, 0]] (+90 degrees about X: +Y -> +Z, +Z -> -Y). Mesh vertices, normals and
  camera-to-world matrices ([[A, 0], [0, 1]] @ c2w) are converted with it. Blender cameras use the same local axes
  as ours (OpenGL: +X right, +Y up, -Z forward), so the camera matrix needs nothing else.
- Intrinsics. sensor_fit HORIZONTAL, lens = fl_x * sensor_width / w; a principal point off the centre becomes
  shift_x = (w/2 - cx) / max(w, h), shift_y = (cy - h/2) / max(w, h); fl_x must equal fl_y (square pixels).
  (Checked with an off-centre principal point and an 80 x 64 image: the background agrees to 65-68 dB.)
- Environment map. Our lookup (Mitsuba's `envmap`) takes a world direction d to the map frame,
  l = envmap_to_world^T d, and reads u = atan2(l_x, -l_z) / 2 pi, v = acos(l_y) / pi, bilinear, with columns at
  u = (i + 1/2) / W and rows at v = j / (H - 1). A Blender world direction d_b is our A^T d_b, so the world shader
  rotates it by envmap_to_world^T A^T (a Mapping node) and computes exactly that u, v with math nodes into an Image
  Texture (see CyclesScene.world); Background strength = envmap_scale. (Cycles' Environment Texture node would
  need the map-frame direction B l, B = [[0, 0, 1], [1, 0, 0], [0, 1, 0]], i.e. +90 degrees about Blender's Z
  for an identity envmap_to_world, and puts rows half a texel off Mitsuba's: measurably so near the poles.)
- Pixels. Box filter of width 1 pixel (uniform samples over the pixel, like our jittered rays), no denoising, no
  adaptive sampling, no clamping, no glossy filter, film not transparent (the map is seen behind the object),
  colour management Standard / exposure 0 / gamma 1 and float EXR output: the EXR holds scene-linear Rec.709
  radiance, the same quantity as our renders.
- Bounces. Our max_bounces counts surface interactions (1 = direct light only); Cycles' max_bounces counts the
  bounces after the first hit (0 = direct light only), so Cycles gets max_bounces - 1.
- Shading normals. Our loader gives every vertex the area-weighted mean of its faces' normals; Blender would
  weight by corner angle. We set exactly our normals as custom normals (smooth shading), and turn off the
  shadow-terminator offsets (ours spawns rays 1e-4 off the geometric surface).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import struct
import sys
import time
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

try:
    import bpy
    from mathutils import Matrix, Vector
    from mathutils.bvhtree import BVHTree
except ImportError:  # pragma: no cover - the main venv imports this module only to read its constants
    bpy = None

# -- conventions ------------------------------------------------------------------------------------------------
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # A: our world -> Blender world
SENSOR_WIDTH_MM = 36.0
TONEMAP = {"exposure": 1.0, "transfer": "srgb"}  # what the synthetic objects use (synth/writer.py TONEMAP)
TARGET_LUMINANCE = 0.6  # neumatex_core.synth.lighting.TARGET_LUMINANCE (the cameras JSON carries the live value)
LUMINANCE = (0.2126, 0.7152, 0.0722)
PHOTO_SEED_OFFSET = 100  # as in synth/writer.py
RELIGHT_SEED_OFFSET = 1000
ORBIT_VIEWS = 17

# Principled BSDF presets (Blender 4.x input names; colours are scene-linear Rec.709). "diffuse" is a pure
# Lambertian: roughness 1, Diffuse Roughness 0 (Lambert, not Oren-Nayar), Specular IOR Level 0 (no dielectric
# reflection at all, so the whole albedo goes to the diffuse lobe), no coat, sheen, metal or transmission.
PRESETS: dict[str, dict[str, Any]] = {
    "diffuse": {
        "description": "pure Lambertian (matches UniformPBR(base, roughness=1, metallic=0, dielectric_f0=0))",
        "inputs": {"Base Color": [0.8, 0.55, 0.35], "Metallic": 0.0, "Roughness": 1.0, "Diffuse Roughness": 0.0,
                   "Specular IOR Level": 0.0, "Coat Weight": 0.0, "Sheen Weight": 0.0},
    },
    "coat": {
        "description": "red dielectric base (roughness 0.5) under a smooth clear coat",
        "inputs": {"Base Color": [0.55, 0.04, 0.03], "Metallic": 0.0, "Roughness": 0.5, "IOR": 1.5,
                   "Specular IOR Level": 0.5, "Coat Weight": 1.0, "Coat Roughness": 0.03, "Coat IOR": 1.5,
                   "Coat Tint": [1.0, 1.0, 1.0]},
    },
    "sheen": {
        "description": "dark blue velvet: rough diffuse base with a white sheen",
        "inputs": {"Base Color": [0.1, 0.14, 0.42], "Metallic": 0.0, "Roughness": 0.9, "Specular IOR Level": 0.3,
                   "Sheen Weight": 1.0, "Sheen Roughness": 0.35, "Sheen Tint": [1.0, 1.0, 1.0]},
    },
    "metal": {
        "description": "hazy brass: a broad metallic lobe (roughness 0.4) with a sharp coat highlight over it",
        "inputs": {"Base Color": [0.86, 0.66, 0.34], "Metallic": 1.0, "Roughness": 0.4, "Coat Weight": 0.5,
                   "Coat Roughness": 0.06, "Coat IOR": 1.5, "Coat Tint": [1.0, 1.0, 1.0]},
    },
}


# -- small numpy helpers (no bpy) -----------------------------------------------------------------------------------
def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions [V, 3] float64 and triangles [F, 3] int64 (0-based) of an OBJ file.

    Only `v` and `f` lines are read; polygons are split into fans (v0, vi, vi+1); negative (relative) indices and
    `v/vt/vn` forms are understood; vertices no face uses are dropped (they would move the bounding box)."""
    verts: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                idx = []
                for p in parts[1:]:
                    k = int(p.split("/")[0])
                    idx.append(k - 1 if k > 0 else len(verts) + k)
                faces.extend((idx[0], idx[i], idx[i + 1]) for i in range(1, len(idx) - 1))
    v = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    fa = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if fa.size == 0 or fa.min() < 0 or fa.max() >= len(v):
        raise ValueError(f"{path}: no triangles, or face indices outside the {len(v)} vertices")
    used, inverse = np.unique(fa, return_inverse=True)
    return v[used], inverse.reshape(-1, 3).astype(np.int64)


def normalisation(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre [3], scale) into the unit sphere as neumatex_core's Mesh.normalization: centre of the bounding box,
    scale = 1 / distance of the farthest vertex from it (float32 like the project's Mesh)."""
    v = vertices.astype(np.float32)
    centre = ((v.min(axis=0) + v.max(axis=0)) / 2).astype(np.float32)
    radius = float(np.linalg.norm(v - centre, axis=1).max())
    return centre, 1.0 / max(radius, 1e-12)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Positions and triangles only, 9 significant digits (float32 round-trips exactly): synth/writer.py's format."""
    v = vertices.astype(np.float64).ravel()
    f = (faces.astype(np.int64) + 1).ravel()
    path.write_text("# NeuMatEx Cycles capture\n" + ("v %.9g %.9g %.9g\n" * vertices.shape[0]) % tuple(v)
                    + ("f %d %d %d\n" * faces.shape[0]) % tuple(f))  # fmt: skip


def area_weighted_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3] float32 unit vertex normals, the area-weighted sum of face normals: Mesh.with_smooth_normals, with the
    same arithmetic (float32 cross products, float64 sums, +Y for vertices whose faces are degenerate)."""
    v = vertices.astype(np.float32)[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    acc = np.zeros(vertices.shape, dtype=np.float64)
    for k in range(3):
        np.add.at(acc, faces[:, k], n)
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.where(length > 0, acc / np.maximum(length, 1e-30), [0.0, 1.0, 0.0]).astype(np.float32)


def yaw_rotation(degrees: float) -> np.ndarray:
    """[3, 3] rotation about +Y (an envmap_to_world), as neumatex_core.synth.lighting.yaw_rotation."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def mean_luminance(rgb: np.ndarray) -> float:
    """Solid-angle weighted mean luminance of an equirectangular map [H, W, 3] (negatives clamped), as
    neumatex_core.synth.lighting.mean_luminance."""
    rgb = np.maximum(rgb[:, :, :3].astype(np.float64), 0.0)
    h = rgb.shape[0]
    weight = np.sin(math.pi * (np.arange(h) + 0.5) / h)[:, None]
    lum = rgb @ np.asarray(LUMINANCE)
    return float((lum * weight).sum() / (weight.sum() * rgb.shape[1]))


def envmap_frame_rotation(envmap_to_world: np.ndarray) -> np.ndarray:
    """[3, 3] rotation of the world shader's Mapping node: a Blender world direction d_b -> the map's own frame
    (Mitsuba's, +Y up), envmap_to_world^T A^T d_b."""
    return np.asarray(envmap_to_world, dtype=np.float64).T @ Y_UP_TO_Z_UP.T


def srgb_tonemap(x: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """The capture tonemap T(x) = OETF_sRGB(clip(exposure x, 0, 1)) (capture/tonemap.py), float32 [..., 3]."""
    y = np.clip(x.astype(np.float32) * np.float32(exposure), 0.0, 1.0)
    power = 1.055 * np.power(np.maximum(y, 1e-12), 1.0 / 2.4) - 0.055
    return np.where(y <= 0.0031308, 12.92 * y, power).astype(np.float32)


def write_png(path: Path, pixels: np.ndarray) -> None:
    """8-bit PNG of float [H, W, C] (C = 1 grey, 3 RGB) in [0, 1], rounded like neumatex_core.imageio.write_image."""
    arr = np.asarray(pixels)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    h, w, c = arr.shape
    data = np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)
    raw = b"".join(b"\x00" + data[j].tobytes() for j in range(h))  # filter type 0 on every row

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    colour = {1: 0, 3: 2}[c]
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)


def pixel_rays(cam: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Ray origin [3] and unit directions [H*W, 3] through the pixel centres (row-major, top row first), in our
    world frame: Camera.rays_for_pixels with x = i + 0.5, y = j + 0.5."""
    h, w = int(cam["h"]), int(cam["w"])
    jj, ii = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    d_cam = np.stack([(ii - cam["cx"]) / cam["fl_x"], -(jj - cam["cy"]) / cam["fl_y"], -np.ones_like(ii)], -1)
    c2w = np.asarray(cam["c2w"], dtype=np.float64)
    d = d_cam.reshape(-1, 3) @ c2w[:3, :3].T
    return c2w[:3, 3], d / np.linalg.norm(d, axis=1, keepdims=True)


@contextmanager
def stdout_to_devnull() -> Iterator[None]:
    """Silence file descriptor 1 (Blender's render log is printed by C code, not through sys.stdout)."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


# -- the Blender scene -------------------------------------------------------------------------------------------
class CyclesScene:
    """One Blender scene: the mesh with a Principled BSDF, one camera, a world per environment map, Cycles settings.

    vertices [V, 3] float32 and faces [F, 3] are in OUR world frame (+Y up, unit sphere); everything handed to
    Blender goes through Y_UP_TO_Z_UP.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, inputs: dict[str, Any], spp: int, max_bounces: int,
                 threads: int) -> None:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self.vertices, self.faces = vertices, faces
        self._setup_render(spp, max_bounces, threads)
        self.obj = self._add_mesh(vertices, faces, inputs)
        cam_data = bpy.data.cameras.new("camera")
        self.camera = bpy.data.objects.new("camera", cam_data)
        self.scene.collection.objects.link(self.camera)
        self.scene.camera = self.camera
        self.worlds: dict[str, Any] = {}
        self._bvh = BVHTree.FromPolygons([tuple(map(float, p)) for p in vertices], faces.tolist(), all_triangles=True)

    def _setup_render(self, spp: int, max_bounces: int, threads: int) -> None:
        s = self.scene
        s.render.engine = "CYCLES"
        c = s.cycles
        c.device = "CPU"
        c.samples = spp
        c.use_adaptive_sampling = False
        c.use_denoising = False
        c.use_preview_denoising = False
        c.pixel_filter_type = "BOX"
        c.filter_width = 1.0  # pixels: uniform samples over the pixel footprint
        c.max_bounces = max(0, max_bounces - 1)  # Cycles counts bounces after the first hit
        c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = c.max_bounces
        c.volume_bounces = 0
        c.transparent_max_bounces = 8
        c.sample_clamp_direct = 0.0
        c.sample_clamp_indirect = 0.0
        c.blur_glossy = 0.0
        c.caustics_reflective = c.caustics_refractive = True
        c.light_sampling_threshold = 0.0
        c.use_guiding = False
        c.film_exposure = 1.0
        c.use_animated_seed = False
        s.render.film_transparent = False
        s.render.threads_mode = "FIXED"
        s.render.threads = max(1, threads)
        s.render.use_persistent_data = True
        s.render.use_compositing = False
        s.render.use_sequencer = False
        s.render.dither_intensity = 0.0
        s.render.resolution_percentage = 100
        s.render.pixel_aspect_x = s.render.pixel_aspect_y = 1.0
        s.view_settings.view_transform = "Standard"
        s.view_settings.look = "None"
        s.view_settings.exposure = 0.0
        s.view_settings.gamma = 1.0
        s.display_settings.display_device = "sRGB"
        fmt = s.render.image_settings
        fmt.file_format = "OPEN_EXR"
        fmt.color_depth = "32"
        fmt.color_mode = "RGB"
        fmt.exr_codec = "ZIP"

    def _add_mesh(self, vertices: np.ndarray, faces: np.ndarray, inputs: dict[str, Any]) -> Any:
        me = bpy.data.meshes.new("object")
        vb = (vertices.astype(np.float64) @ Y_UP_TO_Z_UP.T).astype(np.float32)
        me.vertices.add(len(vb))
        me.vertices.foreach_set("co", vb.ravel())
        me.loops.add(faces.size)
        me.loops.foreach_set("vertex_index", faces.astype(np.int32).ravel())
        me.polygons.add(len(faces))
        me.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
        me.polygons.foreach_set("use_smooth", np.ones(len(faces), dtype=bool))
        me.update(calc_edges=True)
        normals = area_weighted_normals(vertices, faces).astype(np.float64) @ Y_UP_TO_Z_UP.T
        me.normals_split_custom_set_from_vertices([tuple(map(float, n)) for n in normals])
        obj = bpy.data.objects.new("object", me)
        obj.shadow_terminator_geometry_offset = 0.0
        obj.shadow_terminator_shading_offset = 0.0
        obj.shadow_terminator_normal_offset = 0.0
        self.scene.collection.objects.link(obj)
        mat = bpy.data.materials.new("material")
        mat.use_nodes = True
        bsdf = mat.node_tree.nodes["Principled BSDF"]
        bsdf.distribution = "MULTI_GGX"  # Blender's default, written down in cycles.json
        bsdf.subsurface_method = "RANDOM_WALK"
        for name, value in inputs.items():
            socket = bsdf.inputs[name]
            if isinstance(value, list | tuple):
                value = list(value) + [1.0] * (len(socket.default_value) - len(value))
            socket.default_value = value
        me.materials.append(mat)
        return obj

    def world(self, envmap: Path, envmap_to_world: np.ndarray, scale: float) -> Any:
        """A world (made once per map, rotation and scale) that looks the map up exactly as our EnvironmentMap does.

        Node graph: Texture Coordinate `Generated` (the world shader's ray direction, Blender frame) -> Mapping
        (VECTOR, rotation `envmap_frame_rotation`: into the map's own Y-up frame) -> u = atan2(x, -z) / 2 pi,
        v = acos(y) / pi (Mitsuba) -> image coordinates s = u, t = (H - 1/2 - v (H - 1)) / H -> Image Texture
        (bilinear, REPEAT) -> Background (strength = envmap_scale). s = u puts column i's centre at u = (i + 1/2) / W
        and t puts row j (j = 0 the file's top row) at v = j / (H - 1), Mitsuba's texel placement; Cycles' own
        Environment Texture node would put rows at pixel centres, half a texel off (visible near the poles).
        """
        key = f"{envmap}|{np.round(envmap_to_world, 12).tolist()}|{scale!r}"
        if key in self.worlds:
            return self.worlds[key]
        w = bpy.data.worlds.new(f"world{len(self.worlds)}")
        w.use_nodes = True
        nodes, links = w.node_tree.nodes, w.node_tree.links
        nodes.clear()
        image = bpy.data.images.load(str(envmap), check_existing=True)
        image.colorspace_settings.name = "Linear Rec.709"  # scene linear: texels used as stored
        width, height = (int(x) for x in image.size)

        def op(kind: str, a: Any, b: Any = None, c: Any = None) -> Any:
            node = nodes.new("ShaderNodeMath")
            node.operation = kind
            for k, value in enumerate((a, b, c)):
                if value is None:
                    continue
                if isinstance(value, float | int):
                    node.inputs[k].default_value = float(value)
                else:
                    links.new(value, node.inputs[k])
            return node.outputs["Value"]

        coord = nodes.new("ShaderNodeTexCoord")
        mapping = nodes.new("ShaderNodeMapping")
        mapping.vector_type = "VECTOR"
        rotation = Matrix(envmap_frame_rotation(envmap_to_world).tolist()).to_euler("XYZ")
        mapping.inputs["Rotation"].default_value = rotation
        links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
        xyz = nodes.new("ShaderNodeSeparateXYZ")
        links.new(mapping.outputs["Vector"], xyz.inputs["Vector"])
        minus_z = op("MULTIPLY", xyz.outputs["Z"], -1.0)
        u = op("MULTIPLY", op("ARCTAN2", xyz.outputs["X"], minus_z), 0.5 / math.pi)
        theta = op("ARCCOSINE", xyz.outputs["Y"])  # Cycles clamps the argument to [-1, 1]
        t = op("MULTIPLY_ADD", theta, -(height - 1) / (math.pi * height), (height - 0.5) / height)
        st = nodes.new("ShaderNodeCombineXYZ")
        links.new(u, st.inputs["X"])
        links.new(t, st.inputs["Y"])
        tex = nodes.new("ShaderNodeTexImage")
        tex.image = image
        tex.interpolation = "Linear"
        tex.projection = "FLAT"
        tex.extension = "REPEAT"  # wraps u; t stays inside the first and last rows' centres
        links.new(st.outputs["Vector"], tex.inputs["Vector"])
        bg = nodes.new("ShaderNodeBackground")
        bg.inputs["Strength"].default_value = float(scale)
        out = nodes.new("ShaderNodeOutputWorld")
        links.new(tex.outputs["Color"], bg.inputs["Color"])
        links.new(bg.outputs["Background"], out.inputs["Surface"])
        w.cycles.sampling_method = "MANUAL"
        w.cycles.sample_map_resolution = width  # importance map at the map's own resolution
        self.worlds[key] = w
        return w

    def set_camera(self, cam: dict[str, Any]) -> None:
        """Place the Blender camera as our camera: c2w [4, 4] (OpenGL axes, our world), intrinsics in pixels."""
        w, h = int(cam["w"]), int(cam["h"])
        if abs(cam["fl_x"] - cam["fl_y"]) > 1e-6 * cam["fl_x"]:
            raise ValueError(f"fl_x {cam['fl_x']} != fl_y {cam['fl_y']}: only square pixels are supported")
        r = self.scene.render
        r.resolution_x, r.resolution_y = w, h
        data = self.camera.data
        data.type = "PERSP"
        data.sensor_fit = "HORIZONTAL"
        data.sensor_width = SENSOR_WIDTH_MM
        data.lens = float(cam["fl_x"]) * SENSOR_WIDTH_MM / w
        data.shift_x = (w / 2 - float(cam["cx"])) / max(w, h)
        data.shift_y = (float(cam["cy"]) - h / 2) / max(w, h)
        data.clip_start, data.clip_end = 1e-3, 1e4
        a4 = np.eye(4)
        a4[:3, :3] = Y_UP_TO_Z_UP
        self.camera.matrix_world = Matrix((a4 @ np.asarray(cam["c2w"], dtype=np.float64)).tolist())

    def render(self, cam: dict[str, Any], world: Any, seed: int, exr: Path) -> np.ndarray:
        """Render `cam` under `world` into the float32 EXR `exr`; returns its pixels [H, W, 3] (top row first)."""
        self.set_camera(cam)
        self.scene.world = world
        self.scene.cycles.seed = int(seed)
        exr.parent.mkdir(parents=True, exist_ok=True)
        self.scene.render.filepath = str(exr)
        self.scene.render.use_file_extension = False
        with stdout_to_devnull():
            bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(str(exr), check_existing=False)
        try:
            w, h = img.size
            buf = np.empty(w * h * img.channels, dtype=np.float32)
            img.pixels.foreach_get(buf)
            pixels = buf.reshape(h, w, img.channels)[::-1, :, :3].copy()  # Blender rows run bottom-up
        finally:
            bpy.data.images.remove(img)
        return pixels

    def coverage(self, cam: dict[str, Any]) -> np.ndarray:
        """[H, W] bool: the ray through each pixel centre hits the mesh (our world frame, no Blender conversion)."""
        origin, dirs = pixel_rays(cam)
        o = Vector(tuple(map(float, origin)))
        hit = np.fromiter((self._bvh.ray_cast(o, Vector(tuple(d)))[0] is not None for d in dirs.tolist()),
                          dtype=bool, count=len(dirs))  # fmt: skip
        return hit.reshape(int(cam["h"]), int(cam["w"]))


def load_map_pixels(path: Path) -> np.ndarray:
    """[H, W, 3] float32 map pixels through Blender's image loader (top row first)."""
    img = bpy.data.images.load(str(path), check_existing=False)
    try:
        w, h = img.size
        buf = np.empty(w * h * img.channels, dtype=np.float32)
        img.pixels.foreach_get(buf)
        return buf.reshape(h, w, img.channels)[::-1, :, :3].copy()
    finally:
        bpy.data.images.remove(img)


# -- the capture ---------------------------------------------------------------------------------------------------
def _intrinsics(cam: dict[str, Any]) -> dict[str, Any]:
    return {k: (int(cam[k]) if k in ("w", "h") else float(cam[k])) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}


def _write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


class Lighting:
    """One environment: the map file, envmap_to_world [3, 3] (a yaw about +Y) and envmap_scale (> 0)."""

    def __init__(self, path: Path, yaw_deg: float, scale: float | None, target_luminance: float) -> None:
        self.path, self.yaw_deg = path, yaw_deg
        self.to_world = yaw_rotation(yaw_deg)
        if scale is None:  # normalised brightness, as the synthetic objects (lighting_scale with 0 stops)
            scale = float(f"{target_luminance / max(mean_luminance(load_map_pixels(path)), 1e-12):.6g}")
        self.scale = float(scale)

    def top(self) -> dict[str, Any]:
        """transforms.json's lighting fields (the map is copied as envmap<suffix>)."""
        return {"envmap": "envmap" + self.path.suffix.lower(), "envmap_to_world": self.to_world.tolist(),
                "envmap_scale": self.scale, "tonemap": dict(TONEMAP)}  # fmt: skip


def write_views(scene: CyclesScene, folder: Path, light: Lighting, cams: list[dict[str, Any]], names: list[str],
                seeds: list[int], views: list[str] | None, times: list[tuple[float, float]],
                log: bool) -> list[dict[str, Any]]:
    """Render `cams` into folder/{linear,images,masks}/<name>; returns the transforms.json frames.

    Appends (wall seconds, CPU seconds of this process) of each render to `times`."""
    world = scene.world(light.path, light.to_world, light.scale)
    frames = []
    for k, (cam, name, seed) in enumerate(zip(cams, names, seeds, strict=True)):
        start, cpu = time.perf_counter(), time.process_time()
        exr = f"linear/{name}.exr"
        pixels = scene.render(cam, world, seed, folder / exr)
        times.append((time.perf_counter() - start, time.process_time() - cpu))
        write_png(folder / f"images/{name}.png", srgb_tonemap(pixels, TONEMAP["exposure"]))
        write_png(folder / f"masks/{name}.png", scene.coverage(cam).astype(np.float32)[:, :, None])
        frame = {"file_path": f"images/{name}.png", "mask_path": f"masks/{name}.png", "linear_path": exr,
                 "transform_matrix": np.asarray(cam["c2w"], dtype=np.float64).tolist(), **_intrinsics(cam)}
        if views is not None:
            frame["view"] = views[k]
        frames.append(frame)
        if log:
            print(f"  {folder.name}/{name}: {times[-1][0]:.2f} s ({times[-1][1]:.2f} CPU s)", flush=True)
    return frames


def write_capture(args: argparse.Namespace) -> dict[str, Any]:
    """Build the scene and write the capture folder (see the module docstring); returns cycles.json's content."""
    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cameras = json.loads(Path(args.cameras).read_text())
    all_presets = cameras["preset"]
    if len(all_presets) != 23:
        raise ValueError(f"{args.cameras}: expected the 23 preset views, found {len(all_presets)}")
    chosen = list(range(23)) if args.views in ("", "all") else [int(k) for k in args.views.split(",")]
    preset_cams = [all_presets[k] for k in chosen]
    all_names = cameras.get("preset_names")
    random_cams = cameras.get("random", [])
    if args.random > len(random_cams):
        raise ValueError(f"{args.cameras} holds {len(random_cams)} random views; --random {args.random} asked")
    target = float(cameras.get("target_luminance", TARGET_LUMINANCE))
    preset = PRESETS[args.preset]
    inputs = dict(preset["inputs"])
    if args.base_color is not None:
        inputs["Base Color"] = list(args.base_color)

    raw_v, faces = read_obj(Path(args.mesh))
    centre, scale = normalisation(raw_v)
    write_obj(out / "mesh.obj", ((raw_v.astype(np.float32) - centre) * np.float32(scale)), faces)
    vertices, faces_rt = read_obj(out / "mesh.obj")  # exactly what a capture loader reads, as float32
    vertices = vertices.astype(np.float32)
    if faces_rt.shape != faces.shape:
        raise ValueError(f"{out / 'mesh.obj'}: re-read {len(faces_rt)} faces, wrote {len(faces)}")
    scene = CyclesScene(vertices, faces_rt, inputs, args.spp, args.max_bounces, args.threads)
    setup_s = time.perf_counter() - t0

    times: list[tuple[float, float]] = []
    light = Lighting(Path(args.envmap), args.envmap_yaw, args.envmap_scale, target)
    top = light.top()
    shutil.copyfile(light.path, out / top["envmap"])
    names = [f"{i:03d}" for i in chosen]
    view_names = [all_names[k] for k in chosen] if all_names else None
    frames = write_views(scene, out, light, preset_cams, names, [args.seed + i for i in chosen], view_names, times,
                         args.verbose)
    _write_json(out / "transforms.json", {**_intrinsics(preset_cams[0]), "mesh": "mesh.obj", **top, "frames": frames})

    if args.random:
        photos = out / "photos"
        _link(out / "mesh.obj", photos / "mesh.obj")
        _link(out / top["envmap"], photos / top["envmap"])
        cams = random_cams[: args.random]
        pnames = [f"{k:03d}" for k in range(len(cams))]
        seeds = [args.seed + PHOTO_SEED_OFFSET + k for k in range(len(cams))]
        pframes = write_views(scene, photos, light, cams, pnames, seeds, None, times, args.verbose)
        _write_json(photos / "transforms.json", {"mesh": "mesh.obj", **top, "frames": pframes})

    relights = []
    for j, spec in enumerate(args.relight):
        path, _, yaw = spec.partition("@")
        light_j = Lighting(Path(path), float(yaw or 0.0), None, target)
        folder = out / "relight" / str(j)
        top_j = light_j.top()
        _link(out / "mesh.obj", folder / "mesh.obj")
        shutil.copyfile(light_j.path, folder / top_j["envmap"])
        orbit = [k for k in chosen if k < ORBIT_VIEWS]
        seeds = [args.seed + RELIGHT_SEED_OFFSET * (j + 1) + v for v in orbit]
        rframes = write_views(scene, folder, light_j, [all_presets[k] for k in orbit], [f"{k:03d}" for k in orbit],
                              seeds, [all_names[k] for k in orbit] if all_names else None, times, args.verbose)
        _write_json(folder / "transforms.json", {"mesh": "mesh.obj", **top_j, "frames": rframes})
        relights.append({"map": Path(path).name, "envmap_yaw_deg": light_j.yaw_deg, "envmap_scale": light_j.scale})

    record = {
        "renderer": f"Blender {bpy.app.version_string} Cycles (bpy from PyPI), CPU",
        "preset": args.preset,
        "description": preset["description"],
        "principled_bsdf": {"distribution": "MULTI_GGX", "subsurface_method": "RANDOM_WALK", "inputs": inputs},
        "mesh": {"source": Path(args.mesh).name, "faces": int(len(faces)), "vertices": int(len(vertices)),
                 "normalisation": {"centre": [float(c) for c in centre], "scale": float(scale)}},
        "lighting": {"map": Path(args.envmap).name, "envmap_yaw_deg": args.envmap_yaw, "envmap_scale": light.scale,
                     "relight": relights},
        "render": {"spp": args.spp, "seed": args.seed, "pose_seed": cameras.get("random_seed"),
                   "max_bounces": args.max_bounces,
                   "cycles_max_bounces": scene.scene.cycles.max_bounces, "pixel_filter": "BOX 1 px",
                   "denoising": False, "adaptive_sampling": False, "clamping": 0.0, "blur_glossy": 0.0,
                   "view_transform": "Standard", "film_transparent": False, "threads": args.threads,
                   "world_sampling": "MANUAL, map resolution"},
        "conventions": {"y_up_to_z_up": Y_UP_TO_Z_UP.tolist(), "envmap_lookup": "Mitsuba envmap, math nodes",
                        "mapping_rotation": envmap_frame_rotation(light.to_world).tolist()},
        "views": {"preset": len(preset_cams), "random": args.random,
                  "relight": len(args.relight) * sum(k < ORBIT_VIEWS for k in chosen)},
        "timing": {"setup_s": round(setup_s, 3), "render_s": [round(t, 3) for t, _ in times],
                   "render_cpu_s": [round(c, 3) for _, c in times], "total_s": round(time.perf_counter() - t0, 3),
                   "total_cpu_s": round(time.process_time(), 3)},
    }  # fmt: skip
    _write_json(out / "cycles.json", record)
    return record


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="cycles_capture.py", description=__doc__.split("\n")[0])
    p.add_argument("--mesh", required=True, help="mesh file (OBJ; e.g. a shared mesh), any units and placement")
    p.add_argument("--envmap", required=True, help="equirectangular linear HDR map (EXR/HDR)")
    p.add_argument("--cameras", required=True,
                   help="cameras JSON from neumatex_core.synth.cycles.write_cameras_json (main venv)")
    p.add_argument("--out", required=True, help="capture folder to write")
    p.add_argument("--preset", choices=sorted(PRESETS), default="diffuse", help="Principled BSDF preset")
    p.add_argument("--base-color", type=float, nargs=3, default=None, help="override the preset's base colour")
    p.add_argument("--spp", type=int, default=256, help="samples per pixel")
    p.add_argument("--max-bounces", type=int, default=3, help="surface interactions per path (ours; 1 = direct)")
    p.add_argument("--views", default="all",
                   help="preset views to render: all, or indices such as 0,5,20 (file names keep the index)")
    p.add_argument("--random", type=int, default=0, help="random views to render into photos/")
    p.add_argument("--relight", nargs="*", default=[], metavar="MAP[@YAW]",
                   help="held-out maps (optional yaw in degrees): relight/<j>/ with the 17 orbital views")
    p.add_argument("--envmap-yaw", type=float, default=0.0, help="rotation of the map about +Y (degrees)")
    p.add_argument("--envmap-scale", type=float, default=None,
                   help="envmap_scale (default: normalised brightness, mean luminance 0.6 like the synthetic objects)")
    p.add_argument("--seed", type=int, default=0, help="Cycles seed of view 0 (view i: seed + i)")
    p.add_argument("--threads", type=int, default=1, help="Cycles render threads")
    p.add_argument("--verbose", action="store_true", help="one line per rendered view")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    if bpy is None:
        print("error: bpy is not importable: run this script with .venv-cycles/bin/python (make cycles-env)",
              file=sys.stderr)
        return 2
    args = parse_args(sys.argv[1:] if argv is None else argv)
    record = write_capture(args)
    n = sum(record["views"].values())
    print(f"wrote {args.out}: {n} views in {record['timing']['total_s']:.1f} s ({record['renderer']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
