"""Conventions check of the Blender Cycles capture writer: a plain-diffuse Cycles capture against our path tracer.

    make cycles-env                                   # once: .venv-cycles with bpy
    NEUMATEX_SHARED=../shared .venv/bin/python bench/cycles_agreement.py [--mesh teapot.obj --envmap courtyard.exr
        --views 0,7,20 --resolution 64 --spp 256 --ours-spp 4096]

Cycles renders a `diffuse` capture (pure Lambertian Principled BSDF) of one shared mesh under one shared map
(tools/cycles_capture.py), twice with different seeds; our PathTracer renders the same mesh, cameras and map with
UniformPBR(base, roughness=1, metallic=0, dielectric_f0=0) at max_bounces 3. Printed per view, after the
capture's tonemap: PSNR over the covered pixels (the figure that must reach --threshold, 35 dB), PSNR of the
background (the map seen directly: cameras and map rotation alone), the linear brightness ratio Cycles / ours,
and the noise ceiling (Cycles seed-vs-seed PSNR + 3.01 dB: what an exact, noise-free reference would score).
Appends one JSON line to bench/results/cycles.jsonl; writes ours | Cycles | 4x|difference| to --out/compare.png.
Exits 1 when the mean covered-pixel PSNR is below --threshold.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, write_result  # noqa: E402

from neumatex_core.synth.cycles import (  # noqa: E402
    CyclesError,
    compare_with_ours,
    render_cycles_capture,
    seed_noise_psnr,
)

NOISE_SEED = 7919  # Cycles seed of the second capture (any seed unrelated to 0.. of the first)


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__doc__)
    p.add_argument("--mesh", default="teapot.obj", help="mesh file or shared mesh name")
    p.add_argument("--envmap", default="courtyard.exr", help="map file or shared map name")
    p.add_argument("--envmap-yaw", type=float, default=30.0, help="envmap_to_world yaw (degrees): tests the rotation")
    p.add_argument("--views", default="0,7,20", help="preset view indices")
    p.add_argument("--resolution", type=int, default=64, help="image size (pixels)")
    p.add_argument("--spp", type=int, default=256, help="Cycles samples per pixel")
    p.add_argument("--ours-spp", type=int, default=4096, help="our samples per pixel (the reference)")
    p.add_argument("--threads", type=int, default=1, help="Cycles render threads and torch threads")
    p.add_argument("--threshold", type=float, default=35.0, help="mean covered-pixel PSNR that passes (dB)")
    p.add_argument("--no-noise", action="store_true", help="skip the second Cycles capture (noise ceiling)")
    p.add_argument("--out", default="out/bench/cycles-agreement", help="work folder (captures, compare.png)")
    args = p.parse_args(argv)

    import torch

    from neumatex_core.imageio import write_image

    torch.set_num_threads(args.threads)

    out = Path(args.out)
    common: dict[str, Any] = dict(mesh=args.mesh, envmap=args.envmap, preset="diffuse", resolution=args.resolution,
                                  spp=args.spp, views=args.views, envmap_yaw=args.envmap_yaw, threads=args.threads)
    start = time.perf_counter()
    try:
        record = render_cycles_capture(out=out / "cycles", seed=0, **common)
        noise = None
        if not args.no_noise:
            render_cycles_capture(out=out / "cycles-seed2", seed=NOISE_SEED, **common)
            noise = seed_noise_psnr(out / "cycles", out / "cycles-seed2")
    except CyclesError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    cycles_s = time.perf_counter() - start
    start = time.perf_counter()
    images: dict[str, np.ndarray] = {}
    views = compare_with_ours(out / "cycles", spp=args.ours_spp, images=images)
    ours_s = time.perf_counter() - start
    write_image(out / "compare.png", np.concatenate(list(images.values()), axis=0))

    print(f"Cycles ({record['renderer']}, {args.spp} spp) vs ours ({args.ours_spp} spp), diffuse {args.mesh} under "
          f"{args.envmap} (yaw {args.envmap_yaw:g}), {args.resolution} px, tonemapped")
    print(f"{'view':>18} {'PSNR dB':>8} {'bg dB':>7} {'ceiling':>8}  Cycles/ours (linear RGB)")
    for k, v in enumerate(views):
        ceiling = f"{noise[k] + 10 * math.log10(2):8.2f}" if noise else f"{'-':>8}"
        print(f"{v.file:>18} {v.psnr:8.2f} {v.psnr_background:7.2f} {ceiling}  "
              + " ".join(f"{r:.4f}" for r in v.ratio))
    mean = float(np.mean([v.psnr for v in views]))
    verdict = "PASS" if mean >= args.threshold else "FAIL"
    print(f"{'mean':>18} {mean:8.2f} {np.mean([v.psnr_background for v in views]):7.2f}"
          f"{'':9}  {verdict} (threshold {args.threshold:g} dB); Cycles {cycles_s:.1f} s, ours {ours_s:.1f} s")
    path = write_result("cycles", {
        "mesh": Path(args.mesh).name, "envmap": Path(args.envmap).name, "envmap_yaw": args.envmap_yaw,
        "views": args.views, "resolution": args.resolution, "spp": args.spp, "ours_spp": args.ours_spp,
        "max_bounces": 3, "renderer": record["renderer"], "threads": args.threads,
        "psnr": [round(v.psnr, 3) for v in views], "psnr_mean": round(mean, 3),
        "psnr_background": [round(v.psnr_background, 3) for v in views],
        "noise_ceiling": [round(n + 10 * math.log10(2), 3) for n in noise] if noise else None,
        "ratio": [[round(r, 5) for r in v.ratio] for v in views],
        "mask_agreement": [round(v.mask_agreement, 5) for v in views],
        "threshold": args.threshold, "pass": mean >= args.threshold,
        "cycles_s": round(cycles_s, 2), "ours_s": round(ours_s, 2), "cycles_render_s": record["timing"]["render_s"],
        "torch_threads": torch.get_num_threads(),
    })  # fmt: skip
    print(f"appended to {path}")
    return 0 if mean >= args.threshold else 1


if __name__ == "__main__":
    sys.exit(main())
