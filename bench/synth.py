"""Synthetic data engine: objects per hour and where an object's time goes (ray queries, material, writing).

Runs `neumatex_core.synth.generate` on `--objects` train objects (seed `--seed`, default 1000, so they are not the
objects of a real dataset) in a temporary folder with `--workers` processes at the default content options
(128 px, 32 spp, 8 photos, 2 held-out lightings at 16 spp), and prints:

1. objects per hour: measured (wall clock of the whole run, process start-up included) and from the workers' CPU
   seconds (`workers` x 3600 / CPU seconds per object: what `workers` idle cores give, since each worker is one
   thread and objects are independent; on a shared machine the wall-clock figure is lower by the contention);
2. the split of an object's time, summed over objects, in CPU and in wall-clock seconds:
   ray queries (Embree closest hits and shadow rays), the material field query (region and colour noise at each
   hit), material evaluation (the neural material's eval / sample / pdf: the basis MLPs), image writing (EXR, PNG,
   JSON, hashes), G-buffers (primary rays and ground-truth values at pixel centres), setup (shape, basis encoder,
   PBR fit) and the rest (the path tracer's own arithmetic: envmap sampling and lookups, frames, MIS, bookkeeping);
3. as a reference measured in the same run: object 0's 23 preset views rendered (one thread, nothing written) with
   its neural ground truth and with a uniform PBR material, as a ratio, and the whole object's CPU time against
   them.

`--from-timings DIR` summarises an existing dataset's timings.jsonl (e.g. the benchmark split) instead of making
objects. On a shared machine, the `foreign_cpu` figure says how much of the machine other processes used meanwhile.

    .venv/bin/python bench/synth.py                 # 4 objects on 2 workers, ~4 min on an idle 2-core CPU
    .venv/bin/python bench/synth.py --quick         # 2 objects at 32 px, 4 spp (smoke run)
    .venv/bin/python bench/synth.py --from-timings data/benchmark-test
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import _busy_cpu_seconds, argument_parser, write_result  # noqa: E402

from neumatex_core.geometry.camera import preset_views  # noqa: E402
from neumatex_core.materials.field import UniformPBR  # noqa: E402
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig  # noqa: E402
from neumatex_core.render.scene import Scene  # noqa: E402
from neumatex_core.synth import SynthConfig, generate  # noqa: E402
from neumatex_core.synth.dataset import TIMINGS, shared_files  # noqa: E402
from neumatex_core.synth.lighting import lighting_pixels, lighting_scale, yaw_rotation  # noqa: E402
from neumatex_core.synth.shapes import build_shape  # noqa: E402
from neumatex_core.synth.spec import object_spec  # noqa: E402

STAGES = ("rays", "field", "material", "write", "gbuffer", "setup")
OTHER = "other (path tracer arithmetic, envmap)"


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Seconds per object (median, min, max, sum) and each stage's share of the summed object time, in wall-clock
    seconds and, where the records have them, in CPU seconds of the worker processes (not inflated by other
    processes competing for the cores)."""
    out: dict[str, Any] = {"objects": len(records)}
    kinds = [("wall", "seconds", "stages")]
    if all("cpu_seconds" in r for r in records):
        kinds.append(("cpu", "cpu_seconds", "stages_cpu"))
    for kind, total_key, stage_key in kinds:
        total = sum(r[total_key] for r in records)
        stages = {s: sum(r[stage_key].get(s, 0.0) for r in records) for s in STAGES}
        stages[OTHER] = total - sum(stages.values())
        secs = [r[total_key] for r in records]
        out[kind] = {"object_seconds": {"median": statistics.median(secs), "min": min(secs), "max": max(secs),
                                        "sum": total},
                     "stage_seconds": stages, "stage_share": {k: v / total for k, v in stages.items()}}  # fmt: skip
    return out


def print_split(summary: dict[str, Any]) -> None:
    kinds = [k for k in ("cpu", "wall") if k in summary]
    for kind in kinds:
        s = summary[kind]["object_seconds"]
        print(f"{kind} seconds per object: median {s['median']:.1f}, min {s['min']:.1f}, max {s['max']:.1f}")
    print("\n| stage | " + " | ".join(f"{k} s (all objects) | {k} share" for k in kinds) + " |")
    print("|---|" + "---|---|" * len(kinds))
    for stage in summary[kinds[0]]["stage_seconds"]:
        cells = [f"{summary[k]['stage_seconds'][stage]:.1f} | {summary[k]['stage_share'][stage]:.1%}" for k in kinds]
        print(f"| {stage} | " + " | ".join(cells) + " |")


def reference_renders(cfg: SynthConfig, basis_device: str = "cpu") -> dict[str, dict[str, float]]:
    """Wall-clock and CPU seconds to render object 0's 23 preset views (one thread, nothing written) with its
    ground-truth neural field and with a uniform PBR material: {"wall": {"neural": s, "pbr": s}, "cpu": {...}}."""
    from neumatex_core.lighting.envmap import EnvironmentMap, envmap_rgb
    from neumatex_core.materials.neural_basis import load_basis
    from neumatex_core.synth.materials import ProceduralMaterialField, face_regions

    meshes, envmaps = shared_files(cfg)
    spec = object_spec(cfg.split, 0, cfg.seed, meshes, envmaps, cfg.relight_maps)
    pixels = lighting_pixels(spec.lighting, cfg.envmaps_dir())
    env = EnvironmentMap(envmap_rgb(pixels), yaw_rotation(spec.lighting.rotation_deg),
                         lighting_scale(spec.lighting, pixels))  # fmt: skip
    shape = build_shape(spec.shape, cfg.meshes_dir())
    neural = ProceduralMaterialField(spec.material, load_basis(basis_device),
                                     face_regions(spec.material, shape.mesh, shape.parts))  # fmt: skip
    tracer = PathTracer(PathTracerConfig(max_bounces=cfg.max_bounces, spp=cfg.spp))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    out: dict[str, dict[str, float]] = {"wall": {}, "cpu": {}}
    try:
        for name, field in (("neural", neural), ("pbr", UniformPBR((0.6, 0.5, 0.4), 0.4, 0.0))):
            scene = Scene(shape.mesh, env, field)
            start, cpu = time.perf_counter(), time.process_time()
            with torch.no_grad():
                for i, cam in enumerate(preset_views(cfg.resolution)):
                    tracer.render(scene, cam, seed=i)
            out["wall"][name] = time.perf_counter() - start
            out["cpu"][name] = time.process_time() - cpu
    finally:
        torch.set_num_threads(threads)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--objects", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--resolution", type=int, default=SynthConfig.resolution)
    parser.add_argument("--spp", type=int, default=SynthConfig.spp)
    parser.add_argument("--layered", action="store_true", help="also the analytic layered renders")
    parser.add_argument("--from-timings", type=str, default="", help="summarise DIR/timings.jsonl instead")
    parser.add_argument("--quick", action="store_true", help="2 objects, 32 px, 4 spp")
    parser.add_argument("--no-save", action="store_true")
    args = parser.parse_args(argv)
    if args.from_timings:
        folder = Path(args.from_timings)
        records = [json.loads(line) for line in (folder / TIMINGS).read_text().splitlines() if line.strip()]
        settings = json.loads((folder / "synth.json").read_text())
        print(f"{folder}: {len(records)} objects, content {settings['content']}")
        summary = summarise(records)
        print_split(summary)
        if not args.no_save:
            path = write_result("synth", {"source": str(folder), "content": settings["content"], **summary})
            print(f"\nappended to {path}")
        return 0
    if args.quick:
        args.objects, args.resolution, args.spp = 2, 32, 4
    out = Path(tempfile.mkdtemp(prefix="neumatex-bench-synth-"))
    cfg = SynthConfig(n=args.objects, out=str(out / "data"), split="train", seed=args.seed,
                      resolution=args.resolution, spp=args.spp, layered=args.layered, workers=args.workers,
                      progress=False)  # fmt: skip
    try:
        print(f"{args.objects} train objects (seed {args.seed}) on {args.workers} workers; content {cfg.content()}")
        busy0, own0, start = _busy_cpu_seconds(), os.times(), time.perf_counter()
        def progress(done: int, total: int, r: dict[str, Any] | None) -> None:
            if r is not None:
                print(f"  {r['id']}: {r['seconds']:.1f} s wall, {r['cpu_seconds']:.1f} s CPU {r['stages_cpu']}",
                      flush=True)

        result = generate(cfg, progress)
        wall = time.perf_counter() - start
        busy1, own1 = _busy_cpu_seconds(), os.times()
        mine = sum(own1[:4]) - sum(own0[:4])  # user + system, ours and our reaped workers'
        foreign = None
        if busy0 is not None and busy1 is not None:
            foreign = max(0.0, (busy1 - busy0 - mine) / (wall * (os.cpu_count() or 1)))
        records = [json.loads(line) for line in (Path(cfg.out) / TIMINGS).read_text().splitlines()]
        summary = summarise(records)
        per_hour = len(result.made) / wall * 3600
        cpu_total = summary["cpu"]["object_seconds"]["sum"]
        per_hour_idle = args.workers * 3600 * len(records) / cpu_total  # each worker: one thread, one core
        contention = "" if foreign is None else f"; other processes used {foreign:.0%} of the CPUs meanwhile"
        print(f"\nmeasured: {per_hour:.1f} objects per hour on {args.workers} workers ({wall:.1f} s wall for "
              f"{len(result.made)} objects, process start-up included{contention})")
        print(f"from CPU seconds: {per_hour_idle:.1f} objects per hour on {args.workers} idle cores "
              f"({cpu_total / len(records):.1f} CPU s per object, one thread each)\n")
        print_split(summary)
        ref = reference_renders(cfg)
        first = next(r for r in records if r["id"].endswith("000000"))
        n_views = 23 + cfg.photos + 17 * cfg.relight_maps
        neural, pbr = ref["cpu"]["neural"], ref["cpu"]["pbr"]
        print(f"\nreference, object 0 (one thread, nothing written, CPU s): its 23 preset views take {neural:.1f} s "
              f"with the neural material, {pbr:.1f} s with a uniform PBR material ({neural / pbr:.1f}x); the "
              f"whole object ({n_views} views{' + 23 layered' if cfg.layered else ''}, G-buffers, files) took "
              f"{first['cpu_seconds']:.1f} s = {first['cpu_seconds'] / neural:.1f}x its 23 neural views")
        if not args.no_save:
            path = write_result("synth", {"settings": vars(args), "content": cfg.content(), "wall_s": wall,
                                          "objects_per_hour": per_hour, "objects_per_hour_idle_cpu": per_hour_idle,
                                          "foreign_cpu": foreign, "reference_23_views_s": ref, **summary,
                                          "records": records})  # fmt: skip
            print(f"\nappended to {path}")
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
