"""`neumatex`: the command-line interface. Each subcommand's options come from a config dataclass."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from neumatex_core.config import add_config_arguments, config_from_args, option
from neumatex_core.eval.reference_set import ReferencesConfig
from neumatex_core.eval.suite import EvalConfig, run_eval_command
from neumatex_core.extract_cli import ExtractCommandConfig, run_extract
from neumatex_core.lmrm.train import TrainLMRMConfig
from neumatex_core.materials.basis_training import TrainBasisConfig
from neumatex_core.synth.config import SynthConfig
from neumatex_core.synth.cycles import CyclesCaptureConfig, run_cycles_capture
from neumatex_core.synth.random_pose import RandomPoseConfig, run_random_pose
from neumatex_core.synth.sheets import SheetsConfig, run_sheets


@dataclass
class RenderConfig:
    """`neumatex render`: a material asset, or a mesh with a PBR material, under an environment map, from the preset
    views or a capture's cameras, to linear EXR and tonemapped PNG files."""

    asset: str = option("", "material asset package (folder or .zip) to re-render", positional=True)
    material: Literal["auto", "triplane", "textures", "pbr"] = option(
        "auto", "which representation of the asset: its own field (auto), the triplane, the baked neural UV "
        "textures or the PBR fallback")
    mesh: str = option("", "mesh file (OBJ/PLY/GLB); normalised into the unit sphere")
    envmap: str = option("", "equirectangular HDR environment map (EXR/HDR)")
    capture: str = option("", "render a capture (folder or zip): its mesh, envmap, cameras and tonemap")
    allow_outside_paths: bool = option(False, "the capture folder's transforms.json may name files outside it")
    out: str = option("out/render", "output folder")
    views: str = option("all", "preset views: all (23), orbit (17), canonical (6) or indices like 0,5,9")
    resolution: int = option(256, "image size of the preset views (pixels)")
    spp: int = option(64, "samples per pixel")
    max_bounces: int = option(3, "surface interactions per path (1 = direct lighting only)")
    seed: int = option(0, "random seed (view i uses seed + i)")
    base_color: tuple[float, float, float] = option((0.8, 0.8, 0.8), "PBR base colour, linear RGB (mesh mode)")
    roughness: float = option(0.5, "PBR roughness in [0, 1]")
    metallic: float = option(0.0, "PBR metallic in [0, 1]")
    exposure: float = option(1.0, "tonemap exposure for the PNGs (a capture's own tonemap wins)")
    flat_shading: bool = option(False, "shade with face normals instead of smooth vertex normals")
    device: Literal["auto", "cpu", "cuda"] = option("auto", "torch device")


def _select_views(spec: str, n: int) -> list[int]:
    if spec == "all":
        return list(range(n))
    if spec == "orbit":
        return list(range(17))
    if spec == "canonical":
        return list(range(17, 23))
    try:
        picked = [int(s) for s in spec.split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"--views: expected all, orbit, canonical or comma-separated indices, got {spec!r}") from None
    bad = [i for i in picked if not 0 <= i < n]
    if bad or not picked:
        raise ValueError(f"--views: indices must be in 0..{n - 1}, got {spec!r}")
    return picked


def run_render(cfg: RenderConfig) -> int:
    """Render and write files; returns the exit code."""
    import numpy as np
    import torch
    from tqdm import tqdm

    from neumatex_core.capture import Tonemap, load_capture
    from neumatex_core.device import default_device
    from neumatex_core.geometry import load_mesh, preset_views
    from neumatex_core.imageio import write_image
    from neumatex_core.lighting import EnvironmentMap
    from neumatex_core.materials.field import MaterialField, UniformPBR
    from neumatex_core.render import PathTracer, PathTracerConfig, Scene
    from neumatex_core.render.views import contact_sheet, render_views

    device = default_device() if cfg.device == "auto" else torch.device(cfg.device)
    if cfg.asset and cfg.mesh:
        raise ValueError("give an asset or --mesh, not both")
    asset = None
    if cfg.asset:
        from neumatex_core.assets import read_asset

        asset = read_asset(cfg.asset, device=device)
    if cfg.capture:
        from neumatex_core.capture.loader import allow_outside_paths

        with allow_outside_paths(cfg.allow_outside_paths):
            capture = load_capture(cfg.capture)
        envmap_path = cfg.envmap or capture.envmap_path
        to_world, scale = (None, 1.0) if cfg.envmap else (capture.envmap_to_world, capture.envmap_scale)
        envmap = EnvironmentMap.from_file(envmap_path, to_world, scale, device)
        cameras = [f.camera for f in capture.frames]
        if asset is not None and asset.centre is not None and asset.scale is not None:
            cameras = [c.normalized(np.asarray(asset.centre), asset.scale) for c in cameras]  # into object space
        tonemap = capture.tonemap
        mesh = asset.mesh if asset is not None else capture.load_mesh(smooth=not cfg.flat_shading)
    else:
        if not cfg.envmap or not (cfg.mesh or asset is not None):
            raise ValueError("give ASSET --envmap MAP, --mesh and --envmap, or --capture")
        mesh = asset.mesh if asset is not None else load_mesh(cfg.mesh, smooth=not cfg.flat_shading).normalized()
        envmap = EnvironmentMap.from_file(cfg.envmap, device=device)
        presets = preset_views(cfg.resolution)
        cameras = [presets[i] for i in _select_views(cfg.views, len(presets))]
        tonemap = Tonemap(exposure=cfg.exposure)
    if asset is not None:
        material: MaterialField = asset.field(cfg.material)
        print(f"asset {asset.name}: {asset.field_kind} field, rendering {cfg.material} "
              f"({asset.texture_resolution}^2 textures, basis {asset.basis.basis_id})")
    else:
        material = UniformPBR(cfg.base_color, cfg.roughness, cfg.metallic)
    scene = Scene(mesh, envmap, material, device=device)
    tracer = PathTracer(PathTracerConfig(max_bounces=cfg.max_bounces, spp=cfg.spp))
    out = Path(cfg.out)
    with tqdm(total=len(cameras), unit="view", desc="render") as bar:
        views = render_views(
            scene, cameras, tracer, out, tonemap.apply, cfg.seed, progress=lambda done, total: bar.update(done - bar.n)
        )
    sizes = {v.display.shape for v in views}
    if len(sizes) == 1:
        write_image(out / "views.png", contact_sheet([v.display for v in views]))
    print(f"wrote {len(views)} views (EXR + PNG) to {out}/" + (" and views.png" if len(sizes) == 1 else ""))
    return 0


def run_train_basis(cfg: TrainBasisConfig) -> int:
    """Train (or resume) the neural basis; write weights + record to cfg.out (and into the package with --install)."""
    import shutil

    import torch
    from tqdm import tqdm

    from neumatex_core.device import default_device
    from neumatex_core.materials.basis_training import train_basis
    from neumatex_core.materials.neural_basis import DATA_DIR

    device = default_device() if cfg.device == "auto" else torch.device(cfg.device)
    bars: dict[str, tqdm] = {}

    def progress(stage: str, step: int, total: int, loss: float) -> None:
        if stage not in bars:
            bars[stage] = tqdm(total=total, desc=f"train-basis {stage}", unit="step", initial=step - 1)
        bars[stage].update(1)
        if step % 20 == 0 or step == total:
            bars[stage].set_postfix(loss=f"{loss:.4f}")

    basis, metrics = train_basis(cfg, device, progress)
    for bar in bars.values():
        bar.close()
    out = Path(cfg.out)
    basis_id = basis.save(out / "basis.safetensors", out / "basis.json", metrics, cfg.version)
    print(f"basis {basis_id}: median relative BSDF error {metrics['bsdf_median_rel_error']:.4f}, "
          f"log-L1 {metrics['bsdf_log_l1']:.4f}, T MAE {metrics['t_mae']:.4f}, R MAE {metrics['r_mae']:.4f}")
    if cfg.install:
        for name in ("basis.safetensors", "basis.json"):
            shutil.copy2(out / name, DATA_DIR / name)
        print(f"installed into {DATA_DIR}")
    return 0


@dataclass
class GalleryConfig:
    """`neumatex gallery`: spheres of every material family of the prior (and mixtures), the analytic layered
    material next to its neural encoding, under shared environment maps, as one labelled PNG."""

    out: str = option("out/gallery.png", "output PNG")
    envmaps: str = option("../shared/data/envmaps/courtyard.exr,../shared/data/envmaps/studio.exr",
                          "comma-separated environment maps (EXR/HDR)")
    per_family: int = option(1, "materials drawn per family (rows)")
    resolution: int = option(96, "sphere image size (pixels)")
    spp: int = option(64, "samples per pixel")
    exposure: float = option(1.0, "tonemap exposure")
    seed: int = option(0, "seed of the material draws and the renders")
    device: Literal["auto", "cpu", "cuda"] = option("auto", "torch device")


def run_gallery(cfg: GalleryConfig) -> int:
    import torch
    from tqdm import tqdm

    from neumatex_core.capture import Tonemap
    from neumatex_core.device import default_device
    from neumatex_core.imageio import write_image
    from neumatex_core.lighting import EnvironmentMap
    from neumatex_core.materials.neural_basis import load_basis
    from neumatex_core.render.gallery import SphereSettings, family_gallery

    device = default_device() if cfg.device == "auto" else torch.device(cfg.device)
    paths = [Path(p.strip()) for p in cfg.envmaps.split(",") if p.strip()]
    if not paths:
        raise ValueError("--envmaps: give at least one environment map")
    envmaps = [(p.stem, EnvironmentMap.from_file(p, device=device)) for p in paths]
    basis = load_basis(str(device))
    settings = SphereSettings(cfg.resolution, cfg.spp, cfg.seed, strategy="mis")
    with tqdm(unit="sphere pair", desc="gallery") as bar:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        image = family_gallery(envmaps, basis, settings, Tonemap(exposure=cfg.exposure).apply, cfg.per_family,
                               progress)
    Path(cfg.out).parent.mkdir(parents=True, exist_ok=True)
    write_image(cfg.out, image)
    print(f"wrote {cfg.out} (basis {basis.basis_id})")
    return 0


@dataclass
class ExportConfig:
    """`neumatex export`: an asset's PBR fallback as glTF 2.0 (GLB) or USD (UsdPreviewSurface), or its baked
    textures (EXR latents and base colour, PNG PBR maps, the mesh with its uvs), into a folder."""

    asset: str = option("", "material asset package (folder or .zip)", positional=True)
    format: Literal["glb", "usd", "textures"] = option("glb", "what to export")
    out: str = option("out/export", "output folder")


def run_export(cfg: ExportConfig) -> int:
    from neumatex_core.assets import read_asset
    from neumatex_core.assets.export import export_asset

    if not cfg.asset:
        raise ValueError("give the asset to export (neumatex export ASSET --format glb|usd|textures)")
    asset = read_asset(cfg.asset)
    files = export_asset(asset, cfg.format, cfg.out)
    print(f"wrote {cfg.format} of {asset.name}: " + ", ".join(str(f) for f in files))
    return 0


@dataclass
class ViewConfig:
    """`neumatex view`: look at an asset's neural material in the browser (WebGL2, the basis MLP in the shader), lit
    by environment maps, with orbit controls and a switch to the PBR fallback (docs/viewer.md)."""

    asset: str = option("", "material asset package (folder or .zip)", positional=True)
    envmap: str = option("", "equirectangular HDR map to light it with (EXR/HDR); the shared maps are offered too")
    shared_envmaps: str = option("", "folder of further maps for the menu (default: $NEUMATEX_SHARED/data/envmaps)")
    port: int = option(8765, "localhost port of the page (0: any free port)")
    browser: bool = option(True, "open the page in the default browser (--no-browser: only serve it)")
    env_height: int = option(256, "height of the maps the page gets (box-downsampled; width twice this)")


def run_view_command(cfg: ViewConfig) -> int:
    import os

    from neumatex_core.viewer.serve import run_view

    if not cfg.asset:
        raise ValueError("give the asset to view (neumatex view ASSET [--envmap MAP.exr])")
    shared = cfg.shared_envmaps or (str(Path(os.environ["NEUMATEX_SHARED"]) / "data" / "envmaps")
                                    if os.environ.get("NEUMATEX_SHARED") else "")  # fmt: skip
    return run_view(cfg.asset, cfg.envmap, shared, cfg.port, cfg.browser, cfg.env_height)


@contextmanager
def _object_bar(desc: str, show: bool) -> Iterator[Callable[[int, int, dict[str, Any] | None], None]]:
    """A per-object progress bar; yields the callback `progress(done, total, record)` that the split commands
    (synth, references) call after each object (record: its id and seconds, or None)."""
    from tqdm import tqdm

    with tqdm(unit="object", desc=desc, disable=not show) as bar:
        def progress(done: int, total: int, record: dict[str, Any] | None) -> None:
            bar.total = total
            bar.update(done - bar.n)
            if record is not None:
                bar.set_postfix(last=record["id"], s=record["seconds"])
            bar.refresh()

        yield progress


def run_synth(cfg: SynthConfig) -> int:
    """Make (or resume) a synthetic dataset split; prints where it is and whether it is complete."""
    from neumatex_core.synth.dataset import generate

    with _object_bar(f"synth {cfg.split}", cfg.progress) as progress:
        result = generate(cfg, progress)
    state = "complete" if result.complete else "incomplete (other shards or objects missing)"
    print(f"made {len(result.made)} objects, {result.skipped} already there, in {result.seconds:.1f} s; "
          f"{result.manifest}: {state}")
    return 0


def run_references(cfg: ReferencesConfig) -> int:
    """Render (or resume) the reference halves of a synthetic split's objects; prints what was made."""
    from neumatex_core.eval.reference_set import make_references

    with _object_bar("references", cfg.progress) as progress:
        result = make_references(cfg, progress)
    print(f"made the references of {len(result['made'])} objects, {result['skipped']} already there "
          f"(of {result['objects']} selected), in {result['seconds']:.1f} s; spp {cfg.spp_half} x 2 per view")
    return 0


def run_train_lmrm(cfg: TrainLMRMConfig) -> int:
    """Train (or resume) the LMRM with a progress bar; prints the validation PSNRs and where the weights are."""
    from tqdm import tqdm

    from neumatex_core.lmrm.train import train_lmrm

    bar = tqdm(total=cfg.steps, desc="train-lmrm", unit="step")

    def progress(step: int, total: int, row: dict[str, float]) -> None:
        bar.update(step - bar.n)
        if step % 10 == 0 or step == total:
            bar.set_postfix(stage=int(row["stage"]), loss=f"{row['loss']:.4f}", mat=f"{row['l_mat']:.4f}")

    result = train_lmrm(cfg, progress)
    bar.close()
    if not result.finished:
        print(f"stopped at step {result.steps_done}/{cfg.steps} (--max-minutes); rerun the same command to resume "
              f"from {result.out / 'checkpoint.pt'}")
        return 0
    val = result.metrics.get("validation", {})
    if val:
        print(f"validation: PSNR_BaseColor {val['psnr_basecolor']:.2f} dB, PSNR_Latents {val['psnr_latents']:.2f} dB "
              f"(mean material {val.get('mean_psnr_basecolor', float('nan')):.2f} / "
              f"{val.get('mean_psnr_latents', float('nan')):.2f} dB)")
    print(f"wrote {result.out / 'lmrm.safetensors'} and lmrm.json, curves in {result.out / 'curves.png'}"
          + (" (installed into the package)" if cfg.install else ""))
    return 0


COMMANDS: dict[str, tuple[type, Callable[[Any], int]]] = {
    "render": (RenderConfig, run_render),
    "export": (ExportConfig, run_export),
    "view": (ViewConfig, run_view_command),
    "train-basis": (TrainBasisConfig, run_train_basis),
    "gallery": (GalleryConfig, run_gallery),
    "synth": (SynthConfig, run_synth),
    "synth-sheets": (SheetsConfig, run_sheets),
    "synth-random-pose": (RandomPoseConfig, run_random_pose),
    "references": (ReferencesConfig, run_references),
    "cycles-capture": (CyclesCaptureConfig, run_cycles_capture),
    "train-lmrm": (TrainLMRMConfig, run_train_lmrm),
    "extract": (ExtractCommandConfig, run_extract),
    "eval": (EvalConfig, run_eval_command),
}


# Job service client commands (neumatex_client/cli.py), handed over whole: imported only when one of them runs.
CLIENT_COMMANDS = {"submit": "upload captures to the job service and start jobs (--wait, --out: the assets)",
                   "status": "one line per job of the job service; the exit code says if all completed",
                   "jobs": "list the job service's jobs", "job": "show one job of the job service",
                   "cancel": "cancel jobs of the job service", "retry": "run a failed or canceled job again",
                   "download": "download a completed job's asset zip"}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in CLIENT_COMMANDS:
        import importlib.util

        if importlib.util.find_spec("neumatex_client") is None:
            print("error: the job service client (neumatex_client/) is not installed", file=sys.stderr)
            return 2
        from neumatex_client.cli import main as client_main  # the web client stays out of the core's imports

        return client_main(argv)
    parser = argparse.ArgumentParser(prog="neumatex", description="Neural material extraction (NeuMatEx).")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an input error")
    sub = parser.add_subparsers(dest="command", required=True)
    p_validate = sub.add_parser("validate", help="check a capture folder or zip; lists every problem")
    p_validate.add_argument("capture", help="capture folder, transforms.json or .zip")
    p_validate.add_argument("--allow-outside-paths", action="store_true", help="a capture folder's transforms.json "
                            "may name files outside it (e.g. ../mesh.obj shared by relit captures; never for zips)")
    from neumatex_core.capture.colmap import ImportColmapConfig, run_import_colmap

    p_import = sub.add_parser("import", help="turn another tool's cameras into a capture (import colmap ...)")
    import_sub = p_import.add_subparsers(dest="import_format", required=True)
    add_config_arguments(import_sub.add_parser("colmap", help=(ImportColmapConfig.__doc__ or "").split("\n")[0],
                                               description=ImportColmapConfig.__doc__), ImportColmapConfig)
    p_serve = sub.add_parser("serve", help="the job service on this machine: redis-server, nginx, the API and one "
                             "worker (python -m services serve; prints the dashboard URL)")  # fmt: skip
    p_serve.add_argument("args", nargs=argparse.REMAINDER, help="passed on to `python -m services serve`")
    for name, text in CLIENT_COMMANDS.items():
        sub.add_parser(name, help=text, add_help=False)  # listed here; parsed by neumatex_client.cli
    for name, (cls, _) in COMMANDS.items():
        doc = (cls.__doc__ or "").strip()
        p = sub.add_parser(name, help=doc.split("\n")[0], description=doc)
        add_config_arguments(p, cls)
    args = parser.parse_args(argv)

    if args.command == "serve":
        # The service is a layer over the core (docs/architecture.md section 1): run it as its own program, never
        # import it here.
        import importlib.util
        import subprocess

        if importlib.util.find_spec("services") is None:
            print("error: the job service (services/) is not installed beside neumatex_core", file=sys.stderr)
            return 2
        return subprocess.call([sys.executable, "-m", "services", "serve", *args.args])
    try:
        if args.command == "validate":
            from neumatex_core.capture import run_validate

            return run_validate(args.capture, args.allow_outside_paths)
        if args.command == "import":
            return run_import_colmap(config_from_args(ImportColmapConfig, args))
        cls, run = COMMANDS[args.command]
        return run(config_from_args(cls, args))
    # our errors (MeshError, EnvmapError, CaptureError, ...) are ValueErrors; RecursionError: absurdly nested input
    except (ValueError, OSError, RecursionError) as exc:
        if args.debug:
            raise
        print(f"error: {exc} (--debug shows the traceback)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
