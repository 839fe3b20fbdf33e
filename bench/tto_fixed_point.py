"""Does the TTO keep the right answer? The neural TTO started from the ground truth itself, scored clean.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/tto_fixed_point.py [--objects test-000000]
        [--set lr=0.02 --set spp=32 --set pixels=256] [--threads 1]

Per benchmark object with references (`neumatex references`): the object's exact ground-truth material
(`eval.references.truth_field`) is distilled into a triplane of the LMRM's size and a material decoder
(`fields.fit.fit_triplane`, 2000 Adam steps on 200k surface points, no photos): the reference, scored clean on the 17
orbital views and relight views 0, 8, 16 (`eval.references.clean_metrics`, the harness's scoring). Then the
extraction's neural TTO (the cpu preset's steps, learning rate, samples, decoder fine-tuning) runs from that
triplane on the object's photos, with nothing that holds it there (init "lmrm" on the distilled triplane, no
regulariser, no consistency term, no choice of candidates or basis), and its result is scored the same way. A TTO
whose objective has its minimum at the truth and whose steps are quiet enough keeps it; what it loses is the
ceiling its noise and bias put on any start (docs/design-notes.md, note 49). `--set KEY=VALUE` changes a
`TTOConfig` field of that TTO (repeatable). Prints both scores and the loss (after - before, dB) and appends a JSON
line to bench/results/tto_fixed_point.jsonl. Needs the LMRM's other heads only for the prediction's structure: it
runs the pipeline's validate / prepare_views / lmrm stages into --work (resumable). `--resolution R` distils the
truth into an R x R triplane instead of the LMRM's (fewer numbers for the photos' noise to move); `--data` another
split, e.g. the same objects synthesised with less noisy photos (`neumatex synth --spp 256`, its references copied
from the benchmark's: the truth is the same; design note 57). `--seeds 0,1,...` runs that TTO once per seed (its
pixel draws and render samples) and also scores their image-space mean (`SeedMixture`): what the seeds share of the
distance from the truth (the "common" share of the PathTrace error, from the clean MSEs of each run and of their
mean) is what no averaging of runs or of quieter steps removes (docs/design-notes.md, note 82).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, prepared_capture, write_result  # noqa: E402

from neumatex_core.eval.references import clean_metrics, harness_envmap, truth_field  # noqa: E402
from neumatex_core.fields.fit import fit_triplane  # noqa: E402
from neumatex_core.fields.neural_field import TriplaneMaterialField  # noqa: E402
from neumatex_core.geometry.surface import SurfaceInteraction  # noqa: E402
from neumatex_core.lmrm.inference import LMRMPrediction  # noqa: E402
from neumatex_core.materials.field import MaterialField  # noqa: E402
from neumatex_core.materials.neural_basis import NeuralMaterial, load_basis  # noqa: E402
from neumatex_core.pipeline import ExtractConfig  # noqa: E402
from neumatex_core.tto.config import TTOConfig  # noqa: E402
from neumatex_core.tto.pbr_start import solve  # noqa: E402

RENDER_VIEWS = tuple(range(17))
RELIGHT_VIEWS = (0, 8, 16)
SPP_HALF = 32  # the harness's clean_spp_half
FIT_POINTS, FIT_STEPS = 200_000, 2000


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """KEY=VALUE strings -> TTOConfig field values of the field's type."""
    types = {f.name: type(getattr(TTOConfig(), f.name)) for f in fields(TTOConfig)}
    out: dict[str, Any] = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if key not in types:
            raise SystemExit(f"--set {pair}: TTOConfig has no field {key!r}")
        kind = types[key]
        out[key] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return out


def fixed_point_config(overrides: dict[str, Any]) -> TTOConfig:
    """The extraction's TTO started from the given triplane and free to leave it (then `overrides`)."""
    base = ExtractConfig.preset("cpu").tto_config()
    free = {"init": "lmrm", "reg": "none", "lambda_consistency": 0.0, "select_uniform": False, "select_anchor": False,
            "alternative_basis": "", "select_basis": ""}  # fmt: skip
    return replace(base, **{**free, **overrides})


def scores(object_dir: Path, field: MaterialField, mesh: Any) -> dict[str, float]:
    m = clean_metrics(object_dir, field, mesh, RENDER_VIEWS, RELIGHT_VIEWS, SPP_HALF, seed=0)
    return {k: m[k] for k in ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_pathtrace_clean_mse") if k in m}


class SeedMixture(MaterialField):
    """Each shading point takes the material of one of `fields` (triplane fields in one basis) at random, uniformly
    (the global torch generator): its BSDF is in expectation their mean, so where light bounces once its render's
    expectation is the mean of theirs, the image-space average of the runs (their parameters' mean is not: the
    decoder is not linear). Its G-buffers are the mean of theirs."""

    def __init__(self, fields_: list[TriplaneMaterialField]) -> None:
        self.fields = fields_

    def each(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rho_d [F, N, 3], latent [F, N, K]): every field's G-buffers at points [N, 3]."""
        rho, latent = zip(*(f.gbuffer(points) for f in self.fields), strict=True)
        return torch.stack(rho), torch.stack(latent)

    def gbuffer(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rho_d [N, 3], latent [N, K]): the fields' means at points [N, 3]."""
        rho, latent = self.each(points)
        return rho.mean(0), latent.mean(0)

    def at(self, si: SurfaceInteraction) -> NeuralMaterial:
        rho, latent = self.each(si.position)
        pick = torch.randint(0, len(self.fields), (si.position.shape[0],), device=si.position.device)
        take = pick[None, :, None] == torch.arange(len(self.fields), device=pick.device)[:, None, None]
        return NeuralMaterial(self.fields[0].basis, (rho * take).sum(0), (latent * take).sum(0))


def common_share(single_mse: list[float], mean_mse: float) -> float:
    """The share of one run's PathTrace error (clean MSE) that K runs with independent seeds have in common: with
    each run's error image c + n_k (n_k independent, variance s2), a run's MSE is c^2 + s2 and that of the mean of
    their images c^2 + s2 / K."""
    k, single = len(single_mse), sum(single_mse) / len(single_mse)
    s2 = (single - mean_mse) * k / (k - 1)
    return 1 - s2 / single


def base_colour_psnr(field: Any, truth: Any, mesh: Any) -> float:
    """BaseColor PSNR (dB) of `field` against the truth at 50k area-uniform surface points."""
    points, tri = mesh.sample_surface_faces(50_000, seed=2)
    want = truth.gbuffer(points, tri)["base_color"]
    with torch.no_grad():
        rho, _ = field.gbuffer(points)
    return float(-10 * torch.log10(((rho.clamp(0, 1) - want) ** 2).mean()))


def brief(score: dict[str, float]) -> str:
    """'PathTrace clean / relit clean / BaseColor' of a score dict, dB."""
    return (f"{score['psnr_pathtrace_clean']:.2f} / {score.get('psnr_relight_clean', math.nan):.2f} / "
            f"{score['basecolor']:.2f}")


def bench_object(object_dir: Path, work: Path, tto: TTOConfig, resolution: int = 0,
                 seeds: tuple[int, ...] = (0,)) -> dict[str, Any]:
    _, pred, cap, mesh, photos = prepared_capture(object_dir, work)
    truth = truth_field(object_dir)
    points, tri = mesh.sample_surface_faces(FIT_POINTS, seed=1)
    g = truth.gbuffer(points, tri)
    t0 = time.perf_counter()
    start, _ = fit_triplane(points, lambda p: (g["base_color"], g["latent"]), truth.basis,
                            channels=pred.triplane.channels, resolution=resolution or pred.triplane.resolution,
                            steps=FIT_STEPS)  # fmt: skip
    for module in (start.triplane, start.decoder):
        module.requires_grad_(False)
        module.zero_grad(set_to_none=True)
    fit_s = time.perf_counter() - t0
    before = {"basecolor": base_colour_psnr(start, truth, mesh), **scores(object_dir, start, mesh)}
    prediction = LMRMPrediction(start.triplane, start.decoder, pred.uncertainty_decoder, pred.pbr_decoder)
    t0 = time.perf_counter()
    runs = [solve(replace(tto, seed=seed), mesh, harness_envmap(cap), photos, cap.tonemap, prediction, load_basis(),
                  truth=None) for seed in seeds]  # fmt: skip
    tto_s = (time.perf_counter() - t0) / len(seeds)
    ends = [r.params.field() for r in runs]
    row: dict[str, Any] = {}
    end_mesh = runs[0].mesh or mesh
    each = [{"basecolor": base_colour_psnr(f, truth, mesh), **scores(object_dir, f, end_mesh)} for f in ends]
    after = each[0]
    if len(ends) > 1:
        assert all(isinstance(f, TriplaneMaterialField) for f in ends)
        torch.manual_seed(0)
        mixture = SeedMixture(ends)  # type: ignore[arg-type]
        after = {"basecolor": base_colour_psnr(mixture, truth, mesh), **scores(object_dir, mixture, end_mesh)}
        key = "psnr_pathtrace_clean_mse"
        row = {"seeds": list(seeds), "each": each, "common_share": common_share([e[key] for e in each], after[key])}
    loss = {k: after[k] - before[k] for k in before if k in after and not k.endswith("_mse")}
    what = f"the image-space mean of {len(seeds)} seeds' TTOs" if row else "the TTO"
    print(f"{object_dir.name} (PathTrace clean / relit clean / BaseColor, dB): truth distilled {brief(before)}; after "
          f"{what} {brief(after)} ({loss['psnr_pathtrace_clean']:+.2f} / "
          f"{loss.get('psnr_relight_clean', math.nan):+.2f} / {loss['basecolor']:+.2f}); fit {fit_s:.0f} s, TTO "
          f"{tto_s:.0f} s a seed", flush=True)  # fmt: skip
    if row:
        print(f"  each seed: {', '.join(brief(e) for e in each)}; the seeds share "
              f"{100 * row['common_share']:.0f}% of one run's PathTrace error", flush=True)
    return {"object": object_dir.name, "data": str(object_dir.parent), "resolution": start.triplane.resolution,
            "before": before, "after": after, "loss_db": loss, "fit_s": round(fit_s, 1),
            "tto_s": round(tto_s, 1), **row}  # fmt: skip


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--data", default="data/benchmark-test", type=Path)
    parser.add_argument("--objects", default="test-000000", help="comma-separated object ids")
    parser.add_argument("--work", default="runs/bench-tto-fixed-point", type=Path)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a TTOConfig field")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seeds", default="",
                        help="comma-separated TTO seeds (default: the TTO's own); several: also their image-space mean")
    parser.add_argument("--resolution", type=int, default=0,
                        help="texels a side of the triplane the truth is distilled into (0: the LMRM's)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    overrides = parse_overrides(args.set)
    tto = fixed_point_config(overrides)
    seeds = tuple(int(s) for s in args.seeds.split(",")) if args.seeds else (tto.seed,)
    rows = [bench_object(args.data / o, args.work / f"{o}-{args.data.name}", tto, args.resolution, seeds)
            for o in args.objects.split(",") if o.strip()]
    print(f"appended to {write_result('tto_fixed_point', {'set': overrides, 'tto': tto.to_dict(), 'rows': rows})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
