"""`neumatex eval`: the paper's three tables on the benchmark split, plus relighting and minutes per object.

    neumatex eval data/benchmark-test --out runs/eval --doc docs/results.md [--objects every:4 --workers 2]

For each object the shared stages (validate, prepare_views, lmrm) run once into `OUT/work/<object>`; each distinct
TTO variant of the chosen tables (`eval/variants.py`; variants with identical settings, e.g. Table 2 (f) and Table 3
(c), run once) is scored by `harness.evaluate_variant` and stored as `OUT/results/<object>/<variant>.json`, so a
stopped run resumes where it was and finished pairs are never redone. When every pair is done (or with
`--allow-incomplete`; `--out OUT --report-only` writes the page of a stopped or running evaluation from what is
stored, with that run's settings), `write_results` aggregates mean and std over the objects that have every variant
into the tables of `docs/results.md` with the orderings the paper claims checked one by one (paired differences with
standard errors), the hand-written discussion in `results-discussion.md`
beside the page (when present), figure grids (reference, ours, PBR baseline; base colour,
latents, LMRM uncertainty) under `docs/results/`, and the exact command and commit.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Literal

import numpy as np

from neumatex_core.atomic import write_json_atomic
from neumatex_core.config import command_line, option
from neumatex_core.eval.harness import TRUTH
from neumatex_core.eval.plots import DifferenceRow, difference_chart
from neumatex_core.eval.variants import DEFAULT_VARIANT, PAPER_TABLES, TABLES, VARIANTS

METRICS = ("psnr_pathtrace", "psnr_basecolor", "psnr_latents", "psnr_relight", "tto_minutes", "psnr_pathtrace_clean",
           "psnr_relight_clean")
CLEAN_METRICS = ("psnr_pathtrace_clean", "psnr_relight_clean")  # only where references exist (eval/references.py)
LABELS = {
    "psnr_pathtrace": "PSNR PathTrace", "psnr_basecolor": "PSNR BaseColor", "psnr_latents": "PSNR Latents",
    "psnr_relight": "PSNR Relight", "tto_minutes": "TTO min", "psnr_pathtrace_clean": "PSNR PathTrace clean",
    "psnr_relight_clean": "PSNR Relight clean",
}  # fmt: skip
ROW_NAMES = {
    "pbr": "PBR baseline (NVDiffRecMC++: PBR head init, PBR TTO)",
    "ours": "Ours (neural material, LMRM init, unc. reg)",
    DEFAULT_VARIANT: "**Ours, the extraction's default** (neural from the PBR solution, consistency term, choices on "
                     "held-out photos, a longer settling phase from the full rate against the debiased loss)",
    "pbr_tuned_0001": "PBR baseline, its head fine-tuned like the default's PBR phase",
    "t2a_uv": "(a) UV", "t2b_uv_lmrm": "(b) UV + LMRM init", "t2c_uv_lmrm_unc": "(c) UV + LMRM init + unc. reg",
    "t2d_triplane": "(d) triplane", "t2e_triplane_lmrm": "(e) triplane + LMRM init",
    "t2f_triplane_lmrm_unc": "(f) triplane + LMRM init + unc. reg (ours)", "t3a_no_tto": "(a) no TTO (LMRM only)",
    "t3b_no_reg": "(b) TTO, no regulariser", "t3c_unc": "(c) TTO, predicted uncertainty (ours)",
    "t3d_oracle": "(d) TTO, oracle uncertainty",
    "ours_pbr_start_no_reg": "neural from the PBR solution (init pbr), no regulariser",
    "ours_pbr_start": "neural from the PBR solution (init pbr) + unc. reg",
    "pbr_start_v2": "neural from the PBR solution, no regulariser, basis v2 (decoder frozen)",
    "pbr_start_v2_decoder": "neural from the PBR solution, no regulariser, basis v2, decoder fine-tuned",
    "pbr_start_1000": "neural from the PBR solution, no regulariser, 1000 neural steps",
    "pbr_start_v2_1000": "neural from the PBR solution, no regulariser, basis v2, 1000 neural steps",
    "pbr_1400": "PBR baseline, 1400 steps",
    "pbr_start_anchor_01": "neural from the PBR solution, anchored to it (lambda 0.1)",
    "pbr_start_anchor_select": "neural from the PBR solution, anchored (lambda 0.1) or not, chosen on held-out photos",
    "pbr_start_anchor_1": "neural from the PBR solution, anchored to it (lambda 1)",
    "pbr_start_anchor_01_1000": "neural from the PBR solution, anchored (lambda 0.1), 1000 neural steps",
    "pbr_start_consistent_01": "neural from the PBR solution, points that start alike change alike (0.1)",
    "pbr_start_consistent_1": "neural from the PBR solution, points that start alike change alike (1)",
    "pbr_start_alike_01": "neural from the PBR solution, points that start alike end alike (0.1)",
    "pbr_start_alike_1": "neural from the PBR solution, points that start alike end alike (1)",
    "pbr_start_alike_1_s01": "the same, sigma 0.1",
    "pbr_start_alike_latent_1": "the same for the latent, the base colour changes alike",
    "pbr_start_alike_rho_1": "the same for the base colour, the latent changes alike",
    "pbr_start_anchor_01_bsdf": "neural from the PBR solution refined in BSDF space, anchored (lambda 0.1)",
    "pbr_start_anchor_01_bsdf_v2": "the same in basis v2",
    "pbr_start_anchor_01_v3": "neural from the PBR solution, anchored (lambda 0.1), basis v3",
    "pbr_start_anchor_01_bsdf_v3": "neural from the PBR solution refined in BSDF space, anchored, basis v3",
    "pbr_start_anchor_01_v4": "neural from the PBR solution, anchored (lambda 0.1), basis v4",
    "pbr_start_v4": "neural from the PBR solution, no anchor, basis v4",
    "pbr_start_bsdf_lr05": "neural from the PBR solution refined in BSDF space, anchored, neural lr x 1/4",
    "pbr_start_bsdf_lr02": "neural from the PBR solution refined in BSDF space, anchored, neural lr x 1/10",
    "pbr_avg": "PBR baseline, mean iterate of the last half",
    "pbr_start_anchor_01_avg": "neural from the PBR solution, anchored (lambda 0.1), mean iterate of each phase's tail",
    "pbr_decorrelated": "PBR baseline, decorrelated photometric loss",
    "pbr_start_anchor_01_decorrelated": "neural from the PBR solution, anchored (0.1), decorrelated photometric loss",
    "pbr_spp32": "PBR baseline, 256 pixels x 32 spp per step",
    "pbr_start_anchor_01_spp32": "neural from the PBR solution, anchored (0.1), 256 pixels x 32 spp per step",
    "pbr_lin_decorrelated": "PBR baseline, decorrelated photometric loss in linear radiance",
    "pbr_start_anchor_01_lin_decorrelated": "neural from the PBR solution, anchored (0.1), decorrelated in linear",
    "default_lmrm_start": "the default, its neural start blended with the LMRM's prediction by their precisions",
    "default_lmrm_start_anchor": "the same, anchored (0.1) where the LMRM made the start",
    "default_lmrm_start_anchor_2": "the same, anchored (2) where the LMRM made the start",
    "default_lmrm_start_full": "the default, its neural start nearly all the LMRM's prediction, anchored (0.1) to it",
    "default_choose_lmrm_start": "the default, choosing on held-out photos between its start and the LMRM's",
    "default_fit_lr02_500": "the default, its start fitted at rate 0.2 in 500 steps (a third)",
    "default_fit_lr02": "the default, its start fitted at rate 0.2 (four times the default's)",
    TRUTH: "reference: the ground-truth material, same scoring (Monte Carlo noise ceiling)",
}  # fmt: skip
TABLE_METRICS = {  # the clean columns show only when some result has them (pages of older runs stay as they were)
    "table1": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_relight", "psnr_relight_clean",
               "tto_minutes"),
    "table2": ("psnr_basecolor", "psnr_latents", "psnr_pathtrace", "psnr_pathtrace_clean", "psnr_relight",
               "psnr_relight_clean"),
    "table3": ("psnr_basecolor", "psnr_latents", "psnr_pathtrace", "psnr_pathtrace_clean", "psnr_relight",
               "psnr_relight_clean"),
    "default": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
                "psnr_relight_clean", "tto_minutes"),
    "starts": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
               "psnr_relight_clean", "tto_minutes"),
    # Latents are left out: another basis's latents are not comparable with the ground truth's
    "basis": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_relight", "psnr_relight_clean",
              "tto_minutes"),
    "longer": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_relight", "psnr_relight_clean",
               "tto_minutes"),
    "start_anchor": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
                     "psnr_relight_clean", "tto_minutes"),
    "bsdf_start": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_relight", "psnr_relight_clean",
                   "tto_minutes"),
    "averaging": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_relight", "psnr_relight_clean",
                  "tto_minutes"),
    "spp32": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
              "psnr_relight_clean", "tto_minutes"),
    "consistency": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
                    "psnr_relight_clean", "tto_minutes"),
    "decorrelated": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
                     "psnr_relight_clean", "tto_minutes"),
    "lmrm_start": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
                   "psnr_relight_clean", "tto_minutes"),
    "lmrm_start_full": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
                        "psnr_relight_clean", "tto_minutes"),
    "choose_lmrm_start": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents",
                          "psnr_relight", "psnr_relight_clean", "tto_minutes"),
    "start_fit": ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_basecolor", "psnr_latents", "psnr_relight",
                  "psnr_relight_clean", "tto_minutes"),
}
TABLE_TITLES = {
    "table1": "Table 1: PBR baseline vs neural material",
    "table2": "Table 2: design ablation (UV / triplane x LMRM init x uncertainty regulariser)",
    "table3": "Table 3: TTO regularisation",
    "default": "The extraction's default against the PBR baseline (issue 14)",
    "starts": "Where the neural TTO starts (issue 14): LMRM or the PBR solution",
    "basis": "The neural basis (issue 14): default (v1) or v2, from the PBR solution",
    "longer": "Longer TTO (issue 14): neural from the PBR solution vs PBR at equal steps",
    "start_anchor": "Anchored to the PBR start (issue 14): relighting",
    "bsdf_start": "The PBR start refined in BSDF space, and the neural phase's step size (issue 14)",
    "averaging": "Iterate averaging: the mean of the last half of the steps as the result (issue 14)",
    "spp32": "Samples per pixel in TTO: 256 pixels x 32 spp (the photos' own count) against 1024 x 8 (issue 14)",
    "decorrelated": "The photometric loss without the render's variance: independent sample errors (issue 14)",
    "consistency": "Points that start alike change alike: the consistency term instead of the anchor (issue 14)",
    "lmrm_start": "The default's neural start blended with the LMRM's prediction by their precisions (issue 14)",
    "lmrm_start_full": "The default's neural start taken from the LMRM and anchored to it, against PBR (issue 14)",
    "choose_lmrm_start": "The default choosing between its start and the LMRM's on held-out photos (issue 14)",
    "start_fit": "The default with its start's fit at four times the learning rate (issue 14)",
}  # fmt: skip
FIGURE_VARIANTS = ("ours", "pbr")  # the figure grid's columns; the default's join them where it was run
FIGURE_OPTIONAL = (DEFAULT_VARIANT, "t3a_no_tto")


@dataclass
class EvalConfig:
    """`neumatex eval`: the paper's tables (PBR baseline vs ours, the design ablation, TTO regularisation) plus
    relighting PSNR and minutes per object on a synthetic benchmark split; resumable; writes docs/results.md."""

    data: str = option("data/benchmark-test", "benchmark split (a `neumatex synth --split test` folder)",
                       positional=True)
    out: str = option("runs/eval", "work folder and per-(object, variant) results; rerun the command to resume")
    objects: str = option("all", "'all', 'first:N', 'every:K' (objects 0, K, 2K, ...) or comma-separated ids")
    tables: str = option("table1,table2,table3,default", "comma-separated subset of " + ", ".join(TABLES))
    preset: Literal["cpu", "gpu", "tiny"] = option("cpu", "extraction preset (TTO schedule, sample counts)")
    steps: int = option(0, "TTO steps (0: the preset's)")
    render_views: int = option(17, "orbital views scored for PSNR PathTrace (0..N-1; 17: all)")
    relight_views: str = option("0,4,8,12,16", "frames of each held-out lighting scored for PSNR Relight ('': none)")
    clean_spp_half: int = option(32, "samples per pixel of each of the two renders per view scored against the "
                                     "objects' references (`neumatex references`; 0: no clean PSNR)")
    workers: int = option(1, "processes (objects run in parallel; each uses --threads torch threads)")
    threads: int = option(1, "torch CPU threads per process")
    device: Literal["auto", "cpu", "cuda"] = option("auto", "torch device")
    lmrm_weights: str = option("", "an LMRM .safetensors (its .json beside it) instead of the shipped one")
    lmrm_readout: str = option("", "an LMRM .safetensors, or 'shipped', whose decoders read the LMRM's prediction "
                                   "(restated per object; '': the LMRM's own)")
    doc: str = option("docs/results.md", "the results page to write ('': none); figures go beside it")
    figures: int = option(4, "objects shown in the figure grid")
    record: str = option("bench/results/eval.jsonl", "where a JSON line with the headline numbers of the written "
                         "page is appended ('': none)")
    allow_incomplete: bool = option(False, "write the page from the finished pairs even if some are missing")
    report_only: bool = option(False, "run nothing: write the page from the results stored so far (of a stopped or "
                                      "still running evaluation)")
    progress: bool = option(True, "show a progress bar")


def select_objects(data: Path, spec: str) -> list[str]:
    """Object ids of the split `data` chosen by `spec` (see EvalConfig.objects), in index order."""
    ids = sorted(p.name for p in data.iterdir() if (p / "meta.json").is_file()) if data.is_dir() else []
    manifest = data / "manifest.json"
    if manifest.is_file():
        listed = [o["id"] for o in json.loads(manifest.read_text())["objects"]]
        ids = [i for i in listed if (data / i / "meta.json").is_file()]
    if not ids:
        raise ValueError(f"{data}: no finished synthetic objects (run `neumatex synth --split test` first)")
    if spec == "all":
        return ids
    kind, _, arg = spec.partition(":")
    if kind == "first" and arg.isdigit():
        return ids[: int(arg)]
    if kind == "every" and arg.isdigit() and int(arg) > 0:
        return ids[:: int(arg)]
    chosen = [s.strip() for s in spec.split(",") if s.strip()]
    missing = [c for c in chosen if c not in ids]
    if missing:
        raise ValueError(f"{data}: no finished objects {missing} (objects: {ids[0]} .. {ids[-1]})")
    return chosen


def distinct_variants(tables: list[str]) -> dict[str, str]:
    """variant name -> the name of the variant that is run for it (identical settings run once)."""
    canon: dict[str, str] = {}
    seen: dict[str, str] = {}
    for table in tables:
        if table not in TABLES:
            raise ValueError(f"unknown table {table!r} (expected {', '.join(TABLES)})")
        for name in TABLES[table]:
            key = json.dumps(VARIANTS[name], sort_keys=True)
            canon[name] = seen.setdefault(key, "ours" if VARIANTS[name] == VARIANTS["ours"] else name)
    return canon


def _evaluate_object(data: str, obj: str, out: str, cfg_dict: dict[str, Any], runs: list[str], render_views: int,
                     relight_views: list[int], figure: bool, threads: int, clean_spp_half: int = 32
                     ) -> list[tuple[str, dict[str, float]]]:
    """Worker: every variant of `runs` on one object (skipping stored results); returns the new results."""
    import torch

    from neumatex_core.eval.harness import evaluate_variant
    from neumatex_core.pipeline import ExtractConfig

    torch.set_num_threads(max(1, threads))
    config = ExtractConfig.from_dict(cfg_dict)
    done = []
    for variant in runs:
        target = result_path(out, obj, variant)
        if target.is_file():
            continue
        figure_dir = Path(out) / "figures" / obj / variant if figure and variant in FIGURE_VARIANTS + FIGURE_OPTIONAL \
            else None  # fmt: skip
        metrics = evaluate_variant(Path(data) / obj, Path(out) / "work" / obj, variant, config,
                                   render_views=tuple(range(render_views)), relight_views=tuple(relight_views),
                                   figure_dir=figure_dir, clean_spp_half=clean_spp_half)  # fmt: skip
        target.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(target, {"object": obj, "variant": variant, **metrics})  # a stopped run leaves no half
        done.append((variant, metrics))
    return done


def result_path(out: str | Path, obj: str, run: str) -> Path:
    """The stored result of one (object, run) of the evaluation in `out` (JSON: metric -> value)."""
    return Path(out) / "results" / obj / f"{run}.json"


def _stored_pairs(out: Path, objects: list[str], runs: list[str]) -> int:
    """How many (object, run) results are stored (the progress bar's count)."""
    return sum(result_path(out, o, v).is_file() for o in objects for v in runs)


def finished_objects(out: Path, objects: list[str], runs: list[str] | set[str]) -> list[str]:
    """The objects of `objects` that have a stored result for every run in `runs`."""
    return [o for o in objects if all(result_path(out, o, v).is_file() for v in runs)]


def run_eval(cfg: EvalConfig, progress: Callable[[int, int, str], None] | None = None) -> dict[str, Any]:
    """Run (or resume) the evaluation; returns {'objects', 'finished', 'complete', 'doc'}. See the module docstring."""
    from neumatex_core.pipeline import ExtractConfig

    if cfg.report_only:  # the page describes the stored run: take its settings (eval.json), not this command's
        stored = Path(cfg.out) / "eval.json"
        if not stored.is_file():
            raise ValueError(f"{stored}: no stored evaluation to report on (run `neumatex eval` first)")
        stored_run = json.loads(stored.read_text())
        settings = stored_run["config"]
        keep = {"out": cfg.out, "doc": cfg.doc, "figures": cfg.figures, "report_only": True}
        cfg = EvalConfig(**{**{k: v for k, v in settings.items() if k in EvalConfig.__dataclass_fields__}, **keep})
    data, out = Path(cfg.data), Path(cfg.out)
    # --report-only pages the stored run's objects, so the page can be written again where the split is not on disk
    objects = list(stored_run.get("objects") or []) if cfg.report_only else select_objects(data, cfg.objects)
    if not objects:
        raise ValueError(f"{out / 'eval.json'}: the stored evaluation names no objects (run `neumatex eval` again)")
    tables = [t.strip() for t in cfg.tables.split(",") if t.strip()]
    canon = distinct_variants(tables)
    runs = list(dict.fromkeys(canon.values())) + [TRUTH]
    relight = [int(v) for v in cfg.relight_views.split(",") if v.strip()]
    config = ExtractConfig.preset(cfg.preset, device=cfg.device, lmrm_weights=cfg.lmrm_weights,
                                 lmrm_readout=cfg.lmrm_readout)
    # Every variant sets its own field, init, reg and material (eval/variants.py); the base keeps the paper's ("ours")
    # whatever the extraction's defaults, so stored results stay comparable when those change.
    config = replace(config, init="lmrm", tto=replace(config.tto, reg="uncertainty"))
    if cfg.steps:
        config = replace(config, tto=replace(config.tto, steps=cfg.steps))
    out.mkdir(parents=True, exist_ok=True)
    if not cfg.report_only:
        (out / "eval.json").write_text(json.dumps({"config": cfg.__dict__, "extract": config.to_dict(),
                                                   "objects": objects, "runs": runs,
                                                   "object_info": object_info(data, objects)}, indent=1))  # fmt: skip
    figure_objects = set(objects[:: max(1, len(objects) // max(1, cfg.figures))][: cfg.figures])
    total = len(objects) * len(runs)
    finished = _stored_pairs(out, objects, runs)
    if progress and not cfg.report_only:
        progress(finished, total, "")
    jobs = [(cfg.data, o, cfg.out, config.to_dict(), runs, cfg.render_views, relight, o in figure_objects,
             cfg.threads, cfg.clean_spp_half) for o in objects] if not cfg.report_only else []  # fmt: skip
    if cfg.workers <= 1:
        for job in jobs:
            for variant, _ in _evaluate_object(*job):
                finished += 1
                if progress:
                    progress(finished, total, f"{job[1]}/{variant}")
    else:
        with ProcessPoolExecutor(cfg.workers, mp_context=get_context("spawn")) as pool:
            pending = {pool.submit(_evaluate_object, *job) for job in jobs}
            while pending:
                # Poll the stored results so the bar moves per finished variant, not per object.
                done, pending = wait(pending, timeout=10, return_when=FIRST_COMPLETED)
                for fut in done:
                    fut.result()  # a worker's exception stops the run here (finished pairs stay stored)
                now = _stored_pairs(out, objects, runs)
                if progress and now != finished:
                    progress(now, total, "")
                finished = now
    finished_objs = finished_objects(out, objects, runs)
    complete = len(finished_objs) == len(objects)
    doc = None
    if cfg.doc and (complete or cfg.allow_incomplete or cfg.report_only):
        doc = write_results(cfg, objects, tables, canon, Path(cfg.doc))
        if cfg.record:
            append_record(cfg, objects, canon, Path(cfg.record))
    return {"objects": len(objects), "finished": len(finished_objs), "complete": complete, "doc": doc}


# -- the results page -------------------------------------------------------------------------------------------
Results = dict[str, dict[str, dict[str, float]]]  # variant -> metric -> object -> value


def load_results(out: Path, objects: list[str], canon: dict[str, str]) -> Results:
    """variant -> metric -> {object: value} over the objects that have a (finite) result."""
    table: Results = {}
    for name, run in {**canon, TRUTH: TRUTH}.items():
        rows: dict[str, dict[str, float]] = {m: {} for m in METRICS}
        for obj in objects:
            f = result_path(out, obj, run)
            if f.is_file():
                rec = json.loads(f.read_text())
                for m in METRICS:
                    if m in rec and rec[m] is not None and math.isfinite(rec[m]):
                        rows[m][obj] = float(rec[m])
        table[name] = rows
    return table


def _fmt(values: dict[str, float]) -> str:
    if not values:
        return "-"
    arr = np.asarray(list(values.values()))
    return f"{arr.mean():.2f} ± {arr.std():.2f}"


def paired_values(res: Results, a: str, b: str, metric: str, metric_b: str = "") -> dict[str, float]:
    """object -> `metric` of `a` minus `metric_b` (default `metric`) of `b`, over the objects both have (dB)."""
    va, vb = res.get(a, {}).get(metric, {}), res.get(b, {}).get(metric_b or metric, {})
    return {o: va[o] - vb[o] for o in va if o in vb}


def paired_difference(res: Results, a: str, b: str, metric: str, metric_b: str = "") -> tuple[float, float, int]:
    """Mean of `a - b` (`metric` of `a` minus `metric_b`, default `metric`, of `b`) over the objects both have, its
    standard error and the number of objects.

    Paired because the spread between objects (about 2 dB: some objects are harder) is much larger than the
    spread of one variant's advantage over another; the standard error is std(d, ddof=1) / sqrt(n)."""
    d = np.asarray(list(paired_values(res, a, b, metric, metric_b).values()))
    if d.size == 0:
        return math.nan, math.nan, 0
    se = float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else math.nan
    return float(d.mean()), se, int(d.size)


def bias_only_psnr(res: Results, variant: str) -> tuple[float, int]:
    """Median over objects of PathTrace PSNR with the Monte Carlo noise taken out, and the number of objects.

    The photo and the render carry independent noise, so E[MSE] = bias^2 + noise, and the ground-truth row's MSE
    (same spp, seeds and views) estimates the noise: bias^2 ~ MSE(variant) - MSE(reference), MSE = 10^(-PSNR/10).
    Approximate: a PSNR here is a mean over views, so its MSE is a geometric mean. The median, because a variant
    within the noise of the reference has a near-zero difference and an unbounded PSNR (clamped at 60 dB)."""
    va, vt = res.get(variant, {}).get("psnr_pathtrace", {}), res.get(TRUTH, {}).get("psnr_pathtrace", {})
    vals = [-10 * math.log10(max(10 ** (-va[o] / 10) - 10 ** (-vt[o] / 10), 1e-6)) for o in va if o in vt]
    return (float(np.median(vals)), len(vals)) if vals else (math.nan, 0)


def has_metric(res: Results, metric: str) -> bool:
    """Whether any variant has a value of `metric` (the clean metrics exist only for objects with references)."""
    return any(rows.get(metric) for rows in res.values())


def _with_clean(res: Results, metrics: tuple[str, ...]) -> tuple[str, ...]:
    """`metrics` plus the clean twin of PathTrace / Relight among them, where results have it."""
    extra = tuple(f"{m}_clean" for m in metrics if f"{m}_clean" in CLEAN_METRICS and has_metric(res, f"{m}_clean"))
    return metrics + extra


def _fmt_diff(label: str, diff: tuple[float, float, int]) -> str:
    mean, se, n = diff
    resolved = "" if math.isnan(se) or abs(mean) > 2 * se else ", not resolved"
    return f"{label} {mean:+.2f} ± {se:.2f} dB (paired, n={n}{resolved})"


def orderings(res: Results) -> list[tuple[str, bool | None, str]]:
    """The paper's claims, each as (claim, holds (None: not measured), the numbers).

    Each claim is judged on the mean paired difference over the objects that have both variants; the detail gives
    its standard error and says "not resolved" where the difference is within 2 standard errors of zero."""
    checks: list[tuple[str, bool | None, str]] = []

    def add(claim: str, ok: bool | None, detail: str) -> None:
        checks.append((claim, ok, detail))

    d = paired_difference(res, "ours", "pbr", "psnr_pathtrace")
    headroom = paired_difference(res, TRUTH, "pbr", "psnr_pathtrace")  # the most any material could gain
    add("neural material beats the PBR baseline on PathTrace by a wide margin (>= 1 dB)",
        None if math.isnan(d[0]) else d[0] >= 1.0,
        _fmt_diff("ours - PBR", d) + "; headroom: " + _fmt_diff("ground-truth material - PBR", headroom)
        + f"; with the noise taken out (median, approx.): ours {bias_only_psnr(res, 'ours')[0]:.1f}, "
        f"PBR {bias_only_psnr(res, 'pbr')[0]:.1f} dB" + _clean_detail(res))
    for rnd, lmrm, label in (("t2a_uv", "t2b_uv_lmrm", "UV"), ("t2d_triplane", "t2e_triplane_lmrm", "triplane")):
        diffs = {m: paired_difference(res, lmrm, rnd, m)
                 for m in _with_clean(res, ("psnr_basecolor", "psnr_latents", "psnr_pathtrace"))}
        ok = None if any(math.isnan(v[0]) for v in diffs.values()) else all(v[0] > 0 for v in diffs.values())
        add(f"LMRM initialisation beats random initialisation on every metric ({label})", ok,
            "; ".join(_fmt_diff(LABELS[m], v) for m, v in diffs.items()))
    for unc, none, label in (("t3c_unc", "t3b_no_reg", "triplane"), ("t2c_uv_lmrm_unc", "t2b_uv_lmrm", "UV")):
        diffs = {m: paired_difference(res, unc, none, m) for m in ("psnr_basecolor", "psnr_latents")}
        ok = None if any(math.isnan(v[0]) for v in diffs.values()) else all(v[0] > 0 for v in diffs.values())
        add(f"uncertainty regularisation improves BaseColor and Latents over no regulariser ({label})", ok,
            "; ".join(_fmt_diff(LABELS[m], v) for m, v in diffs.items()))
    diffs = {m: paired_difference(res, "t3d_oracle", "t3c_unc", m)
             for m in _with_clean(res, ("psnr_basecolor", "psnr_latents", "psnr_pathtrace"))}
    ok = None if any(math.isnan(v[0]) for v in diffs.values()) else all(abs(v[0]) <= 1.0 for v in diffs.values())
    add("predicted uncertainty lands within 1 dB of the oracle", ok,
        "; ".join(_fmt_diff(f"{LABELS[m]} oracle - ours", v) for m, v in diffs.items()))
    gap, truth_gap = (paired_difference(res, v, v, "psnr_pathtrace", "psnr_relight") for v in ("ours", TRUTH))
    clean_gap = ""
    if has_metric(res, "psnr_relight_clean"):
        clean_gap = "; clean: " + _fmt_diff("ours PathTrace - Relight", paired_difference(
            res, "ours", "ours", "psnr_pathtrace_clean", "psnr_relight_clean"))
    add("(not in the paper; the issue's) relighting within 2 dB of PathTrace under the capture's own lighting",
        None if math.isnan(gap[0]) else gap[0] <= 2.0,
        _fmt_diff("ours PathTrace - Relight", gap) + "; " + _fmt_diff("the ground-truth material's", truth_gap)
        + clean_gap)
    return checks


def _clean_detail(res: Results) -> str:
    """The PathTrace claim's clean numbers (against the references, noise subtracted), '' without them."""
    pc = "psnr_pathtrace_clean"
    if not has_metric(res, pc):
        return ""
    return ("; clean (against references): " + _fmt_diff("ours - PBR", paired_difference(res, "ours", "pbr", pc))
            + "; " + _fmt_diff("ground-truth material - PBR", paired_difference(res, TRUTH, "pbr", pc)))


# Issue 14's targets for the extraction's default on the benchmark, on the clean scoring: (label, kind, metric,
# threshold dB). "above": the default - PBR resolved above the threshold (mean - 2 standard errors >= threshold);
# "within": the ground truth's lead over the default at most the threshold; "level": the default's mean over objects
# at least the threshold.
TARGETS: tuple[tuple[str, Literal["above", "within", "level"], str, float], ...] = (
    ("PathTrace clean: the default - PBR >= +3 dB, resolved", "above", "psnr_pathtrace_clean", 3.0),
    ("PathTrace clean: the default within 1.5 dB of the ground-truth material", "within", "psnr_pathtrace_clean", 1.5),
    ("Relight clean (held-out lighting): the default - PBR >= +2 dB, resolved", "above", "psnr_relight_clean", 2.0),
    ("BaseColor: the default >= 22 dB", "level", "psnr_basecolor", 22.0),
    ("Latents: the default >= 20 dB", "level", "psnr_latents", 20.0),
)


def targets(res: Results) -> list[tuple[str, bool | None, str]]:
    """Issue 14's targets (`TARGETS`), each as (target, met (None: not measured), the numbers)."""
    checks: list[tuple[str, bool | None, str]] = []
    for label, kind, metric, threshold in TARGETS:
        if kind == "level":  # the mean over the objects that have it
            values = list(res.get(DEFAULT_VARIANT, {}).get(metric, {}).values())
            ok = None if not values else float(np.mean(values)) >= threshold
            detail = (f"{np.mean(values):.2f} ± {np.std(values):.2f} dB (mean ± std, n={len(values)})" if values
                      else "no results")  # fmt: skip
        elif kind == "within":
            d = paired_difference(res, TRUTH, DEFAULT_VARIANT, metric)
            ok = None if math.isnan(d[0]) else d[0] <= threshold
            detail = _fmt_diff("ground-truth material - the default", d)
        else:
            d = paired_difference(res, DEFAULT_VARIANT, "pbr", metric)
            ok = None if math.isnan(d[0]) or math.isnan(d[1]) else d[0] - 2 * d[1] >= threshold
            detail = _fmt_diff("the default - PBR", d) + (
                "" if math.isnan(d[1]) else f"; mean - 2 standard errors {d[0] - 2 * d[1]:+.2f} dB")
        checks.append((label, ok, detail))
    return checks


def object_families(data: Path, objects: list[str], known: dict[str, Any] | None = None) -> dict[str, list[str]]:
    """object -> the material families of its regions (from its meta.json, else from `known`: the stored run's
    `object_info`), for the objects that record them."""
    found: dict[str, list[str]] = {}
    for obj in objects:
        meta = data / obj / "meta.json"
        if meta.is_file():
            regions = json.loads(meta.read_text()).get("spec", {}).get("material", {}).get("regions", [])
            families = sorted({r["family"] for r in regions if "family" in r})
        else:
            families = list((known or {}).get(obj, {}).get("families", []))
        if families:
            found[obj] = families
    return found


def reference_spp(data: Path, obj: str) -> int | None:
    """The samples per pixel of each half of the object's references (`neumatex references`), None without them."""
    meta = data / obj / "references" / "meta.json"
    return int(json.loads(meta.read_text())["settings"]["spp_half"]) if meta.is_file() else None


def object_info(data: Path, objects: list[str]) -> dict[str, dict[str, Any]]:
    """What the results page reads from the split beyond the stored results, per object: its material families and
    its references' spp. eval.json keeps it, so `--report-only` writes the same page without the split on disk."""
    families = object_families(data, objects)
    return {o: {"families": families.get(o, []), "reference_spp_half": reference_spp(data, o)} for o in objects}


def stored_object_info(out: Path) -> dict[str, Any]:
    """The stored evaluation's `object_info` ({} when it has none or there is no eval.json)."""
    stored = out / "eval.json"
    return dict(json.loads(stored.read_text()).get("object_info", {})) if stored.is_file() else {}


def family_lines(res: Results, families: dict[str, list[str]], variant: str = "ours", name: str = "ours") -> list[str]:
    """Markdown table: `variant` - PBR (PathTrace, BaseColor) and the headroom, over the objects containing each
    family (`name`: the variant in the column heads).

    An object with two families counts in both rows, so the rows overlap and do not add up."""
    pt, bc, pc = "psnr_pathtrace", "psnr_basecolor", "psnr_pathtrace_clean"
    columns = [(variant, pt), (TRUTH, pt), (variant, bc)] + ([(variant, pc)] if has_metric(res, pc) else [])
    lines = [f"| family | objects | {name} - PBR, PathTrace | ground truth - PBR, PathTrace | {name} - PBR, BaseColor |"
             + (f" {name} - PBR, PathTrace clean |" if len(columns) > 3 else ""), "|---|---|---|---|---|"
             + "---|" * (len(columns) - 3)]
    for family in sorted({f for fs in families.values() for f in fs}):
        keep = {o for o, fs in families.items() if family in fs}
        sub: Results = {v: {m: {o: x for o, x in per.items() if o in keep} for m, per in rows.items()}
                        for v, rows in res.items()}  # fmt: skip
        diffs = [paired_difference(sub, a, "pbr", m) for a, m in columns]
        cells = ["-" if n == 0 else f"{mean:+.2f} ± {se:.2f}" if n > 1 else f"{mean:+.2f}" for mean, se, n in diffs]
        paired = max(diffs[0][2], diffs[-1][2])  # objects with the variant's and PBR's PathTrace (noisy or clean)
        if paired:
            lines.append(f"| {family} | {paired} | " + " | ".join(cells) + " |")
    return lines if len(lines) > 2 else []


def difference_rows(res: Results) -> list[DifferenceRow]:
    """The comparisons behind `orderings`, per object, for the paired-difference chart."""
    bc, lat, pt, pc = "psnr_basecolor", "psnr_latents", "psnr_pathtrace", "psnr_pathtrace_clean"
    spec: list[tuple[str, str, str, str, str, tuple[float, ...]]] = [
        ("ours - PBR, PathTrace", "ours", "pbr", pt, "", (1.0,)),
        ("ground truth - PBR, PathTrace (headroom)", TRUTH, "pbr", pt, "", ()),
        *[(f"LMRM - random init, {label}, {LABELS[m]}", lmrm, rnd, m, "", ())
          for rnd, lmrm, label in (("t2d_triplane", "t2e_triplane_lmrm", "triplane"), ("t2a_uv", "t2b_uv_lmrm", "UV"))
          for m in (bc, lat, pt)],
        *[(f"unc. reg - none, {label}, {LABELS[m]}", unc, none, m, "", ())
          for unc, none, label in (("t3c_unc", "t3b_no_reg", "triplane"), ("t2c_uv_lmrm_unc", "t2b_uv_lmrm", "UV"))
          for m in (bc, lat)],
        *[(f"oracle - ours, {LABELS[m]}", "t3d_oracle", "t3c_unc", m, "", (-1.0, 1.0)) for m in (bc, lat, pt)],
        ("ours: PathTrace - Relight", "ours", "ours", pt, "psnr_relight", (2.0,)),
        ("ground truth: PathTrace - Relight", TRUTH, TRUTH, pt, "psnr_relight", (2.0,)),
        # against the references, noise subtracted (empty, and left out of the chart, without references)
        ("ours - PBR, PathTrace clean", "ours", "pbr", pc, "", (1.0,)),
        ("ground truth - PBR, PathTrace clean (headroom)", TRUTH, "pbr", pc, "", ()),
        *[(f"LMRM - random init, {label}, {LABELS[pc]}", lmrm, rnd, pc, "", ())
          for rnd, lmrm, label in (("t2d_triplane", "t2e_triplane_lmrm", "triplane"), ("t2a_uv", "t2b_uv_lmrm", "UV"))],
        (f"oracle - ours, {LABELS[pc]}", "t3d_oracle", "t3c_unc", pc, "", (-1.0, 1.0)),
        ("ours: PathTrace clean - Relight clean", "ours", "ours", pc, "psnr_relight_clean", (2.0,)),
        # the extraction's default (table "default") and issue 14's thresholds
        ("the default - PBR, PathTrace clean", DEFAULT_VARIANT, "pbr", pc, "", (3.0,)),
        ("the default - PBR, Relight clean", DEFAULT_VARIANT, "pbr", "psnr_relight_clean", "", (2.0,)),
        ("the default - PBR, BaseColor", DEFAULT_VARIANT, "pbr", bc, "", ()),
        ("the default - PBR with its head tuned, PathTrace clean", DEFAULT_VARIANT, "pbr_tuned_0001", pc, "", ()),
    ]  # fmt: skip
    return [DifferenceRow(label, list(paired_values(res, a, b, m, mb).values()), thr)
            for label, a, b, m, mb, thr in spec]


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], capture_output=True, text=True,
                              check=True, cwd=Path(__file__).parent).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


HEADLINE = (("ours", "pbr"), ("ours_pbr_start_no_reg", "pbr"), ("ours_pbr_start", "pbr"), ("t3b_no_reg", "pbr"),
            (TRUTH, "pbr"), (DEFAULT_VARIANT, "pbr"), (DEFAULT_VARIANT, "pbr_tuned_0001"),
            (TRUTH, DEFAULT_VARIANT))  # fmt: skip
HEADLINE_METRICS = ("psnr_pathtrace", "psnr_pathtrace_clean", "psnr_relight", "psnr_relight_clean", "psnr_basecolor",
                    "psnr_latents")  # fmt: skip


def eval_record(cfg: EvalConfig, objects: list[str], canon: dict[str, str]) -> dict[str, Any]:
    """The machine-readable summary of a written page: per variant the mean of each metric over the finished
    objects, and the headline paired differences (mean, standard error, n) of `HEADLINE` on `HEADLINE_METRICS`."""
    finished = finished_objects(Path(cfg.out), objects, set(canon.values()) | {TRUTH})
    res = load_results(Path(cfg.out), finished, canon)
    means = {name: {m: float(np.nanmean(list(v.values()))) for m, v in rows.items() if v}
             for name, rows in res.items()}  # fmt: skip
    diffs = {f"{a} - {b}": {m: paired_difference(res, a, b, m) for m in HEADLINE_METRICS
                            if not math.isnan(paired_difference(res, a, b, m)[0])}
             for a, b in HEADLINE if a in res and b in res}  # fmt: skip
    return {"benchmark": "eval", "timestamp": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "commit": _git_commit(), "command": command_line("neumatex eval", cfg, skip=("progress", "report_only",
                                                                                         "allow_incomplete")),
            "objects": len(finished), "means": means, "paired": diffs}  # fmt: skip


def append_record(cfg: EvalConfig, objects: list[str], canon: dict[str, str], path: Path) -> None:
    """Append `eval_record` as one JSON line to `path` (bench/results/eval.jsonl by default)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        f.write(json.dumps(eval_record(cfg, objects, canon), allow_nan=True) + "\n")


def figure_grid(cfg: EvalConfig, objects: list[str], target: Path) -> bool:
    """One row per figure object: reference photo, ours, PBR baseline renders; true, ours and PBR base colour;
    true and ours latents (channels 0-2); LMRM uncertainty (mean predicted std of the base colour); beside each
    "ours" the extraction's default's picture where every row has it. PNG."""
    import torch

    from neumatex_core.capture import load_capture
    from neumatex_core.capture.tonemap import srgb_oetf_numpy
    from neumatex_core.geometry.gbuffer import render_gbuffer
    from neumatex_core.imageio import read_image, write_image
    from neumatex_core.pipeline import load_prediction
    from neumatex_core.synth.sheets import _tile, sheet

    out, data = Path(cfg.out), Path(cfg.data)
    tiles: list[np.ndarray] = []
    # (an object whose capture is not on disk, e.g. a page written again elsewhere with --report-only, is left out)
    shown = [o for o in objects if all((out / "figures" / o / v / "render.png").is_file() for v in FIGURE_VARIANTS)
             and (data / o / "transforms.json").is_file()]
    # the extraction's default gets its own columns where every shown object has its pictures
    default = bool(shown) and all((out / "figures" / o / DEFAULT_VARIANT / "render.png").is_file() for o in shown)
    extra = [DEFAULT_VARIANT] if default else []
    for obj in shown:
        figs = out / "figures" / obj
        transforms = json.loads((data / obj / "transforms.json").read_text())
        frame = transforms["frames"][0]
        mask = read_image(data / obj / frame["mask_path"])[:, :, 0] > 0.5
        photo = read_image(data / obj / frame["file_path"])[:, :, :3]
        truth_rho = read_image(data / obj / frame["gbuffers"]["basecolor"])[:, :, :3]
        truth_lat = read_image(data / obj / frame["gbuffers"]["latent"])[:, :, :3]
        size = photo.shape[0]

        def white(img: np.ndarray, m: np.ndarray = mask) -> np.ndarray:
            img = img.copy()
            img[~m] = 1.0
            return img

        pred, _ = load_prediction(out / "work" / obj)
        cap = load_capture(data / obj)
        g = render_gbuffer(cap.load_mesh(), cap.frames[0].camera)
        sel = g.mask.reshape(-1)
        std = np.ones(sel.shape[0], dtype=np.float32)
        with torch.no_grad():
            _, _, log_var = pred.gbuffers(g.position.reshape(-1, 3)[sel])
        sigma = torch.exp(0.5 * log_var[:, :3]).mean(-1).numpy()
        std[sel.numpy()] = 1.0 - np.clip(sigma / 0.25, 0, 1)  # dark = uncertain (0.25 std in rho_d is black)
        unc = np.repeat(std.reshape(size, size, 1), 3, axis=2)

        def pictures(kind: str, figs: Path = figs) -> list[tuple[np.ndarray, str]]:
            """ours' (and the default's) `kind`.png of this object"""
            return [(read_image(figs / v / f"{kind}.png")[:, :, :3], "the default" if v == DEFAULT_VARIANT else "ours")
                    for v in ("ours", *extra)]  # fmt: skip

        pics = [
            (white(photo), f"{obj[-3:]} reference"),
            *pictures("render"),
            (read_image(figs / "pbr" / "render.png")[:, :, :3], "PBR baseline"),
            (white(srgb_oetf_numpy(np.clip(truth_rho, 0, 1))), "base colour: truth"),
            *pictures("basecolor"),
            (read_image(figs / "pbr" / "basecolor.png")[:, :, :3], "PBR baseline"),
            (white(np.clip((truth_lat + 1) / 2, 0, 1)), "latents 0-2: truth"),
            *pictures("latent"),
            (unc, "LMRM uncertainty"),
        ]
        tiles += [_tile(p, c, size) for p, c in pics]
    if not shown:
        return False
    write_image(target, sheet(tiles, columns=9 + 3 * len(extra)))
    return True


def write_results(cfg: EvalConfig, objects: list[str], tables: list[str], canon: dict[str, str], doc: Path) -> Path:
    """docs/results.md (and the figure grid beside it) from the stored results; returns the page's path."""
    out = Path(cfg.out)
    # only objects with every variant: rows of a partial page then compare the same objects
    finished = finished_objects(out, objects, set(canon.values()) | {TRUTH})
    res = load_results(out, finished, canon)
    known = stored_object_info(out)  # what the split would tell, kept in eval.json (object_info)
    n_done = {name: len(set().union(*rows.values())) for name, rows in res.items()}  # objects with any metric
    command = command_line("neumatex eval", cfg, skip=("progress", "report_only", "allow_incomplete"))
    subjects = [s for s, shown in (("the paper's tables", any(t in PAPER_TABLES for t in tables)),
                                   ("the extraction's default", "default" in tables),
                                   ("issue 14's studies", any(t not in (*PAPER_TABLES, "default") for t in tables)))
                if shown]  # fmt: skip
    lines = [
        f"# Results: {' and '.join([', '.join(subjects[:-1]), subjects[-1]] if len(subjects) > 2 else subjects)} "
        "on our benchmark",
        "",
        f"Written by `neumatex eval` ({time.strftime('%Y-%m-%d')}, commit `{_git_commit()}`, "
        f"{os.cpu_count()} CPU threads visible, preset `{cfg.preset}`"
        + (f", {cfg.steps} TTO steps" if cfg.steps else "") + "). Command:",
        "",
        "```bash",
        command,
        "```",
        "",
        f"Objects: {len(finished)} of the benchmark split `{cfg.data}` ({', '.join(o[-3:] for o in finished)})"
        + (f", finished out of the {len(objects)} selected" if len(finished) < len(objects) else "") + "; "
        "numbers are mean ± std over objects. PSNR PathTrace: tonemapped renders of the "
        f"{cfg.render_views} orbital views vs the object's photos at the photos' sample count (covered pixels); "
        "BaseColor / Latents: the G-buffers of the 23 preset views vs ground truth; Relight: frames "
        f"{cfg.relight_views} under the two held-out lightings vs their photos (16 spp references, so Monte Carlo "
        "noise caps it); TTO min: wall-clock minutes of the TTO alone on this machine."
        + _clean_description(cfg, res, finished, known)
        + _sources_description(out, finished, canon),
        "",
    ]
    for table in tables:
        metrics = tuple(m for m in TABLE_METRICS[table] if m not in CLEAN_METRICS or has_metric(res, m))
        title = TABLE_TITLES[table]
        lines += [f"## {title}", "", "| variant | n | " + " | ".join(LABELS[m] for m in metrics) + " |",
                  "|---|---|" + "---|" * len(metrics)]
        for name in [*TABLES[table], TRUTH]:
            rows = res[name]
            lines.append(f"| {ROW_NAMES[name]} | {n_done[name]} | "
                         + " | ".join(_fmt(rows[m]) for m in metrics) + " |")
        lines.append("")
    families = object_families(Path(cfg.data), finished, known)
    by_family = family_lines(res, families) if "table1" in tables else []
    if by_family:
        lines += ["### Table 1 by material family", "",
                  "Paired differences (mean ± standard error, dB) over the objects with a region of that family; an "
                  "object with two families counts in both rows.", "", *by_family, ""]
    default_family = family_lines(res, families, DEFAULT_VARIANT, "the default") if "default" in tables else []
    if default_family:
        lines += ["### The extraction's default by material family", "",
                  "The same paired differences for the extraction's default.", "", *default_family, ""]
    if any(t in PAPER_TABLES for t in tables):
        lines += ["## Do the paper's orderings hold?", ""]
        for claim, ok, detail in orderings(res):
            verdict = "not measured" if ok is None else ("holds" if ok else "**does not hold**")
            lines.append(f"- {claim}: {verdict} ({detail})")
        lines.append("")
    if "default" in tables:
        lines += ["## Issue 14's targets (the extraction's default)", ""]
        for target, ok, detail in targets(res):
            verdict = "not measured" if ok is None else ("met" if ok else "**not met**")
            lines.append(f"- {target}: {verdict} ({detail})")
        lines.append("")
    chart, diff_rows = doc.parent / "results" / "differences.png", [r for r in difference_rows(res) if r.values]
    if diff_rows:
        difference_chart(diff_rows, chart)
        lines += ["Each comparison per object (PSNR of the first variant minus the second, dB) with its mean and 2 "
                  "standard errors; orange ticks are the claims' thresholds:", "",
                  f"![paired differences]({os.path.relpath(chart, doc.parent)})", ""]
    notes = doc.with_name(doc.stem + "-discussion.md")
    if notes.is_file():  # the hand-written reading of these numbers, kept beside the page and included in it
        lines += [notes.read_text().rstrip(), ""]
    grid = doc.parent / "results" / "grid.png"
    if figure_grid(cfg, objects, grid):
        rel = os.path.relpath(grid, doc.parent)
        lines += ["## Figures", "", "Per row, one object (preset view 0): reference photo, ours (and the default, "
                  "where it was run), PBR baseline; base colour truth / ours / PBR; latents 0-2 truth / ours; the "
                  "LMRM's uncertainty (dark: uncertain).",
                  "", f"![results grid]({rel})", ""]
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text("\n".join(lines))
    return doc


def _sources_description(out: Path, objects: list[str], canon: dict[str, str]) -> str:
    """The page's sentence on stored results that another command measured with the same harness (their "source":
    e.g. bench/variants_clean.py's rows, which keep the clean metrics only); '' when there are none."""
    found: dict[str, list[str]] = {}
    for name, run in canon.items():
        for obj in objects:
            f = result_path(out, obj, run)
            if f.is_file() and (source := json.loads(f.read_text()).get("source")):
                found.setdefault(name, []).append(str(source))
    return "".join(f" The results of {ROW_NAMES[name]} on {len(sources)} objects were measured by another command "
                   f"with the same harness ({sorted(sources)[0].split()[0]}; columns it does not record are '-')."
                   for name, sources in found.items())


def _clean_description(cfg: EvalConfig, res: Results, objects: list[str], known: dict[str, Any]) -> str:
    """The page's sentence on the clean columns ('' when no result has them); the references' spp from the split,
    else from `known` (the stored run's `object_info`)."""
    if not any(has_metric(res, m) for m in CLEAN_METRICS):
        return ""
    found = [reference_spp(Path(cfg.data), o) or known.get(o, {}).get("reference_spp_half") for o in objects]
    spp = sorted({int(n) for n in found if n})
    return (" PSNR PathTrace clean / Relight clean: the same views rendered twice with independent seeds "
            f"({cfg.clean_spp_half} spp each) against the ground-truth material rendered twice "
            f"({'/'.join(str(s) for s in spp) or '?'} spp each; `neumatex references`), with the Monte Carlo noise of "
            "both sides subtracted (`eval/references.py`, `clean_psnr`; pooled over the covered pixels of the scored "
            "views; the ground-truth row measures what is left of the noise, 100 dB where nothing is); objects "
            "without references: -.")


def run_eval_command(cfg: EvalConfig) -> int:
    """CLI entry: progress bar, then the page's path."""
    from tqdm import tqdm

    bar: Any = None

    def progress(done: int, total: int, last: str) -> None:
        nonlocal bar
        if not cfg.progress:
            return
        if bar is None:
            bar = tqdm(total=total, initial=done, unit="run", desc="eval")
        else:
            bar.update(done - bar.n)
            bar.set_postfix_str(last)

    result = run_eval(cfg, progress)
    if bar is not None:
        bar.close()
    if result["doc"]:
        print(f"wrote {result['doc']} ({result['finished']} of {result['objects']} objects finished)")
    elif not result["complete"]:
        print("evaluation incomplete; rerun to resume (or --allow-incomplete to write the page now)")
    return 0
