"""The PBR fallback that every asset ships, scored against Blender Cycles: each fit of it next to the neural material
it is fit from and the PBR baseline's own TTO.

    NEUMATEX_SHARED=../shared bench/cycles_matrix.sh      # the captures (coat, sheen, metal, diffuse, four meshes)
    NEUMATEX_SHARED=../shared .venv/bin/python bench/cycles_fallback.py runs/cycles/teapot-coat ... \\
        --fit-variants "cosine_directions=6,albedo=split_sum"     # or --fit-variants "": the shipped fit alone

The fallback (GLB / USD, for engines) is fit from the neural material, so bench/assets.py scores it against that
material, on our renders of synthetic objects. This benchmark asks the question a studio asks: how close does it come
to the photographs, made by another renderer? Per capture (made as bench/cycles_extract.py says, with its twin
`<capture>.seed1` for clean scores): the pipeline's stages before the TTO, the PBR baseline's TTO (variant "pbr", 400
steps) and the extraction's default TTO ("neural"), as bench/cycles_extract.py runs them. The default's result is
baked to an asset at the cpu preset's texture resolution (`asset_from_triplane`), whose fallback is fit once with
the shipped `PBRFitConfig` ("fallback") and once with each `--fit-variants` entry ("fallback:<entry>"; fields as in
bench/assets.py). The TTO's PBR phase, baked to the same textures, is "fallback:pbr_phase", and the one of the fit and
the PBR phase that the extraction ships ("fallback:chosen": neumatex_core/tto/fallback_choice.py, chosen on the photos
the TTO held out) carries that choice's own scores. Every material is rendered by our path tracer and scored
noise-corrected against Cycles' two renders (bench/cycles_extract.py's `clean_scores`) on the 8 held-out photos
(capture lighting, unseen poses) and on the relit views (held-out maps). Prints, per Principled preset over its
captures, the paired differences (fallback - PBR baseline, neural - fallback, the chosen fallback against the PBR
baseline, the fit and the neural material, the PBR phase - the fit, each variant's fallback - the fit) and writes a
JSON line to bench/results/cycles_fallback.jsonl. Each capture's scores are kept in
<work>/<capture>/fallback_scores.json and its baked asset in fallback_asset.pt, so an interrupted run resumes and a
new fit variant runs only its own fit and scores; a row made under another default TTO or shipped fit, or before
the choice, is made again, and `--again` recomputes everything.
Split the captures across processes with one thread each.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from assets import fit_variant  # noqa: E402
from common import argument_parser, prepared_capture, write_result  # noqa: E402
from cycles_extract import TWIN_SUFFIX, by_preset, clean_scores, selection_of, variant_tto  # noqa: E402

from neumatex_core.assets import MaterialAsset, asset_from_triplane  # noqa: E402
from neumatex_core.assets.pbr_fit import PBRFitConfig, fit_pbr  # noqa: E402
from neumatex_core.atomic import write_json_atomic  # noqa: E402
from neumatex_core.capture.tonemap import Tonemap  # noqa: E402
from neumatex_core.eval.references import harness_envmap  # noqa: E402
from neumatex_core.fields.neural_field import TriplaneMaterialField  # noqa: E402
from neumatex_core.fields.uv_textures import PBRTextureField  # noqa: E402
from neumatex_core.lighting.envmap import EnvironmentMap  # noqa: E402
from neumatex_core.materials.neural_basis import load_basis  # noqa: E402
from neumatex_core.pipeline import ExtractConfig  # noqa: E402
from neumatex_core.tto import TTOConfig, TTOResult, solve  # noqa: E402
from neumatex_core.tto.data import PhotoSet  # noqa: E402
from neumatex_core.tto.fallback_choice import bake_pbr_solution, choose_fallback  # noqa: E402
from neumatex_core.tto.pbr_start import validation_frames  # noqa: E402

SHIPPED = "fallback"  # the fit to the neural material (before 2026-12-07's choice, always the one shipped)
PBR_PHASE = "fallback:pbr_phase"  # the TTO's PBR phase, baked to the asset's fallback textures
CHOSEN = "fallback:chosen"  # the one of the two that the extraction ships (`choose_fallback`)
ASSET_FILE = "fallback_asset.pt"


def current() -> dict[str, Any]:
    """What a kept row must have been made with to be reused: the default's TTO recipe and the shipped fit."""
    return {"recipe": ExtractConfig.preset("cpu").tto_config().to_dict(), "fit": dataclasses.asdict(PBRFitConfig())}


def fallback_scores(capture: Path, asset: MaterialAsset, cfg: PBRFitConfig, clean_spp: int,
                    bounces: int) -> dict[str, Any]:
    """The scores of the asset's fallback fit again with `cfg`."""
    t0 = time.perf_counter()
    other = refit(asset, cfg)
    return {"fit_s": round(time.perf_counter() - t0, 1), "fit_loss": other.pbr_fit_loss,
            **clean_scores(capture, other.field("pbr"), other.mesh, clean_spp, bounces)}  # fmt: skip


def refit(asset: MaterialAsset, cfg: PBRFitConfig) -> MaterialAsset:
    """The asset with its PBR fallback fit again with `cfg` from its baked textures: the fallback that
    `asset_from_triplane(..., pbr=cfg)` makes."""
    texture, loss = fit_pbr(asset.basis, asset.material_texture, asset.texel_mask, cfg)
    return dataclasses.replace(asset, pbr_texture=texture, pbr_fit_loss=loss)


def choice_scores(capture: Path, asset: MaterialAsset, fit_scores: dict[str, Any], result: TTOResult,
                  photos: PhotoSet, envmap: EnvironmentMap, tonemap: Tonemap, tto: TTOConfig, clean_spp: int,
                  bounces: int) -> dict[str, Any]:
    """The fallback the extraction ships (`choose_fallback` between the fit, whose clean scores are `fit_scores`,
    and the TTO's PBR phase, on the photos the TTO held out, as the export stage chooses) and the PBR phase's baked
    solution, scored clean."""
    if result.pbr_solution is None or not result.selection.get("validation_photos"):
        raise SystemExit(f"{capture}: the default TTO held out no photos, so no fallback choice was made")
    mesh = result.mesh or asset.mesh
    held = photos.subset(validation_frames(photos.cameras, tto.validation_photos, mesh.bounding_sphere()[0]))
    t0 = time.perf_counter()
    chosen = choose_fallback(asset, result.pbr_solution, held, envmap, tonemap, tto)
    seconds = round(time.perf_counter() - t0, 1)
    taken = bool(chosen.metrics["fallback_from_pbr_phase"])
    phase = chosen.pbr_texture if taken else bake_pbr_solution(asset, result.pbr_solution)  # baked once where taken
    phase_scores = clean_scores(capture, PBRTextureField(phase), asset.mesh, clean_spp, bounces)
    choice = {k: chosen.metrics[k] for k in ("fallback_psnr_fit", "fallback_psnr_pbr_phase", "fallback_from_pbr_phase")}
    scores = phase_scores if taken else {k: v for k, v in fit_scores.items() if k not in ("fit_s", "fit_loss")}
    return {PBR_PHASE: phase_scores, CHOSEN: {"choice_s": seconds, **choice, **scores}}


def bench_capture(capture: Path, work: Path, variants: dict[str, PBRFitConfig], clean_spp: int,
                  bounces: int) -> dict[str, Any]:
    """The capture's row: scores of the PBR baseline, the default's neural material and each fallback fit; the
    baked asset is kept in work/fallback_asset.pt."""
    if not (capture.with_name(capture.name + TWIN_SUFFIX) / "cycles.json").is_file():
        raise SystemExit(f"{capture}: no twin capture {capture.name}{TWIN_SUFFIX} (bench/cycles_matrix.sh makes one); "
                         "the clean scores need it")
    config, pred, cap, mesh, photos = prepared_capture(capture, work)
    envmap = harness_envmap(cap)
    record = json.loads((capture / "cycles.json").read_text())
    row: dict[str, Any] = {"capture": str(capture), "preset": record["preset"], "mesh": record["mesh"]["source"],
                           "texture_resolution": config.texture_resolution, **current()}  # fmt: skip
    for name in ("pbr", "neural"):
        tto = variant_tto(name, config)
        t0 = time.perf_counter()
        result = solve(tto, mesh, envmap, photos, cap.tonemap, pred, load_basis(basis_id=tto.basis), truth=None)
        seconds = time.perf_counter() - t0
        field, scene_mesh = result.params.field(), result.mesh or mesh
        print(f"{capture.name} {name}: TTO {seconds:.0f} s, scoring", flush=True)
        row[name] = {"tto_s": round(seconds, 1), **selection_of(result),
                     **clean_scores(capture, field, scene_mesh, clean_spp, bounces)}  # fmt: skip
    if not isinstance(field, TriplaneMaterialField):
        raise SystemExit(f"{capture}: the default's result is a {type(field).__name__}, not a triplane field")
    t0 = time.perf_counter()
    asset = asset_from_triplane(capture.name, scene_mesh, field, config.texture_resolution)
    row[SHIPPED] = {"fit_s": round(time.perf_counter() - t0, 1), "fit_loss": asset.pbr_fit_loss,
                    **clean_scores(capture, asset.field("pbr"), asset.mesh, clean_spp, bounces)}  # fmt: skip
    torch.save(asset, work / ASSET_FILE)
    row.update(choice_scores(capture, asset, row[SHIPPED], result, photos, envmap, cap.tonemap,
                             variant_tto("neural", config), clean_spp, bounces))  # fmt: skip
    for text, cfg in variants.items():
        row[f"{SHIPPED}:{text}"] = fallback_scores(capture, asset, cfg, clean_spp, bounces)
    print(f"{capture.name}: " + ", ".join(f"{k} {v['photos_clean_db']:.2f} / {v['relit_clean_db']:.2f}"
                                           for k, v in row.items() if isinstance(v, dict) and "relit_clean_db" in v),
                                           flush=True)  # fmt: skip
    return row


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("captures", nargs="+", type=Path, help="Cycles capture folders (each with its .seed1 twin)")
    parser.add_argument("--work", type=Path, default=Path("runs/cycles-fallback"),
                        help="work folders (the pipeline's stages and each capture's kept scores)")
    parser.add_argument("--fit-variants", default="cosine_directions=6,albedo=split_sum",
                        help="';'-separated PBRFitConfig fields (field=value,...) fit next to the shipped fit")
    parser.add_argument("--clean-spp", type=int, default=64, help="samples per pixel of each of our half-renders")
    parser.add_argument("--max-bounces", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--again", action="store_true", help="recompute kept scores")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        variants = {t.strip(): fit_variant(t) for t in args.fit_variants.split(";") if t.strip()}
    except ValueError as e:
        raise SystemExit(f"--fit-variants: {e}") from None
    made_with = current()
    rows = []
    for capture in args.captures:
        kept = args.work / capture.name / "fallback_scores.json"
        row = json.loads(kept.read_text()) if kept.is_file() and not args.again else {}
        missing = [t for t in variants if f"{SHIPPED}:{t}" not in row]
        asset_file = args.work / capture.name / ASSET_FILE
        stale = {k: v for k, v in made_with.items() if row.get(k) != v}  # made by another default or fit
        if stale or not all(k in row for k in ("pbr", "neural", SHIPPED, CHOSEN)) or (
                missing and not asset_file.is_file()):
            row = bench_capture(capture, args.work / capture.name, variants, args.clean_spp, args.max_bounces)
        elif missing:  # the kept asset's fallback fit with the new variants only
            asset = torch.load(asset_file, weights_only=False)
            for text in missing:
                row[f"{SHIPPED}:{text}"] = fallback_scores(capture, asset, variants[text], args.clean_spp,
                                                           args.max_bounces)  # fmt: skip
        write_json_atomic(kept, row)
        rows.append(row)
    summary: dict[str, Any] = {"fallback-pbr": by_preset(rows, SHIPPED, "pbr"),
                               "neural-fallback": by_preset(rows, "neural", SHIPPED),
                               "chosen-pbr": by_preset(rows, CHOSEN, "pbr"),
                               "chosen-fallback": by_preset(rows, CHOSEN, SHIPPED),
                               "pbr_phase-fallback": by_preset(rows, PBR_PHASE, SHIPPED),
                               "neural-chosen": by_preset(rows, "neural", CHOSEN)}  # fmt: skip
    print("fallbacks taken from the PBR phase: " + ", ".join(
        Path(r["capture"]).name for r in rows if r[CHOSEN]["fallback_from_pbr_phase"]))
    for text in variants:
        summary[f"fallback-{text}"] = by_preset(rows, SHIPPED, f"{SHIPPED}:{text}")
    path = write_result("cycles_fallback", {"clean_spp": args.clean_spp, "variants": list(variants), "rows": rows,
                                            "by_preset": summary})  # fmt: skip
    print(f"appended to {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
