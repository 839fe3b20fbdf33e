"""Renderer throughput: our torch path tracer against Mitsuba 3 (llvm_ad_rgb) on the same scene.

Scene: one shared mesh (normalised into the unit sphere, smooth normals) under one shared environment map,
seen from preset view 0, with a uniform PBR material (base colour (0.8, 0.5, 0.3), roughness 0.4,
metallic 0). Both renderers trace the same camera rays (box filter, `spp` jittered samples per pixel), the
same bounce counts and no Russian roulette (rr_depth 100 on both sides, so both do the full work).

Figures (each timing repeated `--repeats` times; the MIN wall-clock time is reported, the median is in the
JSON line):
- ours forward, paths/s (W*H*spp / seconds of `PathTracer.render` under torch.no_grad());
- ours forward+backward, paths/s: material parameters require grad, loss = image.sum(), rays rendered with
  `render_rays` in chunks of `--chunk` rays with a backward pass per chunk (bounded memory); the time covers
  ray generation, rendering and every backward;
- Mitsuba forward, paths/s (`mi.render` + copy of the image to numpy), JIT compilation excluded (one
  untimed render first). Mitsuba's material is `principled` (base_color, roughness (alpha = roughness^2,
  GGX), metallic 0, specular 0.5 = F0 0.04) inside `twosided`: the same parameters as our Lambert + GGX PBR
  material (not the identical BRDF; this is a speed comparison, tests/ check correctness);
- ray queries/s on `--rays` random rays (origins on a sphere of radius 3, aimed at random points inside the
  mesh's bounding box): our `RayCaster.intersect` (closest hit) and `occluded`, Mitsuba's
  `ray_intersect_preliminary` and `ray_test`; both include the round trip from and to numpy (torch tensors
  for ours).

Ratios are ours / Mitsuba (> 1: ours faster). Prints a table and appends one JSON line to
bench/results/render.jsonl. Defaults take about 1 minute on an idle 2-core CPU (several
minutes when other processes compete for the cores); `--quick` is a smoke run.

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 .venv/bin/python bench/render.py
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, time_repeats, write_result  # noqa: E402

from neumatex_core.geometry.camera import Camera, preset_views  # noqa: E402
from neumatex_core.geometry.mesh import Mesh, load_mesh  # noqa: E402
from neumatex_core.lighting.envmap import EnvironmentMap  # noqa: E402
from neumatex_core.materials.field import UniformPBR  # noqa: E402
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig  # noqa: E402
from neumatex_core.render.scene import Scene  # noqa: E402

SHARED = Path(os.environ.get("NEUMATEX_SHARED", "/work/shared"))
DEFAULT_MESH = SHARED / "data/meshes/cow.obj"
DEFAULT_ENVMAP = SHARED / "data/envmaps/courtyard.exr"
LIBLLVM_19 = Path("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")
BASE_COLOR = (0.8, 0.5, 0.3)
ROUGHNESS = 0.4
METALLIC = 0.0
RR_DEPTH_OFF = 100  # Russian roulette never starts at these bounce counts
CONTENDED = 0.1  # other processes' share of the machine's CPUs above which a timing is flagged


# ---------------------------------------------------------------------------------------------- Mitsuba


def load_mitsuba() -> Any:
    """`mitsuba` with the llvm_ad_rgb variant (DRJIT_LIBLLVM_PATH pointed at libLLVM 19 when unset)."""
    if "DRJIT_LIBLLVM_PATH" not in os.environ and LIBLLVM_19.is_file():
        os.environ["DRJIT_LIBLLVM_PATH"] = str(LIBLLVM_19)
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return mi


def mitsuba_scene(mi: Any, mesh: Mesh, envmap: EnvironmentMap, camera: Camera, spp: int) -> Any:
    """Our scene in Mitsuba: same vertices / faces / vertex normals, envmap texels and camera rays.

    Camera: to_world = c2w @ diag(-1, 1, -1, 1), horizontal fov, box filter, no border samples.
    """
    bsdf = mi.load_dict({
        "type": "twosided",
        "bsdf": {
            "type": "principled",
            "base_color": {"type": "rgb", "value": list(BASE_COLOR)},
            "roughness": ROUGHNESS,
            "metallic": METALLIC,
            "specular": 0.5,
        },
    })
    props = mi.Properties()
    props["bsdf"] = bsdf
    smooth = mesh.vertex_normals is not None
    m = mi.Mesh("bench_mesh", vertex_count=int(mesh.vertices.shape[0]), face_count=int(mesh.faces.shape[0]),
                props=props, has_vertex_normals=smooth, has_vertex_texcoords=False)
    params = mi.traverse(m)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(mesh.vertices, np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(mesh.faces, np.uint32).ravel())
    if smooth:
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(mesh.vertex_normals, np.float32).ravel())
    params.update()

    env_to_world = np.eye(4)
    env_to_world[:3, :3] = envmap.to_world.cpu().numpy().astype(np.float64)
    w, h = camera.width, camera.height
    cam_to_world = np.asarray(camera.c2w, np.float64) @ np.diag([-1.0, 1.0, -1.0, 1.0])
    return mi.load_dict({
        "type": "scene",
        "mesh": m,
        "emitter": {
            "type": "envmap",
            "bitmap": mi.Bitmap(np.ascontiguousarray(envmap.texels.cpu().numpy(), np.float32),
                                mi.Bitmap.PixelFormat.RGB),
            "to_world": mi.ScalarTransform4f(env_to_world),
        },
        "sensor": {
            "type": "perspective",
            "fov": camera.fov_x_deg,
            "fov_axis": "x",
            "principal_point_offset_x": (w / 2.0 - camera.cx) / w,
            "principal_point_offset_y": (h / 2.0 - camera.cy) / h,
            "near_clip": 1e-3,
            "far_clip": 1e5,
            "to_world": mi.ScalarTransform4f(cam_to_world),
            "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "sample_border": False},
            "sampler": {"type": "independent", "sample_count": int(spp)},
        },
    })


def mitsuba_integrator(mi: Any, bounces: int) -> Any:
    """`path` with max_depth = bounces + 1 (Mitsuba counts the segment reaching the emitter), no RR."""
    return mi.load_dict({"type": "path", "max_depth": bounces + 1, "rr_depth": RR_DEPTH_OFF,
                         "hide_emitters": False})


def mitsuba_rays(mi: Any, o: np.ndarray, d: np.ndarray) -> Any:
    return mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))


# ---------------------------------------------------------------------------------------------- ours


def ours_forward(tracer: PathTracer, scene: Scene, camera: Camera, seed: int) -> torch.Tensor:
    with torch.no_grad():
        return tracer.render(scene, camera, seed=seed)


def ours_forward_backward(tracer: PathTracer, scene: Scene, camera: Camera, spp: int, chunk: int,
                          seed: int) -> None:
    """loss = image.sum() = sum of all ray radiances / spp, backpropagated chunk by chunk."""
    gen = torch.Generator().manual_seed(seed)
    o, d, _ = camera.generate_rays(spp=spp, generator=gen)
    for start in range(0, o.shape[0], chunk):
        radiance = tracer.render_rays(scene, o[start:start + chunk], d[start:start + chunk], gen)
        (radiance.sum() / spp).backward()


def random_rays(mesh: Mesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n rays: origins uniform on the sphere of radius 3, aimed at points uniform in the bounding box."""
    rng = np.random.default_rng(seed)
    origins = rng.normal(size=(n, 3))
    origins *= 3.0 / np.linalg.norm(origins, axis=1, keepdims=True)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    targets = lo + (hi - lo) * rng.random((n, 3))
    d = targets - origins
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return origins.astype(np.float32), d.astype(np.float32)


# ---------------------------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    parser.add_argument("--envmap", type=Path, default=DEFAULT_ENVMAP)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--bounces", type=str, default="1,3", help="comma-separated bounce counts")
    parser.add_argument("--rays", type=int, default=1_000_000, help="random rays for the ray-query figures")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per figure (min reported)")
    parser.add_argument("--budget", type=float, default=40.0,
                        help="seconds per figure after which no further repeats are timed")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch intra-op threads")
    parser.add_argument("--chunk", type=int, default=1 << 18, help="rays per forward+backward chunk")
    parser.add_argument("--view", type=int, default=0, help="preset view index")
    parser.add_argument("--quick", action="store_true", help="smoke run: 64x64, 4 spp, 100k rays, 1 repeat")
    parser.add_argument("--no-save", action="store_true", help="do not append to bench/results/render.jsonl")
    args = parser.parse_args(argv)
    if args.quick:
        args.resolution, args.spp, args.rays, args.repeats = 64, 4, 100_000, 1
    bounces = [int(b) for b in args.bounces.split(",")]

    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    mi = load_mitsuba()
    import drjit as dr

    mesh = load_mesh(args.mesh).normalized()
    envmap = EnvironmentMap.from_file(args.envmap)
    camera = preset_views(args.resolution)[args.view]
    res, spp = args.resolution, args.spp
    paths = res * res * spp
    print(f"scene: {args.mesh.name} ({mesh.num_faces} faces), {args.envmap.name} "
          f"({envmap.width}x{envmap.height}), {res}x{res}, {spp} spp = {paths} paths, view {args.view}; "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads, {os.cpu_count()} CPUs; "
          f"times: min of {args.repeats} (fewer past {args.budget:.0f} s)", flush=True)

    base = torch.tensor(BASE_COLOR)
    scene = Scene(mesh, envmap, UniformPBR(base, torch.tensor(ROUGHNESS), torch.tensor(METALLIC)))
    grad_params = [base.clone().requires_grad_(True), torch.tensor(ROUGHNESS, requires_grad=True),
                   torch.tensor(METALLIC, requires_grad=True)]
    grad_scene = Scene(mesh, envmap, UniformPBR(*grad_params))
    mi_scene = mitsuba_scene(mi, mesh, envmap, camera, spp)
    o_px, d_px, _ = camera.generate_rays(spp=1, jitter=False)
    coverage = float(scene.raycaster.intersect(o_px, d_px).valid.float().mean())
    print(f"the object covers {100 * coverage:.1f}% of the pixels (the other paths only look up the map)")

    figures: dict[str, Any] = {}
    timings: dict[str, Any] = {}
    sanity: dict[str, Any] = {"pixel_coverage": coverage}

    contended: list[str] = []

    def timed(fn: Any, warmup: int = 0) -> dict[str, Any]:
        return time_repeats(fn, args.repeats, warmup=warmup, budget_s=args.budget)

    def record(key: str, timing: dict[str, Any], count: int) -> None:
        timings[key] = timing
        figures[key] = count / timing["min"]
        foreign = timing["foreign_cpu"][timing["times"].index(timing["min"])]
        if foreign is not None and foreign > CONTENDED:
            contended.append(key)
        note = "" if foreign is None else f"  other processes {100 * foreign:.0f}% CPU"
        print(f"  {key:<28} {timing['min']:8.3f} s  (median {timing['median']:.3f} s)  "
              f"{figures[key]:12.4g} /s{note}", flush=True)

    for b in bounces:
        config = PathTracerConfig(max_bounces=b, rr_depth=RR_DEPTH_OFF, spp=spp, chunk_rays=args.chunk)
        tracer = PathTracer(config)
        ours_img = ours_forward(tracer, scene, camera, seed=0)  # warm-up (allocator, envmap tables)
        record(f"ours_forward_{b}b", timed(lambda t=tracer: ours_forward(t, scene, camera, 1)), paths)

        def fwd_bwd(t: PathTracer = tracer) -> None:
            for p in grad_params:
                p.grad = None
            ours_forward_backward(t, grad_scene, camera, spp, args.chunk, seed=2)

        record(f"ours_fwd_bwd_{b}b", timed(fwd_bwd), paths)
        sanity[f"grad_norm_{b}b"] = float(torch.cat([p.grad.reshape(-1) for p in grad_params]).norm())

        integrator = mitsuba_integrator(mi, b)

        def mi_render(seed: int = 0, integ: Any = integrator) -> np.ndarray:
            return np.array(mi.render(mi_scene, integrator=integ, spp=spp, seed=seed), dtype=np.float32)

        warm = time.perf_counter()
        mi_img = mi_render(0)  # JIT compilation, excluded
        timings[f"mitsuba_warmup_{b}b"] = time.perf_counter() - warm
        record(f"mitsuba_forward_{b}b", timed(lambda f=mi_render: f(1)), paths)
        sanity[f"mean_radiance_{b}b"] = {"ours": float(ours_img.mean()),
                                         "mitsuba": float(mi_img[..., :3].mean())}

    # Ray queries on the same random rays, numpy round trip included on both sides.
    o_np, d_np = random_rays(mesh, args.rays, seed=0)
    o_t, d_t = torch.from_numpy(o_np), torch.from_numpy(d_np)
    caster = scene.raycaster

    def mi_intersect() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pi = mi_scene.ray_intersect_preliminary(mitsuba_rays(mi, o_np, d_np), coherent=False)
        dr.eval(pi.t, pi.prim_index, pi.prim_uv)
        return np.array(pi.t), np.array(pi.prim_index), np.array(pi.prim_uv)

    def mi_occluded() -> np.ndarray:
        return np.array(mi_scene.ray_test(mitsuba_rays(mi, o_np, d_np), coherent=False))

    n = args.rays
    record("ours_intersect", timed(lambda: caster.intersect(o_t, d_t), warmup=1), n)
    record("mitsuba_intersect", timed(mi_intersect, warmup=1), n)
    record("ours_occluded", timed(lambda: caster.occluded(o_t, d_t), warmup=1), n)
    record("mitsuba_occluded", timed(mi_occluded, warmup=1), n)
    ours_hit = caster.intersect(o_t, d_t).valid.numpy()
    mi_t = mi_intersect()[0]
    mi_hit = np.isfinite(mi_t) & (mi_t < 1e30)
    sanity["ray_hit_fraction"] = float(ours_hit.mean())
    sanity["ray_hit_agreement"] = float((ours_hit == mi_hit).mean())
    sanity["occluded_agreement"] = float((caster.occluded(o_t, d_t).numpy() == mi_occluded()).mean())

    ratios: dict[str, float] = {}
    for b in bounces:
        for kind in ("forward", "fwd_bwd"):
            ratios[f"ours_{kind}_{b}b"] = figures[f"ours_{kind}_{b}b"] / figures[f"mitsuba_forward_{b}b"]
    ratios["ours_intersect"] = figures["ours_intersect"] / figures["mitsuba_intersect"]
    ratios["ours_occluded"] = figures["ours_occluded"] / figures["mitsuba_occluded"]

    # The table.
    rows = []
    for b in bounces:
        mi_fig = figures[f"mitsuba_forward_{b}b"]
        rows.append((f"forward, {b} bounce{'s' if b > 1 else ''} (paths/s)", figures[f"ours_forward_{b}b"],
                     mi_fig, ratios[f"ours_forward_{b}b"]))
        rows.append((f"fwd+bwd, {b} bounce{'s' if b > 1 else ''} (paths/s)", figures[f"ours_fwd_bwd_{b}b"],
                     mi_fig, ratios[f"ours_fwd_bwd_{b}b"]))
    rows.append(("closest hit (rays/s)", figures["ours_intersect"], figures["mitsuba_intersect"],
                 ratios["ours_intersect"]))
    rows.append(("occlusion (rays/s)", figures["ours_occluded"], figures["mitsuba_occluded"],
                 ratios["ours_occluded"]))
    print()
    print(f"{'figure':<34} {'ours':>12} {'Mitsuba 3':>12} {'ours/Mitsuba':>13}")
    print("-" * 74)
    for name, ours, theirs, ratio in rows:
        print(f"{name:<34} {ours:12.4g} {theirs:12.4g} {ratio:13.3f}")
    print("-" * 74)
    print("fwd+bwd rows are compared with Mitsuba's forward (Mitsuba is not differentiated here).")
    print(f"ray queries: {n} random rays, {100 * sanity['ray_hit_fraction']:.1f}% hit; hit/miss agreement "
          f"{100 * sanity['ray_hit_agreement']:.3f}%, occlusion agreement "
          f"{100 * sanity['occluded_agreement']:.3f}%")
    means = ", ".join(f"{b}b ours {sanity[f'mean_radiance_{b}b']['ours']:.4f} / Mitsuba "
                      f"{sanity[f'mean_radiance_{b}b']['mitsuba']:.4f}" for b in bounces)
    print(f"image mean radiance (different BRDFs, rough check only): {means}")
    if contended:
        print(f"WARNING: other processes used > {100 * CONTENDED:.0f}% of the CPUs during the best run of "
              f"{', '.join(contended)}; those figures are pessimistic (torch's threads stall when a core is "
              "taken): rerun on an idle machine")
    warmups = ", ".join(f"{b}b {timings[f'mitsuba_warmup_{b}b']:.1f} s" for b in bounces)
    total = time.perf_counter() - t_start
    print(f"Mitsuba JIT warm-up (excluded): {warmups}; total benchmark time {total:.0f} s")

    if not args.no_save:
        path = write_result("render", {
            "config": {"mesh": str(args.mesh), "faces": mesh.num_faces, "envmap": str(args.envmap),
                       "resolution": res, "spp": spp, "paths": paths, "bounces": bounces, "rays": n,
                       "repeats": args.repeats, "budget_s": args.budget, "statistic": "min",
                       "threads": args.threads, "chunk": args.chunk, "view": args.view,
                       "quick": args.quick, "rr_depth": RR_DEPTH_OFF,
                       "material": {"base_color": BASE_COLOR, "roughness": ROUGHNESS, "metallic": METALLIC},
                       "mitsuba": {"version": mi.__version__, "variant": mi.variant(),
                                   "bsdf": "twosided(principled)"}},
            "per_second": figures,
            "ratio_to_mitsuba": ratios,
            "seconds": timings,
            "sanity": sanity,
            "contended": contended,
            "total_seconds": total,
        })
        print(f"appended to {path}")
    return 0 if all(math.isfinite(v) for v in figures.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
