"""End to end from random-pose photographs against the true preset views (issue 18): the same extraction (the cpu
preset's default TTO, eval variant `pbr_start_anchor_01`, and the PBR baseline) run twice per object, once on the
object itself (its 23 preset views) and once on its random-pose capture (`<object>/random_pose`, 100 JPEG photos
with per-photo exposure and lens distortion: `neumatex synth-random-pose`), both scored the same way on the object
(`eval/harness.evaluate_variant` with `capture_dir`): PathTrace and Relight clean against the object's references,
BaseColor and Latents against its ground truth.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/random_pose_e2e.py [--data data/benchmark-test]
        [--objects first:2] [--variants pbr_start_anchor_01,pbr] [--workers 2]

Prints each metric from random-pose photos, from the preset views and the difference (dB) per object and the mean;
appends a JSON line to bench/results/random_pose_e2e.jsonl. Needs the objects' references (`neumatex references`)
and random-pose captures.
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import write_result  # noqa: E402

from neumatex_core.eval.harness import evaluate_variant  # noqa: E402
from neumatex_core.eval.suite import select_objects  # noqa: E402
from neumatex_core.pipeline import ExtractConfig  # noqa: E402

METRICS = ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_basecolor", "psnr_latents")
SOURCES = ("preset", "random_pose")


def one(object_dir: str, work: str, variants: list[str]) -> dict[str, Any]:
    torch.set_num_threads(1)
    config = ExtractConfig.preset("cpu", device="cpu")
    row: dict[str, Any] = {"object": Path(object_dir).name}
    for source in SOURCES:
        capture = None if source == "preset" else Path(object_dir) / "random_pose"
        for variant in variants:
            scores = evaluate_variant(object_dir, Path(work) / source, variant, config, relight_views=(0, 8, 16),
                                      capture_dir=capture)  # fmt: skip
            row[f"{source}/{variant}"] = {m: float(scores[m]) for m in (*METRICS, "tto_minutes") if m in scores}
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", default="data/benchmark-test")
    parser.add_argument("--objects", default="first:2")
    parser.add_argument("--variants", default="pbr_start_anchor_01,pbr")
    parser.add_argument("--work", default="runs/bench-random-pose-e2e")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    data = Path(args.data)
    objects = select_objects(data, args.objects)
    variants = args.variants.split(",")
    with ProcessPoolExecutor(args.workers) as pool:
        rows = list(pool.map(one, [str(data / o) for o in objects], [str(Path(args.work) / o) for o in objects],
                             [variants] * len(objects)))  # fmt: skip
    summary: dict[str, dict[str, float]] = {}
    for variant in variants:
        for m in METRICS:
            diffs = [r[f"random_pose/{variant}"][m] - r[f"preset/{variant}"][m] for r in rows
                     if m in r[f"random_pose/{variant}"] and m in r[f"preset/{variant}"]]  # fmt: skip
            if not diffs:
                continue
            summary.setdefault(variant, {})[m] = float(np.mean(diffs))
            for r in rows:
                print(f"{r['object']} {variant} {m}: random-pose {r[f'random_pose/{variant}'][m]:.2f} dB, preset "
                      f"views {r[f'preset/{variant}'][m]:.2f} dB")  # fmt: skip
            print(f"  mean random-pose - preset: {np.mean(diffs):+.2f} dB over {len(diffs)} objects", flush=True)
    print(f"appended to {write_result('random_pose_e2e', {'variants': variants, 'rows': rows, 'mean_diff': summary})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
