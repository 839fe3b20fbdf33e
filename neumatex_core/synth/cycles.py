"""Captures rendered by Blender Cycles, driven from the main venv: an outside renderer in the loop.

Blender runs in its own venv (`make cycles-env`: `.venv-cycles`, bpy from PyPI), where neither torch nor this
package exists. This module does the part that needs the project: it writes the cameras JSON (the 23 preset views of
`preset_views(resolution)`, their names, and seeded random views exactly as the synthetic objects draw them), then
runs `tools/cycles_capture.py` under `.venv-cycles/bin/python`, which builds the scene in bpy, converts the
conventions (its docstring lists them) and writes a capture (docs/capture-format.md) with a `cycles.json` record.

    python -m neumatex_core.synth.cycles --mesh teapot.obj --envmap studio.exr --preset coat --out out/cycles/coat \
        --resolution 128 --spp 256 --random 8 --relight city.exr,forest.exr

Bare file names are looked up in the shared meshes / envmaps folders ($NEUMATEX_SHARED/data/...).
Camera JSON entries: {"c2w": [4, 4] camera-to-world (OpenGL axes, world +Y up), "fl_x", "fl_y", "cx", "cy" (pixels),
"w", "h"}.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from neumatex_core.config import option
from neumatex_core.geometry.camera import Camera, preset_views
from neumatex_core.synth.config import default_shared

REPO_ROOT = Path(__file__).resolve().parents[2]
CYCLES_SCRIPT = REPO_ROOT / "tools" / "cycles_capture.py"
CYCLES_VENV = REPO_ROOT / ".venv-cycles"
PRESETS = ("diffuse", "coat", "sheen", "metal")
RANDOM_CAMERA_SALT = 0xCA  # the synthetic objects' photos use SeedSequence([photo_seed, 0xCA])


class CyclesError(RuntimeError):
    """The Cycles venv is missing or the Blender script failed; the message says which and shows its output."""


def cycles_python() -> Path | None:
    """The Cycles venv's interpreter ($NEUMATEX_CYCLES_PYTHON, else .venv-cycles/bin/python), or None if absent."""
    env = os.environ.get("NEUMATEX_CYCLES_PYTHON")
    path = Path(env) if env else CYCLES_VENV / "bin" / "python"
    return path if path.is_file() else None


def camera_json(cam: Camera) -> dict[str, Any]:
    """A camera as the JSON entry tools/cycles_capture.py reads (float64 values, exact)."""
    return {"c2w": np.asarray(cam.c2w, dtype=np.float64).tolist(), "fl_x": float(cam.fl_x), "fl_y": float(cam.fl_y),
            "cx": float(cam.cx), "cy": float(cam.cy), "w": int(cam.width), "h": int(cam.height)}  # fmt: skip


def camera_from_json(entry: dict[str, Any]) -> Camera:
    """Inverse of `camera_json`."""
    return Camera(np.asarray(entry["c2w"], dtype=np.float64), float(entry["fl_x"]), float(entry["fl_y"]),
                  float(entry["cx"]), float(entry["cy"]), int(entry["w"]), int(entry["h"]))  # fmt: skip


def cameras_document(resolution: int, random: int = 0, seed: int = 0) -> dict[str, Any]:
    """{"resolution", "preset": 23 cameras, "preset_names", "random": `random` cameras, "target_luminance"}.

    Random views are `synth.writer.random_cameras` drawn from SeedSequence([seed, 0xCA]) (a synthetic object's
    photos with photo_seed = seed)."""
    from neumatex_core.synth.lighting import TARGET_LUMINANCE
    from neumatex_core.synth.writer import random_cameras, view_names

    rng = np.random.default_rng(np.random.SeedSequence([seed, RANDOM_CAMERA_SALT]))
    return {
        "resolution": resolution,
        "preset": [camera_json(c) for c in preset_views(resolution)],
        "preset_names": view_names(),
        "random": [camera_json(c) for c in random_cameras(rng, random, resolution)] if random else [],
        "random_seed": seed,
        "target_luminance": TARGET_LUMINANCE,
    }


def write_cameras_json(path: str | Path, resolution: int, random: int = 0, seed: int = 0) -> Path:
    """Write `cameras_document` to `path` (for tools/cycles_capture.py --cameras); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(cameras_document(resolution, random, seed), indent=1) + "\n")
    return path


def shared_file(name: str | Path, kind: Literal["meshes", "envmaps"]) -> Path:
    """`name` itself when it exists, else the shared data file of that name (raises FileNotFoundError)."""
    path = Path(name)
    if path.is_file():
        return path.resolve()
    shared = default_shared() / kind / path.name
    if shared.is_file():
        return shared
    raise FileNotFoundError(f"{name}: not found (nor as {shared})")


def render_cycles_capture(
    mesh: str | Path,
    envmap: str | Path,
    out: str | Path,
    preset: str = "diffuse",
    resolution: int = 128,
    spp: int = 256,
    views: str = "all",
    random: int = 0,
    relight: tuple[str, ...] | list[str] = (),
    envmap_yaw: float = 0.0,
    envmap_scale: float | None = None,
    seed: int = 0,
    threads: int = 1,
    max_bounces: int = 3,
    base_color: tuple[float, float, float] | None = None,
    verbose: bool = False,
    timeout: float | None = None,
    pose_seed: int | None = None,
) -> dict[str, Any]:
    """Write a Cycles capture of `mesh` under `envmap` into `out`; returns its cycles.json record.

    views: "all" or preset view indices ("0,5,20"); random: views at random poses (photos/); relight: held-out maps,
    each "MAP" or "MAP@YAW_DEG" (relight/<j>/, the orbital views among `views`); envmap_scale None: normalised
    brightness like the synthetic objects; max_bounces: surface interactions (ours; Cycles gets one less);
    pose_seed: the random views' poses (None: `seed`), so two captures with the same pose_seed and different seeds
    are independent renders of the same views (the halves of a noise-corrected score).
    Raises CyclesError when `.venv-cycles` is missing (run `make cycles-env`) or Blender fails.
    """
    python = cycles_python()
    if python is None:
        raise CyclesError(f"no Cycles venv at {CYCLES_VENV}: run `make cycles-env` (installs bpy from PyPI)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    relight_args = []
    for spec in relight:
        name, _, yaw = str(spec).partition("@")
        relight_args.append(str(shared_file(name, "envmaps")) + (f"@{yaw}" if yaw else ""))
    with tempfile.TemporaryDirectory(prefix="neumatex-cycles-") as tmp:
        cams = write_cameras_json(Path(tmp) / "cameras.json", resolution, random,
                                  seed if pose_seed is None else pose_seed)
        cmd = [str(python), str(CYCLES_SCRIPT), "--mesh", str(shared_file(mesh, "meshes")),
               "--envmap", str(shared_file(envmap, "envmaps")), "--cameras", str(cams), "--out", str(out),
               "--preset", preset, "--spp", str(spp), "--views", views, "--random", str(random),
               "--envmap-yaw", str(envmap_yaw), "--seed", str(seed), "--threads", str(threads),
               "--max-bounces", str(max_bounces)]  # fmt: skip
        if relight_args:
            cmd += ["--relight", *relight_args]
        if envmap_scale is not None:
            cmd += ["--envmap-scale", repr(float(envmap_scale))]
        if base_color is not None:
            cmd += ["--base-color", *(repr(float(c)) for c in base_color)]
        if verbose:
            cmd.append("--verbose")
        proc = subprocess.run(cmd, capture_output=not verbose, text=True, timeout=timeout)
    if proc.returncode != 0:
        tail = ((proc.stdout or "") + (proc.stderr or ""))[-4000:] or "(its output is above)"
        raise CyclesError(f"Blender Cycles capture failed (exit {proc.returncode}):\n{tail}")
    record: dict[str, Any] = json.loads((out / "cycles.json").read_text())
    return record


# -- agreement with our renderer --------------------------------------------------------------------------------
@dataclass
class ViewAgreement:
    """One view of a Cycles capture against our path tracer, both after the capture's tonemap T.

    psnr: dB over the covered pixels (a ray through the pixel centre hits the mesh); psnr_background: dB over the
    pixels farther than one pixel from any covered one (the map seen directly: checks cameras and map rotation
    without any shading); ratio: mean linear Cycles / ours over the covered pixels, per RGB channel; covered:
    fraction of covered pixels; mask_agreement: fraction of pixels where the capture's mask equals our coverage.
    """

    file: str
    psnr: float
    psnr_background: float
    ratio: tuple[float, float, float]
    covered: float
    mask_agreement: float


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b.astype(np.float64)) ** 2)[mask].mean()) if mask.any() else 0.0
    return float("inf") if mse == 0 else 10 * float(np.log10(1.0 / mse))


def _linear(root: Path, frame: dict[str, Any]) -> np.ndarray:
    from neumatex_core.imageio import read_image

    return read_image(root / frame["linear_path"])[:, :, :3]


def compare_with_ours(capture: str | Path, spp: int = 4096, max_bounces: int = 3, seed: int = 0,
                      images: dict[str, np.ndarray] | None = None) -> list[ViewAgreement]:
    """Render every frame of a `diffuse` Cycles capture with our path tracer and compare (see ViewAgreement).

    Our side: the capture's mesh (area-weighted smooth normals), its map (envmap_to_world, envmap_scale) and
    UniformPBR(base colour of cycles.json, roughness=1, metallic=0, dielectric_f0=0), a pure Lambertian, at
    `max_bounces` surface interactions and `spp` samples (seed + frame index). `images`, when given, receives
    "<file>" -> [H, 3W, 3] tonemapped ours | Cycles | 4 x |difference| for looking at."""
    import torch

    from neumatex_core.capture import load_capture
    from neumatex_core.geometry.gbuffer import render_gbuffer
    from neumatex_core.imageio import read_image
    from neumatex_core.lighting.envmap import EnvironmentMap
    from neumatex_core.materials.field import UniformPBR
    from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
    from neumatex_core.render.scene import Scene

    with load_capture(capture) as cap:
        record = json.loads((cap.root / "cycles.json").read_text())
        if record["preset"] != "diffuse":
            raise ValueError(f"{capture}: preset {record['preset']!r}; only a diffuse capture has a Lambertian twin")
        frames = json.loads((cap.root / "transforms.json").read_text())["frames"]
        red, green, blue = (float(c) for c in record["principled_bsdf"]["inputs"]["Base Color"][:3])
        base = (red, green, blue)
        mesh = cap.load_mesh()
        env = EnvironmentMap(cap.load_envmap(), cap.envmap_to_world)  # load_envmap applies envmap_scale
        scene = Scene(mesh, env, UniformPBR(base, roughness=1.0, metallic=0.0, dielectric_f0=0.0))
        tracer = PathTracer(PathTracerConfig(max_bounces=max_bounces, spp=spp))
        out = []
        for i, (frame, entry) in enumerate(zip(cap.frames, frames, strict=True)):
            with torch.no_grad():
                ours = tracer.render(scene, frame.camera, seed=seed + i).cpu().numpy()
            theirs = _linear(cap.root, entry)
            covered = render_gbuffer(mesh, frame.camera, scene.raycaster).mask.cpu().numpy()
            grown = covered.copy()  # covered pixels and their 8 neighbours
            padded = np.pad(covered, 1)
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    grown |= padded[1 + dy:1 + dy + covered.shape[0], 1 + dx:1 + dx + covered.shape[1]]
            a, b = cap.tonemap.apply_numpy(ours), cap.tonemap.apply_numpy(theirs)
            mask_file = read_image(frame.mask_path)[:, :, 0] > 0.5 if frame.mask_path else covered
            ratio = theirs[covered].mean(0) / np.maximum(ours[covered].mean(0), 1e-12)
            out.append(ViewAgreement(entry["file_path"], _psnr(a, b, covered), _psnr(a, b, ~grown),
                                     (float(ratio[0]), float(ratio[1]), float(ratio[2])), float(covered.mean()),
                                     float((mask_file == covered).mean())))  # fmt: skip
            if images is not None:
                images[entry["file_path"]] = np.concatenate([a, b, np.clip(4 * np.abs(a - b), 0, 1)], axis=1)
    return out


def seed_noise_psnr(capture_a: str | Path, capture_b: str | Path) -> list[float]:
    """Per frame, PSNR (dB, tonemapped, covered pixels) between two captures that differ only in the Cycles seed.

    Two independent estimates differ by twice the variance of one, so an unbiased renderer with no noise of its own
    would agree with one capture at this figure + 3.01 dB: the noise ceiling of `compare_with_ours`."""
    from neumatex_core.capture import load_capture
    from neumatex_core.geometry.gbuffer import render_gbuffer

    with load_capture(capture_a) as a, load_capture(capture_b) as b:
        fa = json.loads((a.root / "transforms.json").read_text())["frames"]
        fb = json.loads((b.root / "transforms.json").read_text())["frames"]
        mesh = a.load_mesh()
        out = []
        for frame, ea, eb in zip(a.frames, fa, fb, strict=True):
            covered = render_gbuffer(mesh, frame.camera).mask.cpu().numpy()
            out.append(_psnr(a.tonemap.apply_numpy(_linear(a.root, ea)), a.tonemap.apply_numpy(_linear(b.root, eb)),
                             covered))  # fmt: skip
    return out


@dataclass
class CyclesCaptureConfig:
    """`neumatex cycles-capture`: a capture rendered by Blender Cycles (needs `make cycles-env`): the 23 preset
    views, random views (photos/) and the orbital views under held-out maps (relight/<j>/), with a Principled BSDF
    preset; linear EXR, tonemapped PNG, masks, transforms.json, cycles.json."""

    mesh: str = option("teapot.obj", "mesh file, or the name of a shared mesh")
    envmap: str = option("studio.exr", "equirectangular HDR map, or the name of a shared map")
    out: str = option("out/cycles/capture", "capture folder to write")
    preset: Literal["diffuse", "coat", "sheen", "metal"] = option("diffuse", "Principled BSDF preset")
    resolution: int = option(128, "image size (pixels, square)")
    spp: int = option(256, "Cycles samples per pixel")
    views: str = option("all", "preset views: all, or indices such as 0,5,20")
    random: int = option(8, "views at random poses (photos/)")
    relight: str = option("city.exr,forest.exr", "held-out maps, comma separated (MAP or MAP@YAW_DEG); empty: none")
    envmap_yaw: float = option(0.0, "rotation of the map about +Y, degrees")
    envmap_scale: float = option(0.0, "envmap_scale (0: normalised brightness like the synthetic objects)")
    seed: int = option(0, "Cycles seed of view 0, and the random views' seed unless --pose-seed is given")
    pose_seed: int = option(-1, "seed of the random views' poses (-1: --seed); the same --pose-seed with another "
                                "--seed renders the same views with independent noise")
    threads: int = option(1, "Cycles render threads")
    max_bounces: int = option(3, "surface interactions per path (1 = direct lighting only)")


def run_cycles_capture(cfg: CyclesCaptureConfig) -> int:
    """Render the capture; the Blender script prints each view's time and where the capture is."""
    relight = [m.strip() for m in cfg.relight.split(",") if m.strip()]
    render_cycles_capture(cfg.mesh, cfg.envmap, cfg.out, cfg.preset, cfg.resolution, cfg.spp, cfg.views, cfg.random,
                          relight, cfg.envmap_yaw, cfg.envmap_scale or None, cfg.seed, cfg.threads, cfg.max_bounces,
                          verbose=True, pose_seed=None if cfg.pose_seed < 0 else cfg.pose_seed)
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m neumatex_core.synth.cycles ...` (the same options as `neumatex cycles-capture`)."""
    import argparse

    from neumatex_core.config import add_config_arguments, config_from_args

    doc = (CyclesCaptureConfig.__doc__ or "").strip()
    parser = argparse.ArgumentParser(prog="neumatex cycles-capture", description=doc)
    add_config_arguments(parser, CyclesCaptureConfig)
    try:
        return run_cycles_capture(config_from_args(CyclesCaptureConfig, parser.parse_args(argv)))
    except (ValueError, OSError, CyclesError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
