"""`neumatex extract --compare-pbr`: the PBR baseline's TTO on the same capture, scored beside the neural material.

The baseline is the evaluation's "pbr" variant (eval/variants.py: the LMRM's PBR head on its triplane, no anchor,
material "pbr"; NVDiffRecMC++ in the paper's table 1), run through the same `tto.pbr_start.solve` as the extraction,
from the same lmrm-stage prediction, for as many Adam steps as the extraction's whole TTO (equal steps). It is
re-rendered at the photos the export stage scores (same picks, samples, bounces, seed, masks) and its PSNR is written
beside the neural one: `psnr_photos_pbr_baseline` and `psnr_gain_vs_pbr_baseline_db` in the asset's manifest metrics,
and a table in its report. The result is kept in WORK/compare_pbr/done.json, so a rerun does not repeat the TTO.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neumatex_core.pipeline import (
    ExtractConfig,
    PipelineError,
    _normalised,
    _open_capture,
    _photo_set,
    load_prediction,
    photo_tonemap,
)

STAGE = "compare_pbr"


def run_pbr_baseline(capture: Path, work: Path, config: ExtractConfig) -> dict[str, Any]:
    """Run (or read back) the PBR baseline TTO and its photo PSNR; the metrics dict."""
    from neumatex_core.eval.metrics import psnr
    from neumatex_core.eval.variants import variant_config
    from neumatex_core.geometry.gbuffer import render_gbuffer
    from neumatex_core.materials.neural_basis import load_basis
    from neumatex_core.render import PathTracer, PathTracerConfig, Scene
    from neumatex_core.tto.pbr_start import solve

    done = Path(work) / STAGE / "done.json"
    if done.is_file():
        return dict(json.loads(done.read_text()))
    device = config.torch_device()
    pred, record = load_prediction(work, device)
    neural = config.tto_config()
    tto = variant_config("pbr", neural)
    assert tto is not None
    tto = replace(tto, steps=neural.total_steps(), basis="", seed=config.seed)
    t0 = time.perf_counter()
    with _open_capture(capture) as cap:
        norm = _normalised(cap, work, device)
        photos = _photo_set(norm, device)
        result = solve(tto, norm.mesh, norm.envmap, photos, cap.tonemap, pred, load_basis(str(device)),
                       anchor_available=bool(record["trained"]))  # fmt: skip
        seconds = time.perf_counter() - t0
        n_eval = min(config.eval_photos, len(cap.frames))
        if n_eval == 0:
            raise PipelineError("--compare-pbr scores the photos the export stage re-renders; the preset has "
                                "eval_photos = 0")  # fmt: skip
        picks = np.linspace(0, len(cap.frames) - 1, n_eval).round().astype(int).tolist()
        scene = Scene(result.mesh or norm.mesh, norm.envmap, result.params.field(), device=device)
        tracer = PathTracer(PathTracerConfig(spp=config.eval_spp, max_bounces=max(neural.max_bounces, 2)))
        scores = []
        with torch.no_grad():
            for n, i in enumerate(picks):  # as the export stage scores its renders (same seeds, masks, tonemap)
                img = tracer.render(scene, norm.cameras[i], seed=config.seed + n)
                m = render_gbuffer(norm.mesh, norm.cameras[i]).mask
                user = cap.load_mask(i)
                if user is not None:
                    m = m & torch.as_tensor(user)
                shown = photo_tonemap(cap, i, result.exposure).apply(img.cpu())  # the photo's own (fitted) exposure
                scores.append(float(psnr(shown, torch.as_tensor(cap.load_image(i)), m)))
    tail = result.history[-max(1, len(result.history) // 10):]
    metrics = {"psnr_photos_pbr_baseline": float(np.mean(scores)), "pbr_baseline_steps": float(tto.steps),
               "pbr_baseline_tto_s": seconds, "pbr_baseline_psnr_batch": float(np.mean([r["psnr"] for r in tail]))}
    done.parent.mkdir(parents=True, exist_ok=True)
    done.write_text(json.dumps(metrics, indent=1) + "\n")
    return metrics


def compare_pbr(capture: Path, asset: Path, work: Path, config: ExtractConfig) -> dict[str, float]:
    """Run the baseline and write its scores beside the neural ones into the asset folder `asset` (manifest metrics
    and report); returns the metrics added."""
    from neumatex_core.report import append_table

    if not (asset / "manifest.json").is_file():
        raise PipelineError(f"{asset}: --compare-pbr writes into an asset folder (not a .zip)")
    baseline = run_pbr_baseline(capture, work, config)
    manifest = json.loads((asset / "manifest.json").read_text())
    metrics = manifest.setdefault("metrics", {})
    added = {k: float(v) for k, v in baseline.items()}
    if "psnr_photos" in metrics:
        added["psnr_gain_vs_pbr_baseline_db"] = float(metrics["psnr_photos"]) - added["psnr_photos_pbr_baseline"]
    metrics.update(added)
    (asset / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    report = asset / "report" / "index.html"
    if report.is_file():
        rows = {"neural material (this asset)": metrics.get("psnr_photos", float("nan")),
                "its PBR fallback (fitted to it)": metrics.get("psnr_photos_pbr", float("nan")),
                "PBR baseline TTO (--compare-pbr)": added["psnr_photos_pbr_baseline"]}  # fmt: skip
        append_table(report, "Against the PBR baseline (photo PSNR, dB)", rows,
                     f"The PBR baseline's TTO (eval variant 'pbr') ran {int(added['pbr_baseline_steps'])} steps, as "
                     "many as the extraction's TTO, and is scored on the same photos with the same samples.")
    return added
