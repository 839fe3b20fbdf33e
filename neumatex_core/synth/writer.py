"""One synthetic object -> one capture folder (docs/capture-format.md), with ground truth beside it.

```
<id>/
  transforms.json          the 23 preset views (17 orbital + 6 canonical): a valid capture / upload
  mesh.obj                 the object (normalised into the unit sphere), what every render used
  envmap.exr               the map (a shared map byte for byte, or a sky); transforms.json: envmap_to_world (a
                           yaw) and envmap_scale (exposure)
  images/000.png ...       tonemapped (the capture's tonemap: exposure 1, sRGB), 8-bit
  linear/000.exr ...       the same renders, linear HDR float32
  masks/000.png ...        coverage at pixel centres (white = object)
  gbuffers/000_position.exr, _normal.exr (world, unit, facing the camera), _basecolor.exr (rho_d),
          _latent.exr (6 channels l0..l5), _pbr.exr (5 channels: base colour, roughness, metallic), _region.exr
                           ground truth at pixel centres, zero where uncovered; no uncertainty (it is exact)
  layered/000.exr/.png     (optional) the same views with the analytic layered material: out of basis
  photos/                  a capture of `photos` extra views at random poses (same mesh and lighting)
  relight/<j>/             a capture of the 17 orbital views under held-out lighting j
  material.json            regions: family, parameters (named), base colours, latent, PBR fit levels
  meta.json                the object spec, shape parameters, lighting scales, file list with SHA-256 (last)
```

Renders use the path tracer with the ground-truth neural material (`ProceduralMaterialField`) and the seeds of
the spec (`ObjectSpec.render_seed`), on one thread, so the files depend only on the spec and the content options.
transforms.json frames carry extra keys (ignored by capture loaders): `view`, `linear_path`, `gbuffers`,
`layered_path`. The mesh and map of the sub-captures are hard links to the root's (copies where links fail).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.geometry.camera import PRESET_ORBIT_VIEWS, Camera, camera_from_fov, look_at, preset_views
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh, load_mesh
from neumatex_core.geometry.raycast import RayCaster
from neumatex_core.hashing import sha256_file
from neumatex_core.imageio import write_image
from neumatex_core.lighting.envmap import EnvironmentMap, envmap_rgb
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.layered import PARAMETER_NAMES
from neumatex_core.materials.neural_basis import LATENT_DIM, NeuralBasis, latent_channel_names
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.synth.config import SynthConfig
from neumatex_core.synth.lighting import LightingSpec, lighting_pixels, lighting_scale, yaw_rotation
from neumatex_core.synth.materials import PBR_LEVELS, ProceduralMaterialField, face_regions
from neumatex_core.synth.profile import StageTimes, TimedField, TimedRayCaster
from neumatex_core.synth.shapes import build_shape
from neumatex_core.synth.spec import ObjectSpec

CANONICAL_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")
GBUFFER_CHANNELS = {
    "position": ("X", "Y", "Z"),
    "normal": ("X", "Y", "Z"),
    "basecolor": ("R", "G", "B"),
    "latent": latent_channel_names(LATENT_DIM),
    "pbr": ("base_r", "base_g", "base_b", "roughness", "metallic"),
    "region": ("region",),
}
TONEMAP = Tonemap()
PHOTO_SEED_OFFSET = 100
RELIGHT_SEED_OFFSET = 1000


def view_names() -> list[str]:
    """Names of the 23 preset views: orbit_00 .. orbit_16, canonical_+x .. canonical_-z."""
    return [f"orbit_{k:02d}" for k in range(PRESET_ORBIT_VIEWS)] + [f"canonical_{a}" for a in CANONICAL_NAMES]


def write_obj(path: Path, mesh: Mesh) -> None:
    """Positions and triangles only, 9 significant digits (float32 round-trips exactly)."""
    v = mesh.vertices.astype(np.float64).ravel()
    f = (mesh.faces.astype(np.int64) + 1).ravel()
    path.write_text("# NeuMatEx synthetic object\n" + ("v %.9g %.9g %.9g\n" * mesh.vertices.shape[0]) % tuple(v)
                    + ("f %d %d %d\n" * mesh.num_faces) % tuple(f))  # fmt: skip


def random_cameras(rng: np.random.Generator, n: int, resolution: int) -> list[Camera]:
    """`n` cameras at random poses that see the whole unit sphere: azimuth uniform, elevation -30..70 degrees,
    field of view 30..50 degrees, distance such that the sphere fills 70..95% of it, aimed within 0.15 of the
    origin, rolled by up to 10 degrees."""
    cams = []
    for _ in range(n):
        az = rng.uniform(0.0, 2 * math.pi)
        el = math.radians(rng.uniform(-30.0, 70.0))
        fov = rng.uniform(30.0, 50.0)
        fill = rng.uniform(0.7, 0.95)
        dist = 1.0 / math.sin(math.radians(fov / 2) * fill)
        eye = dist * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        target = rng.uniform(-0.15, 0.15, 3)
        roll = math.radians(rng.uniform(-10.0, 10.0))
        c2w = look_at(eye, target, np.array([0.0, 1.0, 0.0]))
        r = np.array([[math.cos(roll), -math.sin(roll), 0.0], [math.sin(roll), math.cos(roll), 0.0], [0, 0, 1.0]])
        c2w[:3, :3] = c2w[:3, :3] @ r
        cams.append(camera_from_fov(c2w, resolution, resolution, fov))
    return cams


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _intrinsics(cam: Camera) -> dict[str, float | int]:
    return {"fl_x": cam.fl_x, "fl_y": cam.fl_y, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height}


def tree_hashes(root: Path, exclude: tuple[str, ...] = ("meta.json",)) -> tuple[dict[str, str], str]:
    """({relative path: SHA-256} of every file under root except `exclude`, SHA-256 of the sorted listing)."""
    files = {p.relative_to(root).as_posix(): sha256_file(p) for p in sorted(root.rglob("*"))
             if p.is_file() and p.relative_to(root).as_posix() not in exclude}  # fmt: skip
    listing = "".join(f"{k} {v}\n" for k, v in sorted(files.items()))
    return files, hashlib.sha256(listing.encode()).hexdigest()


class ObjectWriter:
    """Writes one object (see the module docstring). `times` collects rays / material / write seconds."""

    def __init__(self, spec: ObjectSpec, cfg: SynthConfig, basis: NeuralBasis, times: StageTimes | None = None):
        self.spec, self.cfg, self.basis = spec, cfg, basis
        self.times = times or StageTimes()

    # -- pieces --------------------------------------------------------------------------------------------
    def _lighting(self, light: LightingSpec, folder: Path) -> tuple[EnvironmentMap, dict[str, Any]]:
        """Write the map into folder/envmap.exr (.hdr for a shared .hdr map); the EnvironmentMap a capture loader
        would make of it."""
        pixels = lighting_pixels(light, self.cfg.envmaps_dir())
        name = "envmap" + (Path(light.map).suffix.lower() if light.kind == "shared" else ".exr")
        with self.times.stage("write"):
            if light.kind == "shared":
                shutil.copyfile(self.cfg.envmaps_dir() / light.map, folder / name)
            else:
                write_image(folder / name, pixels)
        rotation = yaw_rotation(light.rotation_deg)
        scale = lighting_scale(light, pixels)
        env = EnvironmentMap(envmap_rgb(pixels), rotation, scale)
        top = {"envmap": name, "envmap_to_world": rotation.tolist(), "envmap_scale": scale,
               "tonemap": {"exposure": TONEMAP.exposure, "transfer": TONEMAP.transfer}}  # fmt: skip
        return env, top

    def _render(self, tracer: PathTracer, scene: Scene, cam: Camera, seed: int, folder: Path, name: str,
                subdir: str = "images", linear_dir: str = "linear") -> tuple[str, str]:
        with torch.no_grad():
            image = tracer.render(scene, cam, seed=seed).cpu().numpy()
        with self.times.stage("write"):
            png, exr = f"{subdir}/{name}.png", f"{linear_dir}/{name}.exr"
            write_image(folder / exr, image)
            write_image(folder / png, TONEMAP.apply_numpy(image))
        return png, exr

    def _gbuffers(self, mesh: Mesh, raycaster: RayCaster, field: ProceduralMaterialField, cam: Camera,
                  folder: Path, name: str) -> tuple[str, dict[str, str], float]:
        """Masks and G-buffers of one view; returns (mask path, {buffer: path}, coverage)."""
        with self.times.stage("gbuffer"):
            gb = render_gbuffer(mesh, cam, raycaster)
            mask = gb.mask.reshape(-1)
            h, w = cam.height, cam.width
            values = field.gbuffer(gb.position.reshape(-1, 3)[mask], gb.triangle.reshape(-1)[mask])
            buffers = {"position": gb.position.reshape(-1, 3)[mask], "normal": gb.normal.reshape(-1, 3)[mask],
                       "basecolor": values["base_color"], "latent": values["latent"], "pbr": values["pbr"],
                       "region": values["region"].float().unsqueeze(-1)}  # fmt: skip
        paths = {}
        with self.times.stage("write"):
            mask_path = f"masks/{name}.png"
            write_image(folder / mask_path, gb.mask.float().numpy()[:, :, None])
            for key, val in buffers.items():
                full = torch.zeros(h * w, val.shape[-1])
                full[mask] = val.float().cpu()
                paths[key] = f"gbuffers/{name}_{key}.exr"
                write_image(folder / paths[key], full.reshape(h, w, -1).numpy(), GBUFFER_CHANNELS[key])
        return mask_path, paths, float(mask.float().mean())

    def _sub_capture(self, folder: Path, root: Path, scene: Scene, top: dict[str, Any], cameras: list[Camera],
                     names: list[str], seeds: list[int], spp: int) -> None:
        """A capture of `cameras` in `folder` (mesh linked from root; envmap already written there)."""
        _link(root / "mesh.obj", folder / "mesh.obj")
        tracer = PathTracer(PathTracerConfig(max_bounces=self.cfg.max_bounces, spp=spp))
        frames = []
        for cam, name, seed in zip(cameras, names, seeds, strict=True):
            png, exr = self._render(tracer, scene, cam, seed, folder, name)
            with self.times.stage("gbuffer"):
                gb = render_gbuffer(scene.mesh, cam, scene.raycaster)
            with self.times.stage("write"):
                write_image(folder / f"masks/{name}.png", gb.mask.float().numpy()[:, :, None])
            frames.append({"file_path": png, "mask_path": f"masks/{name}.png", "linear_path": exr, **_intrinsics(cam),
                           "transform_matrix": cam.c2w.tolist()})  # fmt: skip
        _write_json(folder / "transforms.json", {"mesh": "mesh.obj", **top, "frames": frames})

    # -- the object ----------------------------------------------------------------------------------------
    def write(self, root: Path) -> dict[str, Any]:
        """Write the object into `root` (created; should be empty); returns its meta.json content."""
        spec, cfg = self.spec, self.cfg
        root.mkdir(parents=True, exist_ok=True)
        with self.times.stage("setup"):
            shape = build_shape(spec.shape, cfg.meshes_dir())
            write_obj(root / "mesh.obj", shape.mesh)
            mesh = load_mesh(root / "mesh.obj")  # exactly what a capture loader reads
            if mesh.num_faces != shape.mesh.num_faces:
                raise ValueError(f"{root / 'mesh.obj'}: re-read {mesh.num_faces} faces, wrote {shape.mesh.num_faces}")
            regions = face_regions(spec.material, mesh, shape.parts)
            field = ProceduralMaterialField(spec.material, self.basis, regions)
            field.pbr_lut()
        env, top = self._lighting(spec.lighting, root)
        timed_field: MaterialField = TimedField(field, self.times)
        scene = Scene(mesh, env, timed_field)
        raycaster = scene.raycaster
        scene.raycaster = TimedRayCaster(raycaster, self.times)
        tracer = PathTracer(PathTracerConfig(max_bounces=cfg.max_bounces, spp=cfg.spp))
        cameras = preset_views(cfg.resolution)
        names = [f"{i:03d}" for i in range(len(cameras))]
        frames, coverage = [], []
        for i, (cam, name, view) in enumerate(zip(cameras, names, view_names(), strict=True)):
            png, exr = self._render(tracer, scene, cam, spec.render_seed + i, root, name)
            mask_path, buffers, cov = self._gbuffers(mesh, raycaster, field, cam, root, name)
            coverage.append(cov)
            frame: dict[str, Any] = {"file_path": png, "mask_path": mask_path, "transform_matrix": cam.c2w.tolist(),
                                     "view": view, "linear_path": exr, "gbuffers": buffers}  # fmt: skip
            frames.append(frame)
        if cfg.layered:
            layered = ProceduralMaterialField(spec.material, self.basis, regions, kind="layered")
            layered_scene = Scene(mesh, env, TimedField(layered, self.times))
            layered_scene.raycaster = scene.raycaster
            for i, (cam, name) in enumerate(zip(cameras, names, strict=True)):
                png, exr = self._render(tracer, layered_scene, cam, spec.render_seed + i, root, name, "layered",
                                        "layered")
                frames[i]["layered_path"] = exr
                frames[i]["layered_png"] = png
        _write_json(root / "transforms.json", {**_intrinsics(cameras[0]), "mesh": "mesh.obj", **top,
                                               "frames": frames})  # fmt: skip
        # Extra photos at random poses, same lighting.
        if cfg.photos:
            photos = root / "photos"
            photos.mkdir()
            _link(root / top["envmap"], photos / top["envmap"])
            rng = np.random.default_rng(np.random.SeedSequence([spec.photo_seed, 0xCA]))
            cams = random_cameras(rng, cfg.photos, cfg.resolution)
            self._sub_capture(photos, root, scene, top, cams, [f"{k:03d}" for k in range(len(cams))],
                              [spec.render_seed + PHOTO_SEED_OFFSET + k for k in range(len(cams))], cfg.spp)
        # Held-out lighting: the orbital views under other maps.
        relight_scales = []
        for j, light in enumerate(spec.relight):
            folder = root / "relight" / str(j)
            folder.mkdir(parents=True)
            env_j, top_j = self._lighting(light, folder)
            relight_scales.append(top_j["envmap_scale"])
            scene_j = Scene(mesh, env_j, timed_field)
            scene_j.raycaster = scene.raycaster
            orbit = cameras[:PRESET_ORBIT_VIEWS]
            seeds = [spec.render_seed + RELIGHT_SEED_OFFSET * (j + 1) + v for v in range(len(orbit))]
            self._sub_capture(folder, root, scene_j, top_j, orbit, names[:len(orbit)], seeds, cfg.relight_spp)
        with self.times.stage("write"):
            _write_json(root / "material.json", self._material_json(field))
            files, tree = tree_hashes(root)
            meta = {
                "id": spec.id, "spec": spec.to_json(), "content": cfg.content(),
                "basis": {"id": self.basis.basis_id, "sha256": self.basis.content_hash},
                "shape": shape.params, "faces": mesh.num_faces,
                "lighting": {"envmap_scale": top["envmap_scale"], "relight_envmap_scales": relight_scales},
                "coverage": round(float(np.mean(coverage)), 6), "views": len(cameras), "photos": cfg.photos,
                "tree_sha256": tree, "files": files,
            }  # fmt: skip
            _write_json(root / "meta.json", meta)
        return meta

    def _material_json(self, field: ProceduralMaterialField) -> dict[str, Any]:
        lut = field.pbr_lut()
        regions = []
        for k, region in enumerate(self.spec.material.regions):
            regions.append({
                "family": region.family,
                "params": dict(zip(PARAMETER_NAMES, region.params, strict=True)),
                "base_color_0": list(region.color0), "base_color_1": list(region.color1),
                "latent": [float(x) for x in field.latents[k]],
                "pbr_levels": [[float(x) for x in row] for row in lut[k]],
            })  # fmt: skip
        return {
            "basis_id": self.basis.basis_id,
            "note": "rho_d = base_color_0 + t (base_color_1 - base_color_0), t from the colour pattern; the neural "
                    f"material is (rho_d, latent); PBR (base rgb, roughness, metallic) at t = k/{PBR_LEVELS - 1}",
            "spec": self.spec.material.to_json(),
            "regions": regions,
        }


def _write_json(path: Path, data: dict[str, Any]) -> None:
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
