"""End to end from random-pose photographs against the true preset views (issue 18): the same extraction (the cpu
preset with eval variant `pbr_start_anchor_01`, the extraction's default until 2026-11-27, and the PBR baseline) run
twice per object, once on the object itself (its 23 preset views) and once on its random-pose capture
(`<object>/random_pose`, 100 JPEG photos with per-photo exposure and lens distortion: `neumatex synth-random-pose`),
both scored the same way on the object (`eval/harness.evaluate_variant` with `capture_dir`): PathTrace and Relight
clean against the object's references, BaseColor and Latents against its ground truth.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/random_pose_e2e.py [--data data/benchmark-test]
        [--objects first:2] [--variants pbr_start_anchor_01,pbr] [--workers 2]
    .venv/bin/python bench/random_pose_e2e.py --summarise    # the table over every object measured so far

Prints each metric from random-pose photos, from the preset views and the difference (dB) per object and the mean;
appends a JSON line to bench/results/random_pose_e2e.jsonl. Needs the objects' references (`neumatex references`)
and random-pose captures.
"""

from __future__ import annotations

import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, mean_se, write_result  # noqa: E402

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
    parser = argument_parser(__doc__)
    parser.add_argument("--data", default="data/benchmark-test")
    parser.add_argument("--objects", default="first:2")
    parser.add_argument("--variants", default="pbr_start_anchor_01,pbr")
    parser.add_argument("--work", default="runs/bench-random-pose-e2e")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--summarise", action="store_true",
                        help="print the table over every object in bench/results/random_pose_e2e.jsonl and stop")
    args = parser.parse_args()
    if args.summarise:
        return summarise(Path(__file__).resolve().parent / "results" / "random_pose_e2e.jsonl",
                         args.variants.split(",")[0])
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


def summarise(results: Path, variant: str) -> int:
    """The table over every object measured so far (the latest row per object in `results`): per metric the
    mean of random-pose and of preset views, and the paired difference with its standard error over objects."""
    import json

    latest: dict[str, dict[str, Any]] = {}
    baseline: dict[str, dict[str, Any]] = {}  # the PBR baseline's latest row per object, where one was run
    for line in results.read_text().splitlines():
        for row in json.loads(line).get("rows", []):
            if f"random_pose/{variant}" in row and f"preset/{variant}" in row:
                latest[row["object"]] = row
            if variant != "pbr" and "preset/pbr" in row and "random_pose/pbr" in row:
                baseline[row["object"]] = row
    if not latest:
        print(f"{results}: no rows for variant {variant!r}")
        return 1
    names = {"psnr_pathtrace_clean": "PathTrace, clean", "psnr_relight_clean": "Relight, clean",
             "psnr_basecolor": "BaseColor", "psnr_latents": "Latents"}  # fmt: skip
    print(f"variant {variant}, objects {', '.join(sorted(latest))} (n={len(latest)})")
    print("| PSNR, dB, random-pose / preset views | PathTrace clean | Relight clean | BaseColor | Latents |")
    print("|---|---|---|---|---|")
    for name in sorted(latest):
        r = latest[name]
        cells = [f"{r[f'random_pose/{variant}'].get(m, np.nan):.2f} / {r[f'preset/{variant}'].get(m, np.nan):.2f}"
                 for m in METRICS]  # fmt: skip
        print(f"| {name} | {' | '.join(cells)} |")
    print()
    print("| PSNR, dB | random-pose photos | preset views | random-pose - preset (paired, +- s.e.) | worst object |")
    print("|---|---|---|---|---|")
    for m in METRICS:
        pairs = [(r[f"random_pose/{variant}"].get(m, np.nan), r[f"preset/{variant}"].get(m, np.nan))
                 for r in latest.values()]  # fmt: skip
        d = np.array([a - b for a, b in pairs])
        if np.isnan(d).all():
            continue
        _, se = mean_se(d)
        print(f"| {names[m]} | {np.mean([a for a, _ in pairs]):.2f} | {np.mean([b for _, b in pairs]):.2f} | "
              f"{np.mean(d):+.2f} +- {se:.2f} | {d[np.argmax(np.abs(d))]:+.2f} |")
    paired = sorted(set(latest) & set(baseline))
    if paired:
        print(f"\n{variant} / the PBR baseline and the paired difference over the {len(paired)} objects that have "
              "both (dB, +- s.e.)")
        print("| PSNR, dB | from preset views: ours / PBR: ours - PBR | from random-pose photos |")
        print("|---|---|---|")
        for m in METRICS:
            cells = []
            for source in SOURCES:
                ab = np.array([(latest[o][f"{source}/{variant}"].get(m, np.nan),
                                baseline[o][f"{source}/pbr"].get(m, np.nan)) for o in paired])  # fmt: skip
                ab = ab[np.isfinite(ab).all(axis=1)]
                d = ab[:, 0] - ab[:, 1]
                cells.append(f"{ab[:, 0].mean():.2f} / {ab[:, 1].mean():.2f}: {np.mean(d):+.2f} +- "
                             f"{np.std(d, ddof=1) / np.sqrt(len(d)):.2f} (n={len(d)})" if len(d) > 1 else "-")
            print(f"| {names[m]} | {' | '.join(cells)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
