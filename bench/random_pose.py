"""How well the pipeline's prepare_views stage synthesises the 23 preset views from a random-pose capture
(`neumatex synth-random-pose`, docs/benchmark.md "Random-pose captures"), and what it costs.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/random_pose.py [--data data/benchmark-test]
        [--objects first:2] [--preset cpu] [--view-resolution R] [--threads 2]
    .venv/bin/python bench/random_pose.py --summarise [--view-resolution 64]   # docs/benchmark.md's table rows

For each object: `run_stage("validate")` then `run_stage("prepare_views")` (timed) on <object>/random_pose/ (100 JPEG
photos with per-photo exposure and lens distortion), then the synthesised views (display, the stage's sRGB at the
capture's exposure) against the object's own preset views, which are its 23 frames, truly rendered: their linear
renders box-filtered to the view resolution and sRGB-encoded. PSNR (peak 1) over the object's mask (truth pixels
fully covered, and the synthesised mask), pooled over the 23 views; also over the pixels some photo observed only
(`observed`), and the observed fraction. Prints per object and the mean, and appends a JSON line to
bench/results/random_pose.jsonl. The truth renders carry their own Monte Carlo noise (32 spp), so the PSNR has a
ceiling well below infinity.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, time_repeats, write_result  # noqa: E402

from neumatex_core.capture.tonemap import Tonemap  # noqa: E402
from neumatex_core.eval.suite import select_objects  # noqa: E402
from neumatex_core.imageio import read_image  # noqa: E402
from neumatex_core.pipeline import ExtractConfig, run_stage  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def box(image: np.ndarray, factor: int) -> np.ndarray:
    """[H, W, C] -> [H / f, W / f, C], mean over f x f blocks."""
    h, w, c = image.shape
    return image.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3))


def psnr(mse: float) -> float:
    return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")


def truth_views(object_dir: Path, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """(display [23, R, R, 3], fully covered [23, R, R] bool) of the object's own 23 preset views."""
    frames = json.loads((object_dir / "transforms.json").read_text())["frames"]
    imgs, masks = [], []
    for f in frames:
        lin = read_image(object_dir / f["linear_path"])[:, :, :3]
        cover = read_image(object_dir / f["mask_path"])[:, :, :1]
        factor = lin.shape[0] // resolution
        if factor * resolution != lin.shape[0]:
            raise ValueError(f"{object_dir}: views of {lin.shape[0]} px do not box-filter to {resolution} px")
        imgs.append(Tonemap().apply_numpy(box(lin, factor)))
        masks.append(box(cover, factor)[:, :, 0] > 0.999)
    return np.stack(imgs), np.stack(masks)


def bench_object(object_dir: Path, config: ExtractConfig, root: Path) -> dict[str, Any]:
    from safetensors.torch import load_file

    capture = object_dir / "random_pose"
    if not (capture / "transforms.json").is_file():
        raise SystemExit(f"{capture}: missing; run `neumatex synth-random-pose {object_dir.parent} ...` first")
    work = root / object_dir.name
    run_stage("validate", capture, work, config)
    timing = time_repeats(lambda: run_stage("prepare_views", capture, work, config), repeats=1)
    views = load_file(str(work / "prepare_views" / "views.safetensors"))
    source = json.loads((work / "prepare_views" / "views.json").read_text())["source"]
    display = views["display"].numpy()
    made_mask, observed = views["mask"].numpy() > 0, views["observed"].numpy() > 0
    truth, cover = truth_views(object_dir, display.shape[1])
    sel = cover & made_mask
    err = ((display - truth) ** 2).mean(axis=-1)
    per_view = [psnr(float(err[v][sel[v]].mean())) for v in range(len(err))]
    n_photos = len(json.loads((capture / "transforms.json").read_text())["frames"])
    return {"object": object_dir.name, "photos": n_photos, "view_resolution": int(display.shape[1]),
            "psnr_mask": psnr(float(err[sel].mean())), "psnr_observed": psnr(float(err[sel & observed].mean())),
            "psnr_per_view": [round(p, 3) for p in per_view],
            "observed_fraction": float((sel & observed).sum() / max(int(sel.sum()), 1)),
            "mask_iou": float((cover & made_mask).sum() / max(int((cover | made_mask).sum()), 1)),
            "prepare_views_s": timing["min"], "prepare_views_minutes": timing["min"] / 60,
            "foreign_cpu": timing["foreign_cpu"], "source": source}  # fmt: skip


def main() -> int:
    ap = argument_parser(__doc__)
    ap.add_argument("--data", default=str(REPO / "data" / "benchmark-test"))
    ap.add_argument("--objects", default="first:2")
    ap.add_argument("--preset", default="cpu", choices=["tiny", "cpu", "gpu"])
    ap.add_argument("--view-resolution", type=int, default=0, help="0: the preset's")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--summarise", action="store_true",
                    help="print the table rows over every object in bench/results/random_pose.jsonl and stop")
    args = ap.parse_args()
    if args.summarise:
        return summarise(Path(__file__).resolve().parent / "results" / "random_pose.jsonl", args.view_resolution or 64)
    torch.set_num_threads(args.threads)
    config = ExtractConfig.preset(args.preset, device="cpu")
    if args.view_resolution:
        config = replace(config, view_resolution=args.view_resolution)
    data = Path(args.data)
    root = Path(tempfile.mkdtemp(prefix="bench-random-pose-"))
    rows = []
    try:
        for obj in select_objects(data, args.objects):
            row = bench_object(data / obj, config, root)
            rows.append(row)
            print(f"{obj}: {row['photos']} photos -> 23 views of {row['view_resolution']} px: PSNR "
                  f"{row['psnr_mask']:.2f} dB over the object's mask ({row['psnr_observed']:.2f} dB where observed, "
                  f"{row['observed_fraction']:.1%} observed, mask IoU {row['mask_iou']:.3f}); prepare_views "
                  f"{row['prepare_views_minutes']:.3f} min", flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("psnr_mask", "psnr_observed", "observed_fraction",
                                                              "prepare_views_minutes")}  # fmt: skip
    record = {"config": {"data": str(data), "objects": args.objects, "preset": args.preset,
                         "view_resolution": config.view_resolution, "blend_k": config.blend_k,
                         "threads": args.threads}, "objects": rows, "mean": mean}  # fmt: skip
    path = write_result("random_pose", record)
    print(f"mean over {len(rows)} objects: PSNR {mean['psnr_mask']:.2f} dB over the mask "
          f"({mean['psnr_observed']:.2f} dB where observed, {mean['observed_fraction']:.1%} observed); prepare_views "
          f"{mean['prepare_views_minutes']:.3f} min per capture -> {path}")
    return 0


def summarise(results: Path, view_resolution: int) -> int:
    """docs/benchmark.md's rows: the latest measurement per object at `view_resolution`, then their mean."""
    latest: dict[str, dict[str, Any]] = {}
    for line in results.read_text().splitlines():
        for row in json.loads(line).get("objects", []):
            if row.get("view_resolution") == view_resolution:
                latest[row["object"]] = row
    if not latest:
        print(f"{results}: no objects at {view_resolution} px")
        return 1
    rows = [latest[k] for k in sorted(latest)]
    for r in rows:
        print(f"| {r['object']} | {view_resolution} px | {r['psnr_mask']:.2f} dB | "
              f"{r['prepare_views_minutes']:.3f} min | |")
    print(f"| mean of {len(rows)} | {view_resolution} px | {np.mean([r['psnr_mask'] for r in rows]):.2f} dB | "
          f"{np.mean([r['prepare_views_minutes'] for r in rows]):.3f} min | |")
    worst = min(rows, key=lambda r: r["psnr_mask"])
    print(f"worst: {worst['object']} {worst['psnr_mask']:.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
