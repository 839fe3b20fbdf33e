"""Neural basis quality and speed: the shipped basis against the analytic layered material it was trained on.

Figures:
1. BSDF / T / R errors on `--heldout` (10,000) held-out parameter sets (4 direction pairs each, wo uniform, wi half
   importance-sampled, half uniform; a seed training never used): median relative error of f_neu against f_spec
   where visible (|f_neu - f| / (f + 1e-3 / cos_i)), log-L1 of f cos_i (the training loss), mean absolute T and R
   errors; overall and per family of the prior (1/8 of the sets each, plus the uniform draws overall).
2. Per family, sphere renders of the neural material (basis.encode(params)) against the analytic material under
   each shared environment map, at equal samples per pixel, one bounce (a sphere is convex): PSNR after the
   default tonemap over the sphere's pixels, mean and minimum over `--per-family` materials x maps (goal: 35 dB
   in every family). Both renders use next-event estimation with the same seed (common random numbers: the same
   light samples), so most of the noise cancels in their difference d = T(neural) - T(analytic); what is left is
   removed by a second, independent pair of renders: mean(d_a d_b) over the sphere is an unbiased estimate of the
   squared difference of the noise-free display images (E[d_a d_b] = E[d_a] E[d_b]), the same correction as
   `eval.references.clean_psnr` applies to independent halves. "clean" is -10 log10 of it, "raw" the PSNR of
   one pair as it is. For scale, the noise floor of independent rendering (the analytic material against itself
   with another seed, MIS) is printed too.
3. Importance sampling: per (material, wo) the variance of the albedo estimator f cos / pdf with the neural
   sampler (NeuralMaterial.sample) against cosine sampling at equal samples; ratio var_cosine / var_neural
   (> 1: ours better), median and geometric mean; the analytic material's own sampler as a reference.
4. Speed: decoder evaluations per second (the 4x64 MLP alone, and `NeuralBasis.bsdf` with its direction
   features) on `--batch` points under no_grad, times the decoder's FLOPs per evaluation, as a fraction of the
   machine's peak FP32 rate measured in the same run by a 4096^2 matrix product.

`--fit-latent N` renders the spheres of 2. with a latent fitted to the analytic material by N Adam steps through the
frozen decoder and aux networks (from basis.encode(params); the training loss, bsdf log-L1 + 2 x |T, R| error)
instead of the encoder's: the difference between the two runs is the encoder's share of the sphere error, what
is left the decoder's (docs/design-notes.md item 31).

    .venv/bin/python bench/basis.py            # ~5 min on an idle 2-core CPU
    .venv/bin/python bench/basis.py --quick    # smoke run
    .venv/bin/python bench/basis.py --weights runs/basis/basis.safetensors   # a candidate, not the shipped one
    .venv/bin/python bench/basis.py --families coated,fuzzy --fit-latent 300   # the encoder's share of the error
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, time_repeats, write_result  # noqa: E402

from neumatex_core.capture import Tonemap  # noqa: E402
from neumatex_core.eval.metrics import psnr  # noqa: E402
from neumatex_core.geometry.mesh import icosphere  # noqa: E402
from neumatex_core.lighting.envmap import EnvironmentMap  # noqa: E402
from neumatex_core.materials.base import cosine_pdf, cosine_sample  # noqa: E402
from neumatex_core.materials.basis_training import EPS, _generator, bsdf_loss, draw_batch, log_target  # noqa: E402
from neumatex_core.materials.layered import LayeredMaterial  # noqa: E402
from neumatex_core.materials.neural_basis import (  # noqa: E402
    NeuralBasis,
    NeuralMaterial,
    direction_features,
    load_basis,
    load_basis_from,
)
from neumatex_core.materials.prior import FAMILIES, sample_base_color, sample_parameters  # noqa: E402
from neumatex_core.render.gallery import SphereSettings, sphere_pair  # noqa: E402

SHARED = Path(os.environ.get("NEUMATEX_SHARED", Path(__file__).resolve().parents[2] / "shared"))
ENVMAPS = SHARED / "data" / "envmaps"
BENCH_SEED = 777_001  # held-out draws: training uses other seeds (basis_training._generator)


def paired_clean_mse(d_a: np.ndarray, d_b: np.ndarray) -> tuple[float, float]:
    """(clean MSE, its standard error) from two independent difference images d_a, d_b [P, 3] (display units):
    mean(d_a d_b), an unbiased estimate of mean((E d)^2); SE over pixels (a pixel's channels share paths)."""
    per_pixel = (d_a * d_b).mean(-1)
    return float(per_pixel.mean()), float(per_pixel.std(ddof=1) / np.sqrt(per_pixel.shape[0]))


def errors(basis: NeuralBasis, params: torch.Tensor, seed: int) -> dict[str, float]:
    """Decoder / aux errors for the parameter sets `params` [n, 22], 4 direction pairs each."""
    g = _generator(seed, "heldout", 1)
    rel, log_l1, t_err, r_err = [], [], [], []
    with torch.no_grad():
        for _ in range(4):
            b = draw_batch(params.shape[0], g, params)
            latent = basis.encode(b.params)
            f = basis.bsdf(latent, b.wi, b.wo)
            cos_i = b.wi[:, 2:3]
            rel.append(((f - b.f_spec).abs() / (b.f_spec + EPS / cos_i)).flatten())
            log_l1.append((log_target(f, b.wi[:, 2]) - log_target(b.f_spec, b.wi[:, 2])).abs().flatten())
            t, r = basis.transmission_reflectance(latent, b.wo)
            t_err.append((t - b.transmission).abs().flatten())
            r_err.append((r - b.reflected).abs())
    return {"bsdf_median_rel_error": float(torch.cat(rel).median()), "bsdf_log_l1": float(torch.cat(log_l1).mean()),
            "t_mae": float(torch.cat(t_err).mean()), "r_mae": float(torch.cat(r_err).mean())}  # fmt: skip


def sampling_variance(basis: NeuralBasis, n_materials: int, n_samples: int, seed: int) -> dict[str, float]:
    """Variance ratios of the albedo estimator: cosine / neural sampler, cosine / analytic sampler."""
    g = torch.Generator().manual_seed(seed)
    per = max(1, n_materials // len(FAMILIES))
    params = torch.cat([sample_parameters(f, per, g) for f in FAMILIES])
    colors = torch.cat([sample_base_color(f, per, g) for f in FAMILIES])
    k = params.shape[0]
    z = torch.rand(k, generator=g) * 0.95 + 0.05
    wo = torch.stack([torch.sqrt(1 - z * z), torch.zeros(k), z], dim=-1)
    idx = torch.arange(k).repeat_interleave(n_samples)
    wo_n = wo[idx]
    with torch.no_grad():
        neural = NeuralMaterial(basis, colors[idx], basis.encode(params)[idx])
        analytic = LayeredMaterial(params[idx], colors[idx])

        def estimator_var(material: Any, wi: torch.Tensor, pdf: torch.Tensor) -> torch.Tensor:
            f = material.eval(wi, wo_n).mean(-1) * wi[:, 2].clamp_min(0)
            w = torch.where(pdf > 0, f / pdf.clamp_min(1e-30), torch.zeros_like(f)).double()
            return w.reshape(k, n_samples).var(1)

        u_lobe, u_dir = torch.rand(k * n_samples, generator=g), torch.rand(k * n_samples, 2, generator=g)
        wi_c = cosine_sample(u_dir)
        var_cos_neural = estimator_var(neural, wi_c, cosine_pdf(wi_c))
        var_cos_analytic = estimator_var(analytic, wi_c, cosine_pdf(wi_c))
        var_neural = estimator_var(neural, *neural.sample(wo_n, u_lobe, u_dir))
        var_analytic = estimator_var(analytic, *analytic.sample(wo_n, u_lobe, u_dir))
    ratio_n = (var_cos_neural / var_neural.clamp_min(1e-30)).clamp(1e-6, 1e6)
    ratio_a = (var_cos_analytic / var_analytic.clamp_min(1e-30)).clamp(1e-6, 1e6)
    return {"neural_median": float(ratio_n.median()), "neural_geomean": float(ratio_n.log().mean().exp()),
            "analytic_median": float(ratio_a.median()), "analytic_geomean": float(ratio_a.log().mean().exp()),
            "materials": k, "samples": n_samples}  # fmt: skip


def fitted_latent(basis: NeuralBasis, params: torch.Tensor, steps: int, seed: int, n: int = 8192,
                  render_weight: float = 0.0, group: int = 16) -> torch.Tensor:
    """The latent [latent_dim] in (-1, 1) whose decoded BSDF, T and R best match the analytic material `params`
    [22]: `steps` Adam steps on atanh(latent) from basis.encode(params), the training loss on n direction pairs
    (with render_weight > 0 plus that weight times the render-unit term over groups of `group`)."""
    with torch.no_grad():
        start = basis.encode(params.unsqueeze(0))[0]
    u = torch.atanh(start.clamp(-0.999, 0.999)).requires_grad_(True)
    opt = torch.optim.Adam([u], lr=0.02)
    g = group if render_weight > 0 else 1
    for step in range(steps):
        b = draw_batch(n, _generator(seed, "heldout", step), params.unsqueeze(0).expand(n // g, -1).contiguous(),
                       group=g)
        loss = bsdf_loss(basis, b, aux_weight=2.0, latent=torch.tanh(u).expand(n, -1), render_weight=render_weight,
                         group=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return torch.tanh(u).detach()


def decoder_flops(basis: NeuralBasis) -> int:
    """Multiply-adds x 2 of the decoder MLP for one evaluation."""
    return sum(2 * m.in_features * m.out_features for m in basis.decoder if isinstance(m, torch.nn.Linear))


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--heldout", type=int, default=10_000, help="held-out parameter sets")
    parser.add_argument("--per-family", type=int, default=2, help="sphere materials per family")
    parser.add_argument("--envmaps", type=str, default="", help="comma-separated maps (default: all shared)")
    parser.add_argument("--fit-latent", type=int, default=0, help="spheres with a latent fitted by this many steps "
                        "instead of the encoder's (0: the encoder's)")
    parser.add_argument("--fit-render-weight", type=float, default=0.0, help="with --fit-latent: weight of the "
                        "render-unit term (basis_training.render_terms) in the fit's objective")
    parser.add_argument("--families", type=str, default="", help="comma-separated sphere families (default: all; "
                        "the others' spheres are drawn and skipped, so each family's spheres stay the same)")
    parser.add_argument("--resolution", type=int, default=40)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--batch", type=int, default=1 << 16, help="points per decoder evaluation")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="smoke run: fewer sets, 1 map, 24 px, 32 spp")
    parser.add_argument("--no-save", action="store_true")
    parser.add_argument("--weights", type=Path, default=None,
                        help="a basis .safetensors to measure instead of the shipped one (its .json beside it)")
    args = parser.parse_args(argv)
    if args.quick:
        args.heldout, args.per_family, args.resolution, args.spp, args.repeats = 800, 1, 24, 32, 2
        args.envmaps = args.envmaps or str(ENVMAPS / "studio.exr")
    map_paths = [Path(p) for p in args.envmaps.split(",")] if args.envmaps else sorted(ENVMAPS.glob("*.exr"))
    basis = load_basis() if args.weights is None else load_basis_from(args.weights, args.weights.with_suffix(".json"))
    print(f"basis {basis.basis_id}")

    # 1. held-out errors, overall and per family
    g = torch.Generator().manual_seed(BENCH_SEED)
    from neumatex_core.materials.basis_training import draw_parameters

    overall = errors(basis, draw_parameters(args.heldout, g), BENCH_SEED)
    per_family_err = {f: errors(basis, sample_parameters(f, args.heldout // len(FAMILIES), g), BENCH_SEED + 1)
                      for f in FAMILIES}  # fmt: skip
    print(f"\nBSDF on {args.heldout} held-out parameter sets: median relative error "
          f"{overall['bsdf_median_rel_error']:.4f}, log-L1 {overall['bsdf_log_l1']:.4f}, "
          f"T MAE {overall['t_mae']:.4f}, R MAE {overall['r_mae']:.4f}")

    # 2. sphere PSNR per family and map
    tonemap = Tonemap().apply
    sphere = icosphere(4)
    settings = SphereSettings(args.resolution, args.spp, seed=11, strategy="light")
    settings_b = SphereSettings(args.resolution, args.spp, seed=12, strategy="light")
    mis_a = SphereSettings(args.resolution, args.spp, seed=13, strategy="mis")
    mis_b = SphereSettings(args.resolution, args.spp, seed=14, strategy="mis")
    gm = torch.Generator().manual_seed(BENCH_SEED + 2)
    psnr_rows: dict[str, dict[str, float]] = {}
    sphere_families = args.families.split(",") if args.families else list(FAMILIES)
    for family in FAMILIES:
        params = sample_parameters(family, args.per_family, gm)
        colors = sample_base_color(family, args.per_family, gm)
        if family not in sphere_families:
            continue
        latents = [fitted_latent(basis, params[i], args.fit_latent, BENCH_SEED + 5,
                                 render_weight=args.fit_render_weight) if args.fit_latent else None
                   for i in range(args.per_family)]  # fmt: skip
        raw, clean, clean_se, floor = [], [], [], []
        for path in map_paths:
            env = EnvironmentMap.from_file(path)
            for i in range(args.per_family):
                analytic, neural = sphere_pair(params[i], colors[i], env, basis, settings, sphere, latents[i])
                analytic_b, neural_b = sphere_pair(params[i], colors[i], env, basis, settings_b, sphere, latents[i])
                mask = analytic.sum(-1) > 0
                raw.append(psnr(tonemap(neural), tonemap(analytic), mask))
                d_a = (tonemap(neural) - tonemap(analytic))[mask].cpu().numpy()
                d_b = (tonemap(neural_b) - tonemap(analytic_b))[mask].cpu().numpy()
                mse, se = paired_clean_mse(d_a, d_b)
                clean.append(-10 * np.log10(max(mse, 1e-10)))
                clean_se.append(se / max(mse, 1e-10) * 10 / np.log(10))  # dB, first order
                if i == 0:
                    ma, _ = sphere_pair(params[i], colors[i], env, basis, mis_a, sphere)
                    mb, _ = sphere_pair(params[i], colors[i], env, basis, mis_b, sphere)
                    floor.append(psnr(tonemap(ma), tonemap(mb), mask))
        psnr_rows[family] = {"psnr_mean": float(np.mean(clean)), "psnr_min": float(np.min(clean)),
                             "psnr_se_max": float(np.max(clean_se)), "raw_psnr_mean": float(np.mean(raw)),
                             "independent_noise_floor_mean": float(np.mean(floor))}  # fmt: skip
        print(f"  {family:11s} sphere PSNR neural vs analytic, clean {np.mean(clean):5.1f} dB "
              f"(min {np.min(clean):5.1f}, SE <= {np.max(clean_se):.2f}); raw {np.mean(raw):5.1f} dB; "
              f"independent-noise floor at this spp {np.mean(floor):5.1f} dB")

    # 3. sampling
    sampling = sampling_variance(basis, 1024 if not args.quick else 128, 256, BENCH_SEED + 3)
    print(f"\nsampling variance reduction over cosine (equal samples): neural median {sampling['neural_median']:.2f}x "
          f"(geomean {sampling['neural_geomean']:.2f}x); analytic sampler median {sampling['analytic_median']:.2f}x")

    # 4. speed
    n = args.batch
    gs = torch.Generator().manual_seed(1)
    latent = torch.rand(n, basis.arch.latent_dim, generator=gs) * 2 - 1
    wi = torch.nn.functional.normalize(torch.randn(n, 3, generator=gs), dim=-1).abs()
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=gs), dim=-1).abs()
    x = torch.cat([latent, direction_features(wi, wo)], dim=-1)
    a_mat, b_mat = torch.randn(4096, 4096, generator=gs), torch.randn(4096, 4096, generator=gs)
    with torch.no_grad():
        t_mlp = time_repeats(lambda: basis.decoder(x), args.repeats, warmup=1)
        t_bsdf = time_repeats(lambda: basis.bsdf(latent, wi, wo), args.repeats, warmup=1)
        t_mm = time_repeats(lambda: a_mat @ b_mat, args.repeats, warmup=1)
    peak = 2 * 4096**3 / t_mm["min"]
    flops = decoder_flops(basis)
    mlp_rate, bsdf_rate = n / t_mlp["min"], n / t_bsdf["min"]
    print(f"\ndecoder: {flops} FLOP/eval; MLP alone {mlp_rate:.3e} evals/s = {mlp_rate * flops / 1e9:.1f} GFLOP/s "
          f"= {mlp_rate * flops / peak:.3f} of peak {peak / 1e9:.1f} GFLOP/s (4096^2 matmul); "
          f"bsdf() with features {bsdf_rate:.3e} evals/s = {bsdf_rate * flops / peak:.3f} of peak")

    print("\n| family | clean PSNR neural vs analytic (dB, mean / min) | raw (dB) | BSDF median rel. err. | T MAE |"
          " R MAE |")
    print("|---|---|---|---|---|---|")
    for family in sphere_families:
        p, e = psnr_rows[family], per_family_err[family]
        print(f"| {family} | {p['psnr_mean']:.1f} / {p['psnr_min']:.1f} | {p['raw_psnr_mean']:.1f} | "
              f"{e['bsdf_median_rel_error']:.3f} | {e['t_mae']:.4f} | {e['r_mae']:.4f} |")
    if not args.no_save:
        path = write_result("basis", {
            "basis_id": basis.basis_id, "envmaps": [p.name for p in map_paths],
            "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "heldout": overall, "heldout_per_family": per_family_err, "sphere_psnr": psnr_rows,
            "sampling": sampling,
            "speed": {"decoder_flops_per_eval": flops, "mlp_evals_per_s": mlp_rate, "bsdf_evals_per_s": bsdf_rate,
                      "peak_flops": peak, "mlp_fraction_of_peak": mlp_rate * flops / peak,
                      "bsdf_fraction_of_peak": bsdf_rate * flops / peak, "timings": {
                          "mlp": t_mlp, "bsdf": t_bsdf, "matmul": t_mm}},
        })  # fmt: skip
        print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
