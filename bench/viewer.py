"""Frame time of the browser viewer (neumatex_core/viewer, docs/viewer.md) next to the torch path tracer's time for
the same image.

Asset: a benchmark-sized one made here as tests do (tests/asset_fixtures.make_asset): a shared mesh (`--mesh`,
normalised) with two material draws of the prior blended over it, distilled into a triplane, unwrapped and baked to
`--texture`^2 textures. Page: headless Debian Chromium (/usr/bin/chromium), WebGL2 through ANGLE on SwiftShader
(software, on the CPU: the GL backend is printed and recorded), canvas `--resolution`^2, the studio map at 512 x 256.
One frame = `--spp` samples per pixel, each a map sample and a BSDF sample with MIS (two decoder evaluations), the
neural mode; the time is wall clock per frame after a warm-up frame (shader compilation), waited for with a
readPixels (the GPU work is finished). Torch: `PathTracer` with max_bounces=1 (direct lighting, the same estimator
plus shadow rays), `--spp` samples per pixel, the same camera, size and map, under torch.no_grad(); the min of
`--repeats` runs.

Prints both and the ratio torch / viewer (> 1: the viewer is faster), appends a JSON line to
bench/results/viewer.jsonl. With `--screenshot PATH`, afterwards writes a screenshot of the page (the UI included)
at `--shot-size`, accumulated over `--shot-frames` frames of `--shot-spp` samples (docs/viewer.png).

    NEUMATEX_SHARED=/work/shared .venv/bin/python bench/viewer.py
    NEUMATEX_SHARED=/work/shared .venv/bin/python bench/viewer.py --resolution 256 --screenshot docs/viewer.png
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from asset_fixtures import make_asset  # noqa: E402
from common import argument_parser, time_repeats, write_result  # noqa: E402
from conftest import ENVMAPS, MESHES  # noqa: E402
from viewer_fixtures import CHROMIUM_ARGS, set_camera, view_camera, viewer_page  # noqa: E402

from neumatex_core.assets import read_asset, write_asset  # noqa: E402
from neumatex_core.assets.render import asset_scene  # noqa: E402
from neumatex_core.geometry.mesh import load_mesh  # noqa: E402
from neumatex_core.materials.neural_basis import load_basis  # noqa: E402
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig  # noqa: E402
from neumatex_core.viewer.serve import serve_folder  # noqa: E402
from neumatex_core.viewer.web_bundle import EnvSource, torch_envmap, write_bundle  # noqa: E402


def main() -> int:
    ap = argument_parser(__doc__)
    ap.add_argument("--mesh", default="cow", help="shared mesh name")
    ap.add_argument("--envmap", default="studio", help="shared map name")
    ap.add_argument("--texture", type=int, default=512, help="texture resolution of the asset")
    ap.add_argument("--resolution", type=int, default=1024, help="image size (pixels, square)")
    ap.add_argument("--spp", type=int, default=1, help="samples per pixel per frame (and of the torch render)")
    ap.add_argument("--frames", type=int, default=2, help="timed viewer frames")
    ap.add_argument("--repeats", type=int, default=1, help="torch renders (min reported)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--screenshot", default="", help="also write a screenshot of the page here")
    ap.add_argument("--shot-size", type=int, default=320)
    ap.add_argument("--shot-frames", type=int, default=8)
    ap.add_argument("--shot-spp", type=int, default=4)
    ap.add_argument("--screenshot-only", action="store_true", help="only the screenshot: no timing, no JSON line")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    t0 = time.perf_counter()
    mesh = load_mesh(MESHES / f"{args.mesh}.obj").normalized()
    asset = make_asset(mesh, load_basis(), name=args.mesh, resolution=args.texture)
    with tempfile.TemporaryDirectory(prefix="bench-viewer-") as tmp:
        write_asset(asset, Path(tmp) / "asset")
        asset = read_asset(Path(tmp) / "asset")
        bundle = Path(tmp) / "bundle"
        write_bundle(asset, bundle, [EnvSource.from_file(ENVMAPS / f"{args.envmap}.exr")], env_height=256)
        envmap = torch_envmap(bundle, args.envmap)
        print(f"asset {args.mesh} ({asset.mesh.num_faces} faces, {args.texture}^2 textures) in "
              f"{time.perf_counter() - t0:.1f} s")
        camera = view_camera(args.resolution)

        server = serve_folder(bundle)
        try:
            with viewer_page(server.url + f"?auto=0&spp={args.spp}", viewport=args.resolution + 80) as page:
                info = page.evaluate("() => window.neumatexViewer.info()")
                set_camera(page, view_camera(64))
                t1 = time.perf_counter()
                page.evaluate("() => window.neumatexViewer.renderFrames(1)")  # compiles the shaders
                compile_s = time.perf_counter() - t1
                set_camera(page, camera)
                if not args.screenshot_only:
                    page.evaluate("() => window.neumatexViewer.renderFrames(1)")
                frame_ms = [page.evaluate("() => window.neumatexViewer.renderFrames(1)")
                            for _ in range(0 if args.screenshot_only else args.frames)] or [0.0]  # fmt: skip
                viewer_s = min(frame_ms) / 1000
                print(f"viewer: {viewer_s:.2f} s/frame at {args.resolution}^2, {args.spp} spp "
                      f"(frames {[round(m / 1000, 2) for m in frame_ms]}; first frame + compile {compile_s:.1f} s) "
                      f"on {info['renderer']}")
                if args.screenshot:
                    set_camera(page, view_camera(args.shot_size, distance=2.9))
                    page.evaluate(f"() => window.neumatexViewer.setSpp({args.shot_spp})")
                    page.evaluate(f"() => window.neumatexViewer.renderFrames({args.shot_frames})")
                    page.set_viewport_size({"width": args.shot_size + 560, "height": args.shot_size})
                    page.evaluate("() => window.neumatexViewer.readDisplay()")
                    page.screenshot(path=args.screenshot, clip={"x": 0, "y": 0, "width": args.shot_size + 280,
                                                                "height": args.shot_size})  # panel + canvas
                    print(f"wrote {args.screenshot}")
        finally:
            server.close()
        if args.screenshot_only:
            return 0

        scene = asset_scene(asset, envmap, "textures")
        tracer = PathTracer(PathTracerConfig(max_bounces=1, spp=args.spp))

        def render() -> None:
            with torch.no_grad():
                tracer.render(scene, camera, seed=0)

        timing = time_repeats(render, repeats=args.repeats)
        torch_s = timing["min"]
    ratio = torch_s / viewer_s
    print(f"torch path tracer (direct lighting, {args.threads} threads): {torch_s:.2f} s for the same image; "
          f"torch / viewer = {ratio:.2f}")
    path = write_result("viewer", {
        "config": {"mesh": args.mesh, "faces": int(asset.mesh.num_faces), "texture": args.texture,
                   "envmap": args.envmap, "envmap_size": [512, 256], "resolution": args.resolution,
                   "spp_per_frame": args.spp, "frames": args.frames, "repeats": args.repeats,
                   "threads": args.threads, "chromium_args": CHROMIUM_ARGS},
        "gl_renderer": info["renderer"], "gl_version": info["version"],
        "viewer_frame_s": viewer_s, "viewer_frames_s": [m / 1000 for m in frame_ms], "viewer_compile_s": compile_s,
        "torch_s": torch_s, "torch_times_s": timing["times"], "torch_foreign_cpu": timing["foreign_cpu"],
        "torch_over_viewer": ratio,
    })  # fmt: skip
    print(f"appended to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
