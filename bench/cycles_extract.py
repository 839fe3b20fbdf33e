"""Extraction on captures rendered by Blender Cycles: the default neural recipe against the PBR baseline.

    make cycles-env
    neumatex cycles-capture --mesh teapot.obj --envmap courtyard.exr --envmap-yaw 30 --preset coat \\
        --resolution 64 --spp 256 --random 8 --out runs/cycles/coat          # and sheen, metal, diffuse
    NEUMATEX_SHARED=../shared .venv/bin/python bench/cycles_extract.py runs/cycles/coat runs/cycles/sheen
    NEUMATEX_SHARED=../shared bench/cycles_matrix.sh     # coat, sheen, metal, diffuse on four shared meshes

Per capture (23 preset views, 8 held-out photos at random poses in photos/, held-out maps in relight/<j>/; Cycles,
256 spp): the pipeline's validate / prepare_views / lmrm stages, then two TTOs on the preset views through
`tto.solve`, as `neumatex eval` runs them: the PBR baseline (material "pbr", 400 steps from the LMRM's PBR head) and
the extraction's default (`ExtractConfig.preset("cpu")`: PBR TTO, then the neural TTO from its solution, with the
consistency term since 2026-11-27 and anchored to it before; since the same day its variation "choose": one uniform
material or textured, chosen on 4 held-out input views). Each is rendered at --spp with our path tracer and
scored (PSNR after the capture's tonemap, covered pixels) on the held-out photos (capture lighting, unseen poses)
and on every relit view (unseen lighting). Prints neural - PBR per capture, then per Principled preset the mean over
captures with its standard error, and writes a JSON line to bench/results/cycles_extract.jsonl. The reference is
Cycles itself at 256 spp, so both rows carry the same Cycles noise (it adds the same MSE to both, so the dB
difference understates the clean one); the difference is the figure. Each capture's scores are kept in
<work>/<capture name>/scores.json, so an interrupted run resumes (`--again` recomputes them). `--variants
pbr,neural,ours_pbr_start_no_reg` adds a `neumatex eval` variant (here the neural TTO from the PBR start without a
regulariser; only the missing variants are run), each compared with the PBR baseline. `--lmrm-weights W
--lmrm-readout shipped --work DIR` has another LMRM predict (each row records it; a work folder holds one LMRM's
stages), writes its line to bench/results/cycles_extract_lmrm.jsonl and pairs each variant with its latest scores
under the shipped LMRM (the extraction's default as bench/basis_choice.py reads it).

Clean scores: when a twin capture <capture>.seed1 exists (the same views rendered by Cycles with another --seed and
the same --pose-seed, as bench/cycles_matrix.sh writes), each render is scored noise-corrected
(`eval.references.clean_psnr`, display average, as `neumatex eval` scores: Cycles' two renders at the capture's
spp, ours rendered twice at --clean-spp with independent seeds), pooled over the folder's views: `photos_clean_db`
and `relit_clean_db`, in place of the raw scores. Both Cycles' and our noise are taken out, so these differences
are not compressed by either.

On a machine without the kept scores (a fresh clone), `--stored` takes each capture's scores from its latest row in
bench/results/cycles_extract.jsonl written on a machine of the same CPU model, so that only the variants it lacks
are run: a new candidate is paired with the stored baseline and default. They are not bit for bit what a rerun
gives: the Cycles renders and our code move the scores by a few thousandths of a dB (docs/design-notes.md item 62),
and where that flips one of the TTO's discrete choices (the basis, uniform or textured; each row's `selection`)
the capture's score jumps: teapot-diffuse's stored default chose the default basis and scored 49.42 / 45.17 dB
(held-out photos / relit), rerun on 2026-12-03 it chose basis v4 and 40.51 / 41.14 (item 66). Compare the
selections of the pair, and rerun without `--stored` (another --work) where they differ.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Literal

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from common import (  # noqa: E402
    RESULTS_DIR,
    argument_parser,
    cpu_model,
    mean_se,
    prepared_capture,
    write_result,
)

from neumatex_core.atomic import write_json_atomic  # noqa: E402
from neumatex_core.capture import load_capture  # noqa: E402
from neumatex_core.eval.harness import _render_psnr  # noqa: E402
from neumatex_core.eval.references import CLEAN_TAG, clean_psnr, coverage_mask, half_seed, harness_envmap  # noqa: E402
from neumatex_core.eval.variants import DEFAULT_VARIANT, variant_config  # noqa: E402
from neumatex_core.eval.variants import VARIANTS as EVAL_VARIANTS  # noqa: E402
from neumatex_core.imageio import read_image  # noqa: E402
from neumatex_core.materials.field import MaterialField  # noqa: E402
from neumatex_core.materials.neural_basis import load_basis  # noqa: E402
from neumatex_core.pipeline import ExtractConfig  # noqa: E402
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig  # noqa: E402
from neumatex_core.render.scene import Scene  # noqa: E402
from neumatex_core.tto.config import TTOConfig  # noqa: E402
from neumatex_core.tto.pbr_start import solve  # noqa: E402

SHIPPED = "the shipped LMRM"  # by_preset's name for a variant's stored scores under the shipped LMRM
TWIN_SUFFIX = ".seed1"  # bench/cycles_matrix.sh's second capture of the same views
# How each side's two halves are averaged in the clean scores: after the tonemap, the robust one with heavy-tailed
# highlights (docs/design-notes.md, note 48). Kept scores made another way are recomputed.
CLEAN_AVERAGE: Literal["radiance", "display"] = "display"


def clean_render_psnr(folder: Path, twin: Path, field: MaterialField, spp: int, bounces: int, mesh: Any,
                      lighting: int) -> float:
    """Noise-corrected PSNR (dB) of `field` on every frame of the Cycles capture `folder`, pooled over its covered
    pixels: ours rendered twice at `spp` (seeds half_seed(0, CLEAN_TAG, lighting, view, 0 | 1)) against the two
    Cycles renders of each view (`folder` and its `twin`, linear EXR), `clean_psnr` averaging each side's halves
    as CLEAN_AVERAGE says."""
    cap = load_capture(folder)
    frames = json.loads((folder / "transforms.json").read_text())["frames"]
    twin_frames = json.loads((twin / "transforms.json").read_text())["frames"]
    scene = Scene(mesh, harness_envmap(cap), field)
    tracer = PathTracer(PathTracerConfig(spp=spp, max_bounces=bounces))
    a: list[list[np.ndarray]] = [[], []]
    r1, r2, masks = [], [], []
    for v, (entry, twin_entry) in enumerate(zip(frames, twin_frames, strict=True)):
        cam = cap.frames[v].camera
        with torch.no_grad():
            for h in (0, 1):
                a[h].append(tracer.render(scene, cam, seed=half_seed(0, CLEAN_TAG, lighting, v, h)).cpu().numpy())
        r1.append(read_image(folder / entry["linear_path"])[:, :, :3])
        r2.append(read_image(twin / twin_entry["linear_path"])[:, :, :3])
        masks.append(coverage_mask(cap, mesh, v))
    score = clean_psnr(np.stack(a[0]), np.stack(a[1]), np.stack(r1), np.stack(r2), np.stack(masks), cap.tonemap,
                       average=CLEAN_AVERAGE)  # fmt: skip
    return score.psnr


def clean_scores(capture: Path, field: MaterialField, mesh: Any, clean_spp: int, bounces: int) -> dict[str, Any]:
    """Clean PSNR (dB) of `field` on `mesh` against the Cycles capture and its twin (`clean_render_psnr`): the
    held-out photos in photos/ (`photos_clean_db`) and the mean over the held-out maps in relight/
    (`relit_clean_db`, each map in `relit_clean_maps_db`)."""
    twin = capture.with_name(capture.name + TWIN_SUFFIX)
    relit = sorted(p for p in (capture / "relight").glob("*") if (p / "transforms.json").is_file())
    maps = [clean_render_psnr(r, twin / "relight" / r.name, field, clean_spp, bounces, mesh, j + 1)
            for j, r in enumerate(relit)]  # fmt: skip
    return {"relit_clean_maps_db": maps, "relit_clean_db": sum(maps) / max(len(maps), 1),
            "photos_clean_db": clean_render_psnr(capture / "photos", twin / "photos", field, clean_spp, bounces,
                                                 mesh, 0)}  # fmt: skip


def variant_tto(name: str, config: ExtractConfig) -> TTOConfig:
    """"neural": the extraction's default TTO; any other name: that `neumatex eval` variant (eval/variants.py) on the
    config's variant base."""
    if name == "neural":
        return config.tto_config()
    tto = variant_config(name, config.variant_base())
    if tto is None:
        raise ValueError(f"variant {name!r} runs no TTO")
    return tto


def bench_capture(capture: Path, work: Path, spp: int, bounces: int, clean_spp: int, names: list[str],
                  out: dict[str, Any], lmrm: dict[str, str] | None = None) -> dict[str, Any]:
    """Add the scores of the variants `names` that `out` (the capture's kept row, or {}) lacks; returns it. `lmrm`:
    ExtractConfig's lmrm_weights / lmrm_readout where another LMRM than the shipped one predicts (kept in the row)."""
    config, pred, cap, mesh, photos = prepared_capture(capture, work, **(lmrm or {}))
    variants = {name: variant_tto(name, config) for name in names if name not in out}
    held_out = capture / "photos"
    n_photos = len(load_capture(held_out).frames)
    relit = sorted(p for p in (capture / "relight").glob("*") if (p / "transforms.json").is_file())
    record = json.loads((capture / "cycles.json").read_text())
    out.update({"capture": str(capture), "preset": record["preset"], "mesh": record["mesh"]["source"],
                "recipe": config.tto_config().to_dict(), **({"lmrm": lmrm} if lmrm else {})})  # fmt: skip
    for name, tto in variants.items():
        t0 = time.perf_counter()
        result = solve(tto, mesh, harness_envmap(cap), photos, cap.tonemap, pred, load_basis(basis_id=tto.basis),
                       truth=None)  # fmt: skip
        seconds = time.perf_counter() - t0
        field, scene_mesh = result.params.field(), result.mesh or mesh
        print(f"{capture.name} {name}: TTO {seconds:.0f} s, scoring"
              + (f" (choice: {result.selection})" if result.selection else ""), flush=True)
        twin = capture.with_name(capture.name + TWIN_SUFFIX)
        if (twin / "cycles.json").is_file():
            out[name] = {"tto_s": round(seconds, 1), "clean_spp": clean_spp, "clean_average": CLEAN_AVERAGE,
                         **clean_scores(capture, field, scene_mesh, clean_spp, bounces),
                         **selection_of(result)}  # fmt: skip
            continue
        relit_db = [_render_psnr(r, field, range(len(load_capture(r).frames)), spp, bounces, 0, scene_mesh)
                    for r in relit]  # fmt: skip
        out[name] = {"tto_s": round(seconds, 1), "relit_maps_db": relit_db,
                     "photos_db": _render_psnr(held_out, field, range(n_photos), spp, bounces, 0, scene_mesh),
                     "relit_db": sum(relit_db) / max(len(relit_db), 1), **selection_of(result)}  # fmt: skip
    return out


def against_shipped(rows: list[dict[str, Any]], names: list[str],
                    shipped: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Each variant of `names` in `rows` (another LMRM's) against its scores under the shipped LMRM (`shipped`, as
    `shipped_scores` gives them), per preset over the captures both have (`by_preset`, printed)."""
    out = {}
    for name in names:
        paired = [{"capture": r["capture"], "preset": r.get("preset", "?"), name: r[name],
                   SHIPPED: shipped[r["capture"]][name]} for r in rows if name in shipped.get(r["capture"], {})]
        if paired:
            out[f"{name} against {SHIPPED}"] = by_preset(paired, name, SHIPPED)
    return out


def shipped_scores() -> dict[str, dict[str, Any]]:
    """capture -> variant -> its latest clean scores under the shipped LMRM in bench/results/cycles_extract.jsonl
    (`basis_choice.cycles_latest`), "neural" being the extraction's default as bench/basis_choice.py reads it from
    its two bases' sides (`cycles_choices`)."""
    from basis_choice import cycles_choices, cycles_latest
    from variants_clean import basis_sides

    out: dict[str, dict[str, Any]] = {}
    for (capture, name), scores in cycles_latest().items():
        out.setdefault(capture, {})[name] = scores
    sides = basis_sides(DEFAULT_VARIANT)
    if sides is not None:
        for capture, scores in cycles_choices(DEFAULT_VARIANT, sides)[2].items():
            out.setdefault(capture, {})["neural"] = scores
    return out


def stored_rows(cpu_model: str) -> dict[str, dict[str, Any]]:
    """Per capture path, its row in the latest line of bench/results/cycles_extract.jsonl that holds it and was
    written on a machine whose CPU model is `cpu_model` (a later line's row carries the earlier rows' kept scores)."""
    path = RESULTS_DIR / "cycles_extract.jsonl"
    out: dict[str, dict[str, Any]] = {}
    for line in path.read_text().splitlines() if path.is_file() else []:
        record = json.loads(line)
        if record.get("machine", {}).get("cpu_model") == cpu_model:
            out.update({row["capture"]: row for row in record.get("rows", [])})
    return out


def selection_of(result: Any) -> dict[str, Any]:
    """The TTO's choices on held-out photos (select_anchor / select_uniform: held-out PSNRs, which result was kept;
    alternative_basis: the scores that chose the basis), when it made any."""
    return {"selection": result.selection} if result.selection else {}


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("captures", nargs="+", type=Path, help="captures written by `neumatex cycles-capture`")
    parser.add_argument("--work", default="runs/bench-cycles-extract", type=Path)
    parser.add_argument("--spp", type=int, default=256, help="samples per pixel of our scored renders")
    parser.add_argument("--clean-spp", type=int, default=64,
                        help="samples per pixel of each of our two half-renders in the clean scores")
    parser.add_argument("--max-bounces", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--again", action="store_true", help="recompute scores kept from an earlier run")
    parser.add_argument("--stored", action="store_true",
                        help="where no scores are kept, start from the capture's latest stored row (this CPU model's)")
    parser.add_argument("--lmrm-weights", default="",
                        help="an LMRM .safetensors (its .json beside it) instead of the shipped one (give --work too)")
    parser.add_argument("--lmrm-readout", default="",
                        help="an LMRM .safetensors, or 'shipped', whose decoders read the LMRM's prediction")
    parser.add_argument("--variants", default="pbr,neural",
                        help="TTO variants, comma separated: pbr (the baseline), neural (the extraction's default) "
                             "and any `neumatex eval` variant (eval/variants.py); each is compared with pbr")
    args = parser.parse_args()
    names = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in names if v != "neural" and v not in EVAL_VARIANTS]
    if unknown or "pbr" not in names:
        parser.error(f"--variants: unknown {unknown} or no pbr (variants: neural, {', '.join(EVAL_VARIANTS)})")
    lmrm = {k: v for k, v in (("lmrm_weights", args.lmrm_weights), ("lmrm_readout", args.lmrm_readout)) if v}
    if lmrm and args.stored:
        parser.error("--stored pairs with the shipped LMRM's rows: not with --lmrm-weights or --lmrm-readout")
    torch.set_num_threads(args.threads)
    rows = []
    stored = stored_rows(cpu_model()) if args.stored else {}
    for capture in args.captures:
        kept = args.work / capture.name / "scores.json"
        row = json.loads(kept.read_text()) if kept.is_file() and not args.again else dict(stored.get(str(capture), {}))
        if row and row.get("lmrm", {}) != lmrm:  # the work folder's stages hold another LMRM's prediction
            parser.error(f"{kept}: scored with LMRM {row.get('lmrm') or 'shipped'}, not {lmrm or 'shipped'}: give "
                         "another --work")  # fmt: skip
        if "recipe" in row and TTOConfig.from_dict(row["recipe"]) != ExtractConfig.preset("cpu").tto_config():
            row.pop("neural", None)  # kept from an extraction default that has changed since: "neural" is run again
        for name in [n for n in names if "relit_clean_db" in row.get(n, {})]:
            if row[name].get("clean_average", "radiance") != CLEAN_AVERAGE:
                row.pop(name)  # clean scores averaged another way: not comparable, run again
        if any(name not in row for name in names):
            row = bench_capture(capture, args.work / capture.name, args.spp, args.max_bounces, args.clean_spp, names,
                                row, lmrm)  # fmt: skip
            write_json_atomic(kept, row)
        rows.append(row)
        p = row["pbr"]
        for name in (n for n in names if n != "pbr"):
            n = row[name]
            kind = "_clean" if "relit_clean_db" in n else ""
            ph, re = f"photos{kind}_db", f"relit{kind}_db"
            print(f"{capture.name}{kind.replace('_', ', ')}: held-out photos {name} {n[ph]:.2f} dB, PBR {p[ph]:.2f} "
                  f"({n[ph] - p[ph]:+.2f}); relit {name} {n[re]:.2f}, PBR {p[re]:.2f} ({n[re] - p[re]:+.2f}); "
                  f"TTO {n['tto_s']:.0f} s / {p['tto_s']:.0f} s", flush=True)
    summary = {name: by_preset(rows, name) for name in names if name != "pbr"}
    if lmrm:
        summary.update(against_shipped(rows, names, shipped_scores()))
    record = {"spp": args.spp, **({"lmrm": lmrm} if lmrm else {}), "rows": rows, "by_preset": summary}
    # another LMRM's lines go to their own file: the readers of cycles_extract.jsonl take its rows as the shipped's
    print(f"appended to {write_result('cycles_extract_lmrm' if lmrm else 'cycles_extract', record)}")
    return 0


def by_preset(rows: list[dict[str, Any]], variant: str = "neural", base: str = "pbr") -> dict[str, dict[str, Any]]:
    """Per Principled preset, the mean of each side and the paired `variant` - `base` difference (+- s.e. over
    captures; each row holds both under those keys); prints it as a markdown table and returns it."""
    out: dict[str, dict[str, Any]] = {}
    clean = all("relit_clean_db" in r[variant] and "relit_clean_db" in r[base] for r in rows)
    keys = ("photos_clean_db", "relit_clean_db") if clean else ("photos_db", "relit_db")
    print(f"{variant} against {base}; scores: {', '.join(keys)}")
    print(f"| preset (captures) | photos: {variant} / {base} | difference | relit: {variant} / {base} | difference |")
    print("|---|---|---|---|---|")
    for preset in sorted({r.get("preset", "?") for r in rows}):
        group = [r for r in rows if r.get("preset", "?") == preset]
        entry: dict[str, Any] = {"captures": [r["capture"] for r in group]}
        cells = []
        for key in keys:
            n = np.array([r[variant][key] for r in group])
            p = np.array([r[base][key] for r in group])
            d = n - p
            _, se = mean_se(d)
            entry[key] = {"neural": float(n.mean()), "pbr": float(p.mean()), "diff": float(d.mean()), "se": se,
                          "worst": float(d.min())}  # fmt: skip
            cells += [f"{n.mean():.2f} / {p.mean():.2f}", f"{d.mean():+.2f} +- {se:.2f} (worst {d.min():+.2f})"]
        out[preset] = entry
        print(f"| {preset} ({len(group)}) | {' | '.join(cells)} |")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
