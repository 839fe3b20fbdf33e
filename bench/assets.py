"""Material asset packages: size, write/read time, baked-texture and PBR-fallback fidelity, per material family.

Objects: 40 made here (the 40-object benchmark set of `neumatex_core.synth` did not exist when this was written;
using it is a change to `own_objects`): material families of the prior in turn (5 objects per family) on the
shared meshes (`--meshes`, shifted by one each round so every family meets 5 meshes), each object two draws of
its family blended over the surface by a smooth pattern, distilled into a triplane (8 x 32^2 per plane,
`fields.fit.fit_triplane`) as the LMRM / TTO would deliver it. Each object is packaged (`asset_from_triplane`:
xatlas unwrap, bake at `--texture`^2, PBR fit) and measured:

1. Package size (bytes, folder and zip) and its parts; write and read time of the folder and the zip, as ratios
   to writing / reading the same arrays raw (`numpy.save` / `numpy.load` of mesh, triplane and textures, one file
   each) measured in the same run (ratio > 1: the package is slower than raw bytes).
2. Render PSNR (default tonemap, covered pixels, views 0, 4, 8, 12 of the orbit at `--resolution`, `--spp`) of the
   baked neural textures against the triplane, and of the PBR fallback against the triplane (what PBR loses), per
   family. Both sides use next-event estimation with the same seed (one bounce), so their difference is the
   material's, not Monte Carlo noise (design note 10); the triplane against itself with another seed (MIS) is the
   noise floor of independent renders at this spp, printed for scale. Maps: the shared maps in turn.
3. `--fit-variants "albedo=exact;cosine_directions=6"`: the PBR fallback fitted again with other `PBRFitConfig`
   settings (each variant a comma list of field=value) and rendered the same way, per family, with its difference
   from the shipped fit paired per object (same renders' seed, same objects).

    .venv/bin/python bench/assets.py             # 40 objects, ~15 min on a busy 2-core CPU
    .venv/bin/python bench/assets.py --quick     # 8 objects (one per family), 128^2 textures
    .venv/bin/python bench/assets.py --objects 40 --texture 128 --repeats 1 \
        --fit-variants "cosine_directions=6;albedo=exact"  # ~10 min
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, time_repeats, write_result  # noqa: E402

from neumatex_core.assets import asset_from_triplane, read_asset, write_asset  # noqa: E402
from neumatex_core.assets.asset import MaterialAsset  # noqa: E402
from neumatex_core.assets.pbr_fit import PBRFitConfig, fit_pbr  # noqa: E402
from neumatex_core.assets.render import render_asset  # noqa: E402
from neumatex_core.capture.tonemap import Tonemap  # noqa: E402
from neumatex_core.eval.metrics import psnr  # noqa: E402
from neumatex_core.fields.fit import fit_triplane  # noqa: E402
from neumatex_core.geometry.camera import preset_views  # noqa: E402
from neumatex_core.geometry.gbuffer import render_gbuffer  # noqa: E402
from neumatex_core.geometry.mesh import load_mesh  # noqa: E402
from neumatex_core.lighting.envmap import EnvironmentMap  # noqa: E402
from neumatex_core.materials.neural_basis import (  # noqa: E402
    NeuralBasis,
    basis_record,
    load_basis,
    load_basis_from,
)
from neumatex_core.materials.prior import FAMILIES, sample_base_color, sample_parameters  # noqa: E402
from neumatex_core.render.path_tracer import PathTracerConfig  # noqa: E402

SHARED = Path(os.environ.get("NEUMATEX_SHARED", Path(__file__).resolve().parents[2] / "shared"))
MESHES = ("suzanne", "cow", "beetle", "teapot", "fandisk", "cheburashka", "rocker-arm", "beast")
VIEWS = (0, 4, 8, 12)
BENCH_SEED = 515_000


def own_objects(n: int, meshes: list[str]) -> list[dict[str, Any]]:
    """n object specs: family in turn, mesh shifted by one every round of families (so each family sees
    different meshes), seed."""
    specs = []
    for i in range(n):
        family, mesh = FAMILIES[i % len(FAMILIES)], meshes[(i + i // len(FAMILIES)) % len(meshes)]
        specs.append({"name": f"obj{i:02d}-{mesh}-{family}", "mesh": mesh, "family": family, "seed": BENCH_SEED + i})
    return specs


def make_object(spec: dict[str, Any], basis: NeuralBasis, texture: int) -> MaterialAsset:
    mesh = load_mesh(SHARED / "data" / "meshes" / f"{spec['mesh']}.obj").normalized()
    g = torch.Generator().manual_seed(spec["seed"])
    params = sample_parameters(spec["family"], 2, g)
    colors = sample_base_color(spec["family"], 2, g)
    with torch.no_grad():
        latents = basis.encode(params)
    phase = float(torch.rand(1, generator=g)) * 6.28

    def target(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s = torch.sigmoid(4 * torch.sin(3 * p[:, 0] + phase) * torch.cos(2.5 * p[:, 1] - phase)).unsqueeze(-1)
        return colors[0] * s + colors[1] * (1 - s), latents[0] * s + latents[1] * (1 - s)

    t0 = time.perf_counter()
    field, mse = fit_triplane(mesh.sample_surface(8000, seed=spec["seed"])[0], target, basis, channels=8,
                              resolution=32, steps=200, batch=4096, seed=spec["seed"])  # fmt: skip
    distil = time.perf_counter() - t0
    return asset_from_triplane(spec["name"], mesh, field, resolution=texture,
                               provenance={"bench": "assets", **spec}, metrics={"distil_gbuffer_mse": mse},
                               timings={"distil_s": distil})  # fmt: skip


def raw_arrays(asset: MaterialAsset) -> dict[str, np.ndarray]:
    assert asset.triplane is not None
    arrays = {"vertices": asset.mesh.vertices, "faces": asset.mesh.faces, "uvs": asset.mesh.uvs,
              "normals": asset.mesh.vertex_normals, "planes": asset.triplane.planes.detach().numpy(),
              "material": asset.material_texture.numpy(), "pbr": asset.pbr_texture.numpy()}
    return {k: np.ascontiguousarray(v) for k, v in arrays.items() if v is not None}


def io_figures(asset: MaterialAsset, basis: NeuralBasis, repeats: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        arrays = raw_arrays(asset)

        def write_raw() -> None:
            for k, v in arrays.items():
                np.save(root / f"raw_{k}.npy", v)

        def read_raw() -> None:
            for k in arrays:
                np.load(root / f"raw_{k}.npy")

        out["raw_write_s"] = time_repeats(write_raw, repeats)["min"]
        out["raw_read_s"] = time_repeats(read_raw, repeats)["min"]
        out["raw_bytes"] = sum((root / f"raw_{k}.npy").stat().st_size for k in arrays)
        for kind, name in (("folder", "pkg"), ("zip", "pkg.zip")):
            path = root / name
            out[f"{kind}_write_s"] = time_repeats(lambda p=path: write_asset(asset, p, overwrite=True), repeats)["min"]
            out[f"{kind}_read_s"] = time_repeats(lambda p=path: read_asset(p, basis=basis), repeats)["min"]
        pkg = root / "pkg"
        parts: dict[str, int] = {}
        for p in pkg.rglob("*"):
            if p.is_file():
                key = p.relative_to(pkg).parts[0] if p.parent != pkg else p.name
                parts[key] = parts.get(key, 0) + p.stat().st_size
        out["folder_bytes"] = sum(parts.values())
        out["zip_bytes"] = (root / "pkg.zip").stat().st_size
        out["parts_bytes"] = parts
        shutil.rmtree(pkg)
    return out


def fit_variant(text: str) -> PBRFitConfig:
    """A PBRFitConfig from "field=value,field=value" (`--fit-variants`); ValueError naming what is wrong."""
    defaults = PBRFitConfig()
    known = [f.name for f in fields(PBRFitConfig)]
    values: dict[str, Any] = {}
    for item in (x.strip() for x in text.split(",") if x.strip()):
        key, _, value = item.partition("=")
        if key not in known or not value:
            raise ValueError(f"{item!r}: expected field=value with a field of PBRFitConfig ({', '.join(known)})")
        values[key] = type(getattr(defaults, key))(value)  # each field's type is its default's
    return PBRFitConfig(**values)


def render_figures(asset: MaterialAsset, envmap: EnvironmentMap, resolution: int, spp: int,
                   variants: dict[str, PBRFitConfig] | None = None) -> dict[str, float]:
    cams = [preset_views(resolution)[i] for i in VIEWS]
    tm = Tonemap().apply
    masks = [render_gbuffer(asset.mesh, c).mask for c in cams]

    def display(images: list[torch.Tensor]) -> torch.Tensor:
        return torch.cat([tm(img)[m] for img, m in zip(images, masks, strict=True)]).unsqueeze(0)

    light = PathTracerConfig(spp=spp, max_bounces=1, strategy="light", hide_background=True)
    mis = PathTracerConfig(spp=spp, max_bounces=1, strategy="mis", hide_background=True)
    neural = display(render_asset(asset, envmap, cams, light, "triplane", seed=1))
    baked = display(render_asset(asset, envmap, cams, light, "textures", seed=1))
    pbr = display(render_asset(asset, envmap, cams, light, "pbr", seed=1))
    noise_a = display(render_asset(asset, envmap, cams, mis, "triplane", seed=2))
    noise_b = display(render_asset(asset, envmap, cams, mis, "triplane", seed=3))
    out = {"baked_psnr": psnr(baked, neural), "pbr_psnr": psnr(pbr, neural),
           "noise_floor_psnr": psnr(noise_a, noise_b)}
    for name, cfg in (variants or {}).items():  # the fallback fitted another way, rendered with the same seed
        texture, _ = fit_pbr(asset.basis, asset.material_texture, asset.texel_mask, cfg)
        other = display(render_asset(replace(asset, pbr_texture=texture), envmap, cams, light, "pbr", seed=1))
        out[f"pbr_psnr[{name}]"] = psnr(other, neural)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--objects", type=int, default=40)
    parser.add_argument("--texture", type=int, default=256, help="baked texture resolution")
    parser.add_argument("--resolution", type=int, default=64, help="render size (pixels)")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (min reported)")
    parser.add_argument("--meshes", type=str, default=",".join(MESHES))
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1: robust on a shared machine)")
    parser.add_argument("--basis", type=str, default="", help="basis weights .safetensors (record beside it as "
                        ".json); default: the shipped basis")
    parser.add_argument("--quick", action="store_true", help="8 objects (one per family), 128^2 textures, 1 repeat")
    parser.add_argument("--fit-variants", type=str, default="", help="other PBR fallback fits to pair with the "
                        "shipped one: variants separated by ';', each a comma list of PBRFitConfig field=value")
    parser.add_argument("--no-save", action="store_true")
    args = parser.parse_args(argv)
    try:
        variants = {v.strip(): fit_variant(v) for v in args.fit_variants.split(";") if v.strip()}
    except (ValueError, TypeError) as exc:
        parser.error(f"--fit-variants: {exc}")
    if args.quick:
        args.objects, args.texture, args.repeats = len(FAMILIES), 128, 1
    torch.set_num_threads(args.threads)
    basis = (load_basis_from(Path(args.basis), Path(args.basis).with_suffix(".json")) if args.basis
             else load_basis())  # fmt: skip
    print(f"basis {basis.basis_id}; torch threads {torch.get_num_threads()}")
    specs = own_objects(args.objects, [m.strip() for m in args.meshes.split(",") if m.strip()])
    object_source = "bench/assets.py own objects (no neumatex_core.synth benchmark set yet)"
    maps = sorted((SHARED / "data" / "envmaps").glob("*.exr"))
    envmaps = {p.stem: EnvironmentMap.from_file(p) for p in maps}
    rows = []
    for i, spec in enumerate(specs):
        t0 = time.perf_counter()
        asset = make_object(spec, basis, args.texture)
        build = time.perf_counter() - t0
        env_name = maps[i % len(maps)].stem
        row = {**spec, "envmap": env_name, "vertices": len(asset.mesh.vertices), "faces": asset.mesh.num_faces,
               "build_s": build, "timings": asset.timings, "pbr_fit_loss": asset.pbr_fit_loss,
               **io_figures(asset, basis, args.repeats),
               **render_figures(asset, envmaps[env_name], args.resolution, args.spp, variants)}  # fmt: skip
        rows.append(row)
        print(f"{spec['name']:34s} {row['faces']:6d} faces  zip {row['zip_bytes'] / 1e6:6.2f} MB  "
              f"write {row['zip_write_s']:.2f}s ({row['zip_write_s'] / row['raw_write_s']:.0f}x raw)  "
              f"read {row['zip_read_s']:.2f}s ({row['zip_read_s'] / row['raw_read_s']:.0f}x raw)  "
              f"baked {row['baked_psnr']:.1f} dB  pbr {row['pbr_psnr']:.1f} dB  (noise {row['noise_floor_psnr']:.1f})  "
              f"build {build:.1f}s", flush=True)

    def med(key: str, sel: list[dict[str, Any]] | None = None) -> float:
        return statistics.median(r[key] for r in (sel or rows))

    print(f"\n{len(rows)} objects, {args.texture}^2 textures, renders {len(VIEWS)} views x {args.resolution}^2 px x "
          f"{args.spp} spp; objects: {object_source}")
    print("\n| figure | median | min | max |\n|---|---|---|---|")
    table = (("zip_bytes", "package size, zip (MB)", 1e-6), ("folder_bytes", "package size, folder (MB)", 1e-6),
             ("zip_write_s", "write zip (s)", 1), ("zip_read_s", "read zip (s)", 1),
             ("folder_write_s", "write folder (s)", 1), ("folder_read_s", "read folder (s)", 1))
    for key, label, scale in table:
        vals = [r[key] * scale for r in rows]
        print(f"| {label} | {statistics.median(vals):.3f} | {min(vals):.3f} | {max(vals):.3f} |")
    for kind in ("zip", "folder"):
        for op in ("write", "read"):
            ratios = [r[f"{kind}_{op}_s"] / r[f"raw_{op}_s"] for r in rows]
            print(f"| {op} {kind} / raw numpy {op} (ratio) | {statistics.median(ratios):.1f} | {min(ratios):.1f} | "
                  f"{max(ratios):.1f} |")
    print("\nRender PSNR against the triplane (dB), per family: mean (min)\n")
    print("| family | baked textures | PBR fallback | PBR fit loss | noise floor (independent renders) |")
    print("|---|---|---|---|---|")
    per_family = {}
    for fam in FAMILIES:
        sel = [r for r in rows if r["family"] == fam]
        if not sel:
            continue
        fig = {k: [r[k] for r in sel] for k in ("baked_psnr", "pbr_psnr", "pbr_fit_loss", "noise_floor_psnr")}
        per_family[fam] = {k: {"mean": statistics.fmean(v), "min": min(v)} for k, v in fig.items()}
        print(f"| {fam} | {statistics.fmean(fig['baked_psnr']):.1f} ({min(fig['baked_psnr']):.1f}) | "
              f"{statistics.fmean(fig['pbr_psnr']):.1f} ({min(fig['pbr_psnr']):.1f}) | "
              f"{statistics.fmean(fig['pbr_fit_loss']):.4f} | {statistics.fmean(fig['noise_floor_psnr']):.1f} |")
    print(f"| all | {statistics.fmean(r['baked_psnr'] for r in rows):.1f} ({min(r['baked_psnr'] for r in rows):.1f}) | "
          f"{statistics.fmean(r['pbr_psnr'] for r in rows):.1f} ({min(r['pbr_psnr'] for r in rows):.1f}) | "
          f"{statistics.fmean(r['pbr_fit_loss'] for r in rows):.4f} | {med('noise_floor_psnr'):.1f} (median) |")
    if variants:
        print("\nThe PBR fallback's render PSNR against the triplane (dB) by the fit, per family: mean; against the "
              "shipped fit, paired per object: mean +- standard error\n")
        print("| family | shipped fit | " + " | ".join(f"{m} | {m} - shipped" for m in variants) + " |")
        print("|---|---|" + "---|---|" * len(variants))
        for fam in [*FAMILIES, "all"]:
            sel = [r for r in rows if fam in ("all", r["family"])]
            if not sel:
                continue
            cells = [f"{statistics.fmean(r['pbr_psnr'] for r in sel):.2f}"]
            for name in variants:
                key = f"pbr_psnr[{name}]"
                d = [r[key] - r["pbr_psnr"] for r in sel]
                se = statistics.stdev(d) / len(d) ** 0.5 if len(d) > 1 else float("nan")
                cells += [f"{statistics.fmean(r[key] for r in sel):.2f}", f"{statistics.fmean(d):+.2f} +- {se:.2f}"]
                if fam != "all":
                    per_family[fam][key] = {"mean": statistics.fmean(r[key] for r in sel)}
            print(f"| {fam} | " + " | ".join(cells) + " |")
    if not args.no_save:
        record = Path(args.basis).with_suffix(".json") if args.basis else None
        basis_metrics = (basis_record(record) if record else basis_record()).get("metrics")
        path = write_result("assets", {"basis_id": basis.basis_id, "basis_metrics": basis_metrics,
                                       "objects_source": object_source,
                                       "settings": vars(args), "per_family": per_family, "objects": rows})
        print(f"\nappended to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
