"""Does a capture fix its materials' latents, and does a fit find them from one start? (issue 14, Latents target)

For each material region of the test split's objects (`--data`, `neumatex synth --split test`; the LMRM's cached
pixels, `--cache`), `--observations` of its covered pixels give (normal, direction to the camera) pairs, the capture's
views. Each pair's direct-lighting appearance under the object's environment map is estimated with `--env-samples`
directions drawn from the map (shared by the object's regions, so two latents are compared on the same numbers; no
visibility, no indirect light): L(wo) = mean_j f(wi_j, wo) cos(wi_j) L_env(wi_j) / pdf(wi_j), f the basis v1 neural
material with the region's true rho_d. Then a latent is fitted to each region's true appearance (rho_d held at the
truth; Adam on the relative error) from each of nine starts: the training set's mean latent and its eight family
means (`--train`'s material.json). Measured in the same run, per region, latents in bench/lmrm.py's units
((l + 1) / 2), pooled over regions and by family:
- the mean latent alone (no fit): the reference;
- the fit from the mean latent (what one local descent from a neutral start finds);
- the best of the nine fits by appearance error (a choice that reads only the appearance, as the extraction's choice
  on held-out photos does).
Prints the appearance error each reaches and the latent PSNR; writes bench/results/latent_starts.jsonl.
    .venv/bin/python bench/latent_starts.py                 # all 40 test objects (about 10 min on one core)
    .venv/bin/python bench/latent_starts.py --limit 3 --no-save
"""

from __future__ import annotations

import collections
import json
import math
import sys
from dataclasses import dataclass, fields
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, write_result  # noqa: E402

from neumatex_core.geometry.surface import SurfaceInteraction  # noqa: E402
from neumatex_core.lighting.envmap import EnvironmentMap  # noqa: E402
from neumatex_core.lmrm.data import build_cache, finished_objects, load_synth_object, pixel_families  # noqa: E402
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial, load_basis  # noqa: E402


@dataclass
class Regions:
    """K regions, P observations each, M environment samples: wo [K, P, 3] and wi [K, P, M, 3] in each pixel's
    shading frame, radiance_over_pdf [K, M, 3] (L_env / pdf, linear RGB per sr), rho [K, P, 3] the truth's base colour,
    latent [K, 6] the truth's latent, family [K] names."""

    wo: torch.Tensor
    wi: torch.Tensor
    radiance_over_pdf: torch.Tensor
    rho: torch.Tensor
    latent: torch.Tensor
    family: list[str]


def environment_samples(env: EnvironmentMap, m: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """m world directions [m, 3] drawn from the map and their radiance / pdf [m, 3]."""
    wi, pdf, radiance = env.sample(torch.rand(m, 2, generator=generator))
    return wi, radiance / pdf.clamp_min(1e-8).unsqueeze(-1)


def _shading(normal: torch.Tensor) -> SurfaceInteraction:
    """A stand-in hit whose only use is its shading frame (`to_local`, the renderer's frame) at unit normals [N, 3]."""
    n = normal.shape[0]
    return SurfaceInteraction(position=normal, geo_normal=normal, shading_normal=normal, wo=normal, uv=None,
                              tri=torch.zeros(n, dtype=torch.long), bary=torch.zeros(n, 2))  # fmt: skip


def local_frames(normal: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """wo [P, 3] and the shared wi [M, 3] (world) in the shading frame of each normal [P, 3]: [P, 3], [P, M, 3]."""
    p, m = normal.shape[0], wi.shape[0]
    wi_local = _shading(normal.repeat_interleave(m, 0)).to_local(wi.repeat(p, 1)).reshape(p, m, 3)
    return _shading(normal).to_local(wo), wi_local


def region_observations(folder: Path, cache_dir: Path, n_obs: int, n_env: int,
                        generator: torch.Generator) -> Regions | None:
    """The regions of one test object with at least n_obs covered pixels, n_obs of them drawn each (None: none)."""
    data = torch.load(build_cache(folder, cache_dir), weights_only=True)
    wi_world, r_over_pdf = environment_samples(load_synth_object(folder).envmap, n_env, generator)
    targets = data["targets"].float()
    families, region_ids = pixel_families(folder, data["mask"].shape[0])
    region_of_pixel = region_ids[data["mask"]]  # the cache holds the covered pixels in mask order
    wos, wis, rhos, lats, fams = [], [], [], [], []
    for k, region in enumerate(json.loads((folder / "material.json").read_text())["regions"]):
        inside = (region_of_pixel == k).nonzero()[:, 0]
        if len(inside) < n_obs:
            continue
        latent = torch.tensor(region["latent"], dtype=torch.float32)
        pick = inside[torch.randperm(len(inside), generator=generator)[:n_obs]]
        wo, wi = local_frames(data["normal"][pick].float(), data["to_camera"][pick].float(), wi_world)
        wos.append(wo)
        wis.append(wi)
        rhos.append(targets[pick, :3])
        lats.append(latent)
        fams.append(families[k])
    if not lats:
        return None
    return Regions(torch.stack(wos), torch.stack(wis), r_over_pdf.expand(len(lats), n_env, 3), torch.stack(rhos),
                   torch.stack(lats), fams)  # fmt: skip


def concatenate(parts: list[Regions]) -> Regions:
    tensors = [torch.cat([getattr(p, f.name) for p in parts]) for f in fields(Regions) if f.name != "family"]
    return Regions(*tensors, [name for p in parts for name in p.family])


def direct_appearance(basis: NeuralBasis, regions: Regions, latent: torch.Tensor) -> torch.Tensor:
    """[K, P, 3] direct-lighting radiance of each observation with the regions' latents [K, 6] and true rho_d."""
    k, p, m, _ = regions.wi.shape
    lat = latent[:, None, None].expand(k, p, m, latent.shape[-1]).reshape(-1, latent.shape[-1])
    rho = regions.rho[:, :, None].expand(k, p, m, 3).reshape(-1, 3)
    wi = regions.wi.reshape(-1, 3)
    wo = regions.wo[:, :, None].expand(k, p, m, 3).reshape(-1, 3)
    f = NeuralMaterial(basis, rho, lat).eval(wi, wo) * wi[:, 2:3].clamp_min(0)
    return (f.reshape(k, p, m, 3) * regions.radiance_over_pdf[:, None]).mean(2)


def appearance_error(basis: NeuralBasis, regions: Regions, latent: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """[K] mean squared relative error ((L - L*) / (L* + 0.02)) over each region's observations and channels."""
    return (((direct_appearance(basis, regions, latent) - target) / (target + 0.02)) ** 2).mean((1, 2))


def fit_latents(basis: NeuralBasis, regions: Regions, target: torch.Tensor, start: torch.Tensor, steps: int,
                lr: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """Latents [K, 6] fitted to the appearance target [K, P, 3] from one start [6] (Adam on atanh(latent)), and their
    appearance errors [K]."""
    z = torch.atanh(start.clamp(-0.999, 0.999)).expand(len(regions.latent), -1).clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr)
    for _ in range(steps):
        loss = appearance_error(basis, regions, torch.tanh(z), target).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        latent = torch.tanh(z)
        return latent, appearance_error(basis, regions, latent, target)


def latent_psnr(latent: torch.Tensor, truth: torch.Tensor) -> float:
    """Pooled over regions, in (l + 1) / 2 units."""
    return -10 * math.log10(max(float((((latent - truth) / 2) ** 2).mean()), 1e-12))


def training_starts(train: Path, limit: int) -> list[tuple[str, torch.Tensor]]:
    """("mean", the mean latent over the training regions) and (family, its mean latent) per family."""
    by_family: dict[str, list[torch.Tensor]] = collections.defaultdict(list)
    for folder in finished_objects(train)[:limit]:
        for region in json.loads((folder / "material.json").read_text())["regions"]:
            by_family[region["family"]].append(torch.tensor(region["latent"], dtype=torch.float32))
    every = torch.stack([x for v in by_family.values() for x in v])
    return [("mean", every.mean(0))] + [(f, torch.stack(v).mean(0)) for f, v in sorted(by_family.items())]


def main() -> int:
    ap = argument_parser(__doc__)
    ap.add_argument("--data", default="data/lmrm-test", help="test split folder (neumatex synth --split test)")
    ap.add_argument("--cache", default="data/lmrm-test-cache", help="the LMRM's pixel cache for --data")
    ap.add_argument("--train", default="data/synth-train", help="training split: the starts (mean latents)")
    ap.add_argument("--train-objects", type=int, default=400)
    ap.add_argument("--limit", type=int, default=0, help="at most this many test objects (0: all)")
    ap.add_argument("--observations", type=int, default=16, help="(normal, view) pairs per region")
    ap.add_argument("--env-samples", type=int, default=32, help="environment directions per object")
    ap.add_argument("--steps", type=int, default=200, help="Adam steps of each fit")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    generator = torch.Generator().manual_seed(args.seed)
    basis = load_basis()
    basis.requires_grad_(False)
    folders = finished_objects(Path(args.data))[: args.limit or None]
    if not folders:
        print(f"error: {args.data}: no finished test objects", file=sys.stderr)
        return 2
    parts = [region_observations(f, Path(args.cache), args.observations, args.env_samples, generator)
             for f in folders]  # fmt: skip
    regions = concatenate([p for p in parts if p is not None])
    with torch.no_grad():
        target = direct_appearance(basis, regions, regions.latent)
    starts = training_starts(Path(args.train), args.train_objects)
    truth = regions.latent
    best, best_err, from_mean, mean_err = truth.clone(), torch.full((len(truth),), math.inf), truth, truth[:, 0]
    rows = {}
    print(f"{len(truth)} regions of {len(folders)} objects; latent PSNR pooled over regions, (l + 1) / 2 units")
    for name, start in starts:
        latent, err = fit_latents(basis, regions, target, start, args.steps)
        if name == "mean":
            from_mean, mean_err = latent, err
        better = err < best_err
        best[better], best_err[better] = latent[better], err[better]
        rows[name] = {"latent_psnr": latent_psnr(latent, truth),
                      "appearance_rel_rmse_median": float(err.sqrt().median())}
        print(f"  fit from the {name:10s} latent: {rows[name]['latent_psnr']:6.2f} dB, appearance relative rmse "
              f"(median) {rows[name]['appearance_rel_rmse_median']:.4f}", flush=True)  # fmt: skip
    mean_alone = latent_psnr(starts[0][1].expand_as(truth), truth)
    by_family: dict[str, dict[str, float]] = {}
    for fam in sorted(set(regions.family)):
        sel = torch.tensor([f == fam for f in regions.family])
        by_family[fam] = {"regions": int(sel.sum()),
                          "mean_alone": latent_psnr(starts[0][1].expand_as(truth[sel]), truth[sel]),
                          "from_mean": latent_psnr(from_mean[sel], truth[sel]),
                          "best_of_starts": latent_psnr(best[sel], truth[sel])}  # fmt: skip
    summary = {"mean_alone": mean_alone, "from_mean": latent_psnr(from_mean, truth),
               "best_of_starts": latent_psnr(best, truth),
               "from_mean_appearance_rel_rmse_median": float(mean_err.sqrt().median()),
               "best_appearance_rel_rmse_median": float(best_err.sqrt().median())}  # fmt: skip
    print(f"\nthe mean latent alone           {mean_alone:6.2f} dB (reference)")
    print(f"one fit from the mean latent    {summary['from_mean']:6.2f} dB ({summary['from_mean'] - mean_alone:+.2f}), "
          f"appearance relative rmse {summary['from_mean_appearance_rel_rmse_median']:.4f}")
    print(f"best of {len(starts)} starts by appearance {summary['best_of_starts']:6.2f} dB "
          f"({summary['best_of_starts'] - mean_alone:+.2f}), appearance relative rmse "
          f"{summary['best_appearance_rel_rmse_median']:.4f}")  # fmt: skip
    print("by family, mean alone -> one fit -> best of the starts (dB): " + ", ".join(
        f"{f} {v['mean_alone']:.1f} -> {v['from_mean']:.1f} -> {v['best_of_starts']:.1f}"
        for f, v in by_family.items()))
    if not args.no_save:
        path = write_result("latent_starts", {"data": args.data, "objects": len(folders), "regions": len(truth),
                                              "observations": args.observations, "env_samples": args.env_samples,
                                              "steps": args.steps, "summary": summary, "starts": rows,
                                              "by_family": by_family})  # fmt: skip
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
