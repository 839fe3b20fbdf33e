"""Extraction on captures rendered by Blender Cycles: the default neural recipe against the PBR baseline.

    make cycles-env
    neumatex cycles-capture --mesh teapot.obj --envmap courtyard.exr --envmap-yaw 30 --preset coat \\
        --resolution 64 --spp 256 --random 8 --out runs/cycles/coat          # and sheen, metal, diffuse
    NEUMATEX_SHARED=../shared .venv/bin/python bench/cycles_extract.py runs/cycles/coat runs/cycles/sheen

Per capture (23 preset views, 8 held-out photos at random poses in photos/, held-out maps in relight/<j>/; Cycles,
256 spp): the pipeline's validate / prepare_views / lmrm stages, then two TTOs on the preset views through
`tto.solve`, as `neumatex eval` runs them: the PBR baseline (material "pbr", 400 steps from the LMRM's PBR head) and
the extraction's default (`ExtractConfig.preset("cpu")`: PBR TTO, then the neural TTO from its solution anchored
to it). Each is rendered at --spp with our path tracer and scored (PSNR after the capture's tonemap, covered pixels)
on the held-out photos (capture lighting, unseen poses) and on every relit view (unseen lighting). Prints neural -
PBR per capture and writes a JSON line to bench/results/cycles_extract.jsonl. The reference is Cycles itself at
256 spp, so both rows carry the same Cycles noise; the difference is the figure.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import write_result  # noqa: E402

from neumatex_core.capture import load_capture  # noqa: E402
from neumatex_core.eval.harness import _render_psnr  # noqa: E402
from neumatex_core.eval.references import harness_envmap  # noqa: E402
from neumatex_core.materials.neural_basis import load_basis  # noqa: E402
from neumatex_core.pipeline import ExtractConfig, load_prediction, run_stage  # noqa: E402
from neumatex_core.tto.data import PhotoSet  # noqa: E402
from neumatex_core.tto.pbr_start import solve  # noqa: E402


def bench_capture(capture: Path, work: Path, spp: int, bounces: int) -> dict[str, Any]:
    config = ExtractConfig.preset("cpu", device="cpu")
    for stage in ("validate", "prepare_views", "lmrm"):
        run_stage(stage, capture, work, config)
    pred, _ = load_prediction(work)
    cap = load_capture(capture)
    mesh = cap.load_mesh()
    photos = PhotoSet([cap.load_image(i) for i in range(len(cap.frames))], cap.cameras, mesh,
                      [cap.load_mask(i) for i in range(len(cap.frames))])  # fmt: skip
    variants = {"pbr": replace(config.tto_config(), material="pbr", init="lmrm", reg="none"),
                "neural": config.tto_config()}  # fmt: skip
    held_out = capture / "photos"
    n_photos = len(load_capture(held_out).frames)
    relit = sorted(p for p in (capture / "relight").glob("*") if (p / "transforms.json").is_file())
    out: dict[str, Any] = {"capture": str(capture), "recipe": variants["neural"].to_dict()}
    for name, tto in variants.items():
        t0 = time.perf_counter()
        result = solve(tto, mesh, harness_envmap(cap), photos, cap.tonemap, pred, load_basis(), truth=None)
        seconds = time.perf_counter() - t0
        field, scene_mesh = result.params.field(), result.mesh or mesh
        relit_db = [_render_psnr(r, field, range(len(load_capture(r).frames)), spp, bounces, 0, scene_mesh)
                    for r in relit]  # fmt: skip
        out[name] = {"tto_s": round(seconds, 1), "relit_maps_db": relit_db,
                     "photos_db": _render_psnr(held_out, field, range(n_photos), spp, bounces, 0, scene_mesh),
                     "relit_db": sum(relit_db) / max(len(relit_db), 1)}  # fmt: skip
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("captures", nargs="+", type=Path, help="captures written by `neumatex cycles-capture`")
    parser.add_argument("--work", default="runs/bench-cycles-extract", type=Path)
    parser.add_argument("--spp", type=int, default=256, help="samples per pixel of our scored renders")
    parser.add_argument("--max-bounces", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for capture in args.captures:
        row = bench_capture(capture, args.work / capture.name, args.spp, args.max_bounces)
        rows.append(row)
        n, p = row["neural"], row["pbr"]
        print(f"{capture.name}: held-out photos neural {n['photos_db']:.2f} dB, PBR {p['photos_db']:.2f} "
              f"({n['photos_db'] - p['photos_db']:+.2f}); relit neural {n['relit_db']:.2f}, PBR {p['relit_db']:.2f} "
              f"({n['relit_db'] - p['relit_db']:+.2f}); TTO {n['tto_s']:.0f} s / {p['tto_s']:.0f} s", flush=True)
    print(f"appended to {write_result('cycles_extract', {'spp': args.spp, 'rows': rows})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
