"""The benchmarks that build their own TTO from the extraction's default (bench/tto_fixed_point.py,
bench/basis_start.py) must stay valid TTO configs as the default changes (the default's held-out choice of a second
basis once made both refuse to start), and the fixed-point benchmark's image-space mean of several seeds' results
and its share of the error the seeds have in common are what their docstrings say (docs/design-notes.md, items 49,
82); bench/pbr_start.py's start reads a basis of any latent size (item 83); bench/cycles_fallback.py's refit of a kept
asset is the fallback an export with that fit makes (item 102)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Any

import pytest
import torch

from neumatex_core.fields.decoders import MaterialDecoder
from neumatex_core.fields.neural_field import TriplaneMaterialField
from neumatex_core.fields.triplane import Triplane
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.materials.neural_basis import installed_bases, load_basis
from neumatex_core.pipeline import ALTERNATIVE_BASIS, ExtractConfig

BENCH = Path(__file__).resolve().parent.parent / "bench"


def bench_module(name: str) -> Any:
    sys.path.insert(0, str(BENCH))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(BENCH))


def test_the_fixed_point_benchmarks_tto_is_the_defaults_neural_phase_free_to_leave_its_start() -> None:
    default = ExtractConfig.preset("cpu").tto_config()
    tto = bench_module("tto_fixed_point").fixed_point_config({"lr": 0.02})
    tto.check()  # raised ValueError while the default's select_basis was left on without a choice to run it in
    free = (tto.init, tto.reg, tto.lambda_consistency, tto.select_basis, tto.alternative_basis)
    assert free == ("lmrm", "none", 0.0, "", "")
    assert not (tto.select_uniform or tto.select_anchor)
    assert tto.lr == 0.02 and default.lr != 0.02
    assert (tto.steps, tto.settle_fraction, tto.train_decoder) == (default.steps, default.settle_fraction,
                                                                   default.train_decoder)


def test_the_basis_start_benchmarks_problem_is_valid_and_its_rule_has_an_alternative() -> None:
    default = ExtractConfig.preset("cpu").tto_config()
    starts = bench_module("basis_start").start_config(default)
    starts.check()
    assert (starts.init, starts.basis, starts.select_basis, starts.alternative_basis) == ("lmrm", "", "", "")
    # the default tries v6 on held-out photos and so names no alternative; the benchmark's rule column then uses
    # the one the textured and uniform variations use, which must be installed for the column to be read
    assert default.alternative_basis == "" and ALTERNATIVE_BASIS in installed_bases()


def test_the_basis_start_benchmarks_fits_are_named_and_paired_with_the_presets() -> None:
    """`--fits 500@0.2,1500@0.2` and `--bases v1,v6` parse to settings and installed ids; each fit's line pairs its
    held-out scores with the reference fit's per capture (mean and standard error of the differences) and gives its
    MSE and seconds over the reference's."""
    bench = bench_module("basis_start")
    assert bench.parse_fits("500@0.2,1500@0.2") == [(500, 0.2), (1500, 0.2)] and bench.parse_fits("") == []
    v1, v6 = bench.basis_ids("v1,v6")
    assert v1 == load_basis().basis_id and v6.split("-")[2] == "v6" and v6 in installed_bases()
    with pytest.raises(SystemExit, match="not installed"):
        bench.basis_ids("v99")
    reference, fast = bench.fit_name((1500, 0.05)), bench.fit_name((500, 0.2))
    assert (reference, fast) == ("1500@0.05", "500@0.2")

    def scores(db: float, mse: float, seconds: float) -> dict[str, float]:
        return {v1: db, f"{v1}_mse": mse, f"{v1}_s": seconds}

    rows = [{"fits": {reference: scores(20.0, 0.002, 18.0), fast: scores(21.0, 0.001, 6.0)}},
            {"fits": {reference: scores(22.0, 0.002, 18.0), fast: scores(21.0, 0.003, 6.0)}},
            {"fits": {reference: scores(24.0, 0.002, 18.0), fast: scores(27.0, 0.002, 6.0)}}]
    lines = bench.paired_fits(rows, [v1], reference)
    # differences +1, -1, +3: mean +1, standard error 2 / sqrt(3); MSE 0.002 / 0.002, seconds 6 / 18
    assert lines[2] == "| 500@0.2 | v1 | +1.00 +- 1.15 | 2/3 | 1.00 | 0.33 |", lines


def test_the_seeds_mixture_takes_each_runs_material_with_equal_odds_and_averages_their_gbuffers() -> None:
    basis = load_basis()
    fields = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        triplane = Triplane(channels=4, resolution=8, generator=torch.Generator().manual_seed(seed))
        fields.append(TriplaneMaterialField(triplane, MaterialDecoder(triplane.feature_dim,
                                                                      latent_dim=basis.arch.latent_dim), basis))
    mixture = bench_module("tto_fixed_point").SeedMixture(fields)
    n = 20_000
    points = torch.rand(n, 3, generator=torch.Generator().manual_seed(7)) * 2 - 1
    with torch.no_grad():
        (rho_a, lat_a), (rho_b, lat_b) = fields[0].gbuffer(points), fields[1].gbuffer(points)
        rho, latent = mixture.gbuffer(points)
        torch.testing.assert_close(rho, (rho_a + rho_b) / 2)
        torch.testing.assert_close(latent, (lat_a + lat_b) / 2)
        torch.manual_seed(3)
        up = torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)
        hits = SurfaceInteraction(points, up, up, torch.zeros(n, dtype=torch.int64), torch.zeros(n, 2), None, up)
        material = mixture.at(hits)
    from_a = (material.base_color == rho_a).all(-1) & (material.latent == lat_a).all(-1)
    from_b = (material.base_color == rho_b).all(-1) & (material.latent == lat_b).all(-1)
    assert bool((from_a | from_b).all())
    share = float(from_a.float().mean())
    assert abs(share - 0.5) < 4 * (0.25 / n) ** 0.5


def test_the_share_the_seeds_have_in_common_inverts_the_error_model() -> None:
    common_share = bench_module("tto_fixed_point").common_share
    c2, s2 = 3e-4, 1e-4  # each run's error c + n_k: MSE c2 + s2; the mean of K runs c2 + s2 / K
    for k in (2, 4):
        singles = [c2 + s2 * (1 + d) for d in ((-0.1, 0.1) if k == 2 else (-0.1, 0.1, -0.05, 0.05))]
        assert common_share(singles, c2 + s2 / k) == pytest.approx(c2 / (c2 + s2))
    assert common_share([2e-4, 2e-4], 1e-4) == pytest.approx(0.0)  # independent errors: halved by two seeds
    assert common_share([2e-4, 2e-4], 2e-4) == pytest.approx(1.0)  # the same error every time


def test_the_pbr_start_benchmark_reads_a_basis_of_another_latent_size_through_a_resized_decoder() -> None:
    """bench/pbr_start.py fits the LMRM's planes through its material decoder; for basis v6 (16 latent numbers,
    the LMRM's decoder gives 6) the G-buffer must have v6's size, and fitting it must leave the prediction as it
    was (it read the LMRM's 6 and failed on a size mismatch until 2026-12-05)."""
    from neumatex_core.fields.decoders import PBRDecoder, UncertaintyDecoder
    from neumatex_core.lmrm.inference import LMRMPrediction
    from neumatex_core.materials.neural_basis import BASIS_V6

    if BASIS_V6 not in installed_bases():
        pytest.skip("basis v6 is not installed")
    basis = load_basis(basis_id=BASIS_V6)
    triplane = Triplane(channels=4, resolution=8, generator=torch.Generator().manual_seed(0))
    features = 3 * triplane.channels
    pred = LMRMPrediction(triplane, MaterialDecoder(features), UncertaintyDecoder(features), PBRDecoder(features))
    before = triplane.planes.detach().clone()
    neural = bench_module("pbr_start").start_triplane(pred, basis)
    points = torch.rand(5, 3) * 2 - 1
    assert neural.gbuffer(points, None).shape == (5, 3 + basis.arch.latent_dim)
    neural.tensor.data.add_(1.0)
    assert torch.equal(triplane.planes.detach(), before)


def test_the_lmrm_benchmarks_family_table_pools_each_familys_pixels_over_objects(tmp_path: Path) -> None:
    # bench/lmrm.py's base colour by material family: each pixel's family from its region id and material.json,
    # squared errors pooled over objects, PSNR = -10 log10(MSE) and the mean colours of prediction and truth.
    from conftest import ENVMAPS, MESHES

    from neumatex_core.lmrm.data import load_synth_object, pixel_families
    from neumatex_core.materials.prior import FAMILIES
    from neumatex_core.synth import SynthConfig, generate

    lmrm_bench = bench_module("lmrm")
    out = tmp_path / "test"
    generate(SynthConfig(out=str(out), n=1, split="test", seed=5, resolution=24, spp=2, max_bounces=1, photos=0,
                         relight_maps=0, workers=1, progress=False, meshes=str(MESHES), envmaps=str(ENVMAPS)))
    folder = out / "test-000000"
    obj = load_synth_object(folder)
    names, regions = pixel_families(folder, obj.mask.shape[0])
    assert regions.shape == obj.mask.shape and set(regions[obj.mask].unique().tolist()) <= set(range(len(names)))
    # the object's per-pixel family (what the LMRM's family head learns) is its region's family
    assert [FAMILIES[int(f)] for f in obj.family[obj.mask]] == [names[int(r)] for r in regions[obj.mask]]
    table = lmrm_bench.FamilyErrors()
    truth = torch.tensor([[0.2, 0.4, 0.6], [0.2, 0.4, 0.6], [0.0, 0.0, 0.0], [0.1, 0.1, 0.1]])
    pred = torch.tensor([[0.3, 0.4, 0.6], [0.1, 0.4, 0.6], [0.0, 0.0, 0.0], [0.1, 0.1, 0.1]])
    mean = torch.tensor([0.5, 0.5, 0.5])
    table.add("plastic", pred[:2], mean, truth[:2])
    table.add("metal", pred[2:3], mean, truth[2:3])
    table.add("metal", pred[3:], mean, truth[3:])  # a second object's metal pools with the first's
    rows = table.table()
    assert rows["plastic"]["share"] == pytest.approx(0.5) and rows["metal"]["share"] == pytest.approx(0.5)
    assert rows["plastic"]["lmrm_basecolor"] == pytest.approx(-10 * torch.log10(torch.tensor(0.02 / 6)).item())
    mse_mean_metal = (0.25 * 3 + 0.16 * 3) / 6
    assert rows["metal"]["mean_basecolor"] == pytest.approx(-10 * torch.log10(torch.tensor(mse_mean_metal)).item())
    assert rows["metal"]["lmrm_basecolor"] == float("inf")  # no error at all
    assert rows["plastic"]["lmrm_mean_colour"] == pytest.approx([0.2, 0.4, 0.6])
    assert rows["metal"]["truth_mean_colour"] == pytest.approx([0.05, 0.05, 0.05])


def test_the_latent_starts_benchmarks_appearance_is_the_reflected_radiance_under_a_constant_sky() -> None:
    # bench/latent_starts.py: mean_j f(wi_j, wo) cos L / pdf over the map's samples is the integral of f cos over the
    # hemisphere under a unit sky; checked against an independent cosine-weighted estimate (E[f pi]) within 4
    # standard errors of the two Monte Carlo estimates.
    from neumatex_core.lighting.envmap import EnvironmentMap
    from neumatex_core.materials.neural_basis import NeuralMaterial

    bench = bench_module("latent_starts")
    basis = load_basis()
    g = torch.Generator().manual_seed(3)
    m = 16384
    wi, r_over_pdf = bench.environment_samples(EnvironmentMap.constant((1.0, 1.0, 1.0)), m, g)
    wo = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.9, 0.3]]), dim=-1)
    latent = torch.tensor([[0.4, -0.6, 0.5, 0.0, 0.2, 0.1], [-0.4, -0.1, -0.6, -0.5, 0.3, 0.3]])
    rho = torch.tensor([0.5, 0.3, 0.2]).expand(2, 3, 3)
    regions = bench.Regions(wo=wo.expand(2, 3, 3), wi=wi.expand(2, 3, m, 3),
                            radiance_over_pdf=r_over_pdf.expand(2, m, 3), rho=rho, latent=latent,
                            family=["coated", "fuzzy"])  # fmt: skip
    with torch.no_grad():
        got = bench.direct_appearance(basis, regions, latent)  # [2, 3, 3]
        u = torch.rand(m, 2, generator=g)
        r, phi = u[:, 0].sqrt(), 2 * torch.pi * u[:, 1]
        cos_wi = torch.stack([r * phi.cos(), r * phi.sin(), (1 - u[:, 0]).sqrt()], -1)  # pdf cos / pi
        for k in range(2):
            for p in range(3):
                material = NeuralMaterial(basis, rho[k, p].expand(m, 3), latent[k].expand(m, 6))
                ref = material.eval(cos_wi, wo[p].expand(m, 3)) * torch.pi
                inside = (wi[:, 2] > 0).unsqueeze(-1)
                fu = material.eval(wi, wo[p].expand(m, 3))
                own = torch.where(inside, fu * wi[:, 2:3].clamp_min(0) * r_over_pdf, torch.zeros_like(fu))
                se = (ref.var(0) / m + own.var(0) / m).sqrt()
                assert torch.allclose(got[k, p], own.mean(0), rtol=1e-4, atol=1e-6)  # the same samples
                assert ((got[k, p] - ref.mean(0)).abs() <= 4 * se).all(), (k, p, got[k, p], ref.mean(0), se)


def test_the_latent_starts_benchmarks_fit_reproduces_the_appearance_from_a_nearby_start() -> None:
    bench = bench_module("latent_starts")
    basis = load_basis()
    basis.requires_grad_(False)
    g = torch.Generator().manual_seed(4)
    wi = torch.nn.functional.normalize(torch.randn(32, 3, generator=g), dim=-1)
    wi[:, 2] = wi[:, 2].abs()
    wo = torch.nn.functional.normalize(torch.rand(3, 8, 3, generator=g) + torch.tensor([0.0, 0.0, 0.5]), dim=-1)
    truth = torch.tanh(torch.randn(3, 6, generator=g))
    regions = bench.Regions(wo=wo, wi=wi.expand(3, 8, 32, 3), radiance_over_pdf=torch.full((3, 32, 3), 2 * torch.pi),
                            rho=torch.rand(3, 8, 3, generator=g), latent=truth, family=["a", "b", "c"])
    with torch.no_grad():
        target = bench.direct_appearance(basis, regions, truth)
    start = (truth + 0.1).clamp(-0.95, 0.95)
    for k in range(3):
        with torch.no_grad():
            before = bench.appearance_error(basis, regions, start[k].expand(3, 6), target)[k]
        near, err = bench.fit_latents(basis, regions, target, start[k], steps=150)
        assert float(err[k]) < 0.05 * float(before), (k, err, before)  # the fit reproduces the appearance
        assert bench.latent_psnr(near[k:k + 1], truth[k:k + 1]) > bench.latent_psnr(start[k:k + 1], truth[k:k + 1])


def test_the_lmrm_swap_benchmark_pairs_each_variant_per_object_where_both_runs_finished(tmp_path: Path) -> None:
    # bench/lmrm_swap.py: candidate - shipped per variant and metric, paired per object, only on objects where both
    # evaluation folders hold every variant of the default table; and the default - PBR under each LMRM.
    import json

    swap = bench_module("lmrm_swap")
    default, pbr = swap.DEFAULT_VARIANT, swap.PBR
    shipped, candidate = tmp_path / "shipped", tmp_path / "cand"
    # per object: (PBR clean PathTrace, default clean PathTrace) in each run
    scores = {shipped: {"test-000000": (30.0, 35.0), "test-000001": (28.0, 31.0), "test-000002": (25.0, 40.0)},
              candidate: {"test-000000": (29.0, 36.0), "test-000001": (27.0, 31.5)}}
    for folder, rows in scores.items():
        for obj, (p, d) in rows.items():
            for variant, value in ((pbr, p), ("pbr_tuned_0001", p + 0.5), (default, d)):
                f = folder / "results" / obj / f"{variant}.json"
                f.parent.mkdir(parents=True, exist_ok=True)
                f.write_text(json.dumps({"psnr_pathtrace_clean": value, "psnr_basecolor": value - 10.0}))
    # a half-finished object of the candidate (no default yet) is left out
    half = candidate / "results" / "test-000002" / f"{pbr}.json"
    half.parent.mkdir(parents=True)
    half.write_text(json.dumps({"psnr_pathtrace_clean": 50.0}))
    res, objects = swap.joined(shipped, candidate)
    assert objects == ["test-000000", "test-000001"]
    figures = swap.swap_figures(res)
    d = figures[default]["psnr_pathtrace_clean"]
    assert (d["shipped"], d["candidate"], d["n"], d["ahead"]) == (33.0, 33.75, 2, 2)
    assert d["diff"] == pytest.approx(0.75) and d["se"] == pytest.approx(0.25)  # diffs 1.0, 0.5: std 0.354 / sqrt 2
    p = figures[pbr]["psnr_pathtrace_clean"]
    assert p["diff"] == pytest.approx(-1.0) and p["se"] == pytest.approx(0.0) and p["ahead"] == 0
    assert figures[default]["psnr_basecolor"]["diff"] == pytest.approx(0.75)
    gap = figures["default_minus_pbr"]["psnr_pathtrace_clean"]
    assert gap["shipped"][0] == pytest.approx(4.0) and gap["candidate"][0] == pytest.approx(5.75)
    # another variant of both folders (the paper's recipe), paired alone: no default - PBR without the two
    for folder, value in ((shipped, 20.0), (candidate, 21.5)):
        (folder / "results" / "test-000001" / "ours.json").write_text(json.dumps({"psnr_basecolor": value}))
    res, objects = swap.joined(shipped, candidate, ["ours"])
    ours = swap.swap_figures(res, ["ours"])
    assert objects == ["test-000001"] and set(ours) == {"ours"}
    assert ours["ours"]["psnr_basecolor"]["diff"] == pytest.approx(1.5)
    swap.keep(candidate, tmp_path / "kept")
    assert (tmp_path / "kept" / "cand" / "results" / "test-000001" / f"{default}.json").is_file()


def test_the_lmrm_start_benchmark_pairs_each_variant_with_the_default_across_an_lmrms_folders(tmp_path: Path) -> None:
    # bench/lmrm_start.py: each variant - the default per metric, paired per object, the objects of several folders
    # of one LMRM joined (an object in two folders counted once, from the first); the LMRM's start weights kept.
    import json

    bench = bench_module("lmrm_start")
    default, variant = bench.DEFAULT_VARIANT, bench.VARIANTS[0]
    first, second = tmp_path / "a", tmp_path / "b"
    # per object: (default clean PathTrace, variant clean PathTrace); None: not run
    scores = {first: {"test-000000": (35.0, 34.0), "test-000001": (31.0, None)},
              second: {"test-000002": (30.0, 32.0), "test-000000": (99.0, 99.0)}}
    for folder, rows in scores.items():
        for obj, values in rows.items():
            for name, value in zip((default, variant), values, strict=True):
                if value is None:
                    continue
                f = folder / "results" / obj / f"{name}.json"
                f.parent.mkdir(parents=True, exist_ok=True)
                f.write_text(json.dumps({"psnr_pathtrace_clean": value, "psnr_basecolor": value - 10.0,
                                         "choice_lmrm_start_weight_rho": 0.5, "choice_lmrm_start_weight_latent": 0.25}))
    res, weights = bench.joined([first, second], [variant])
    figures = bench.figures(res, [variant])
    d = figures[variant]["psnr_pathtrace_clean"]
    assert (d["default"], d["variant"], d["n"], d["ahead"]) == (32.5, 33.0, 2, 1)
    assert d["diff"] == pytest.approx(0.5) and d["se"] == pytest.approx(1.5)  # diffs -1, +2: std 2.12 / sqrt 2
    assert figures[variant]["psnr_basecolor"]["diff"] == pytest.approx(0.5)
    assert weights[variant] == {"test-000000": [0.5, 0.25], "test-000002": [0.5, 0.25]}


def test_the_lmrm_ship_benchmark_pairs_the_new_extraction_with_todays_across_sides(tmp_path: Path) -> None:
    # bench/lmrm_ship.py: the new extraction's default (default_lmrm_start_full) - today's default, its PBR baseline -
    # today's, and each side's default - its own PBR baseline, paired per object over the objects both sides have.
    import json

    bench = bench_module("lmrm_ship")

    held = {bench.NEW: {"test-000000": 25.0, "test-000001": 20.0, "test-000002": 22.0},  # best held-out PSNR
            bench.DEFAULT_VARIANT: {"test-000000": 24.0, "test-000001": 21.0, "test-000002": 22.0}}

    def write(folder: Path, obj: str, variant: str, clean: float) -> None:
        f = folder / "results" / obj / f"{variant}.json"
        f.parent.mkdir(parents=True, exist_ok=True)
        rec = {"psnr_pathtrace_clean": clean, "psnr_relight_clean": clean - 5.0}
        if obj in held.get(variant, {}):  # the textured candidate's, below the uniform one's
            rec |= {"choice_validation_psnr_uniform": held[variant][obj], "choice_validation_psnr_textured": 1.0}
        f.write_text(json.dumps(rec))

    new_a, new_b, product = tmp_path / "a", tmp_path / "b", tmp_path / "product"
    for obj, (new, new_pbr) in {"test-000000": (34.0, 30.0), "test-000001": (33.0, 28.0)}.items():
        write(new_a, obj, bench.NEW, new)
        write(new_a, obj, "pbr", new_pbr)
    write(new_b, "test-000002", bench.NEW, 31.0)
    write(new_b, "test-000002", "pbr", 29.0)
    write(new_b, "test-000001", bench.NEW, 99.0)  # also in the first folder, which gives it
    write(new_b, "test-000001", "pbr", 99.0)
    write(new_b, "test-000003", bench.NEW, 99.0)  # no PBR baseline: not counted
    for obj, (default, pbr) in {"test-000000": (35.0, 30.0), "test-000001": (31.0, 27.0),
                                "test-000002": (32.0, 29.0), "test-000003": (30.0, 20.0)}.items():
        write(product, obj, bench.DEFAULT_VARIANT, default)
        write(product, obj, "pbr", pbr)
    res = bench.joined([new_a, new_b], [product])
    res = bench.chosen(res, bench.held_out([new_a, new_b], bench.NEW), bench.held_out([product], bench.DEFAULT_VARIANT))
    figs = bench.figures(res)
    d = figs["default"]["psnr_pathtrace_clean"]  # new - product: -1, +2, -1
    assert (d["n"], d["ahead"], d["new"], d["product"]) == (3, 1, pytest.approx(98 / 3), pytest.approx(98 / 3))
    assert d["diff"] == pytest.approx(0.0) and d["se"] == pytest.approx(1.0)  # std 1.732 / sqrt 3
    assert figs["pbr"]["psnr_pathtrace_clean"]["diff"] == pytest.approx(1 / 3)  # 0, +1, 0
    gap = figs["default_minus_pbr"]["psnr_relight_clean"]  # 4, 5, 2 against 5, 4, 3
    assert gap["new"]["diff"] == pytest.approx(11 / 3) and gap["product"]["diff"] == pytest.approx(4.0)
    assert gap["product"]["n"] == 3  # test-000003, which the new side lacks, is left out of today's too
    # chosen on held-out photos: the new default where it scored higher (test-000000), else today's (a tie too)
    c = figs["chosen"]["psnr_pathtrace_clean"]
    assert (c["n"], c["chosen"], c["diff"]) == (3, pytest.approx(97 / 3), pytest.approx(-1 / 3))
    # --keep into a folder that is itself read (the kept results joined with a new run's) copies the others' objects
    argv = sys.argv
    try:
        sys.argv = ["lmrm_ship.py", f"{new_a}+{new_b}", "--product", str(product), "--keep", str(new_a), "--no-record"]
        assert bench.main() == 0
    finally:
        sys.argv = argv
    assert (new_a / "results" / "test-000002" / f"{bench.NEW}.json").is_file()
    # another variant (--variant): its rows, and its held-out scores from the LMRM's sides too (select_lmrm_start)
    choose = tmp_path / "choose" / "results" / "test-000000"
    choose.mkdir(parents=True)
    (choose / "pbr.json").write_text(json.dumps({"psnr_pathtrace_clean": 30.0, "psnr_relight_clean": 25.0}))
    (choose / "default_choose_lmrm_start.json").write_text(json.dumps(
        {"psnr_pathtrace_clean": 36.0, "psnr_relight_clean": 31.0, "choice_validation_psnr_uniform": 23.0,
         "choice_select_basis_lmrm_psnr_textured": 26.0}))  # fmt: skip
    assert bench.held_out([choose.parents[1]], "default_choose_lmrm_start") == {"test-000000": 26.0}
    res = bench.joined([choose.parents[1]], [product], "default_choose_lmrm_start")
    assert bench.figures(res)["default"]["psnr_pathtrace_clean"]["diff"] == pytest.approx(1.0)  # 36 - 35
    # --margins: the choice had the LMRM's start needed to win by a margin. Object 0 took the LMRM's start (26 > 23:
    # gap 3); object 1 took the PBR start (gap -1); each side the choice did not take comes from its plain run
    def result(obj: str, name: str, clean: float, **held: float) -> None:
        f = tmp_path / "choose" / "results" / obj / f"{name}.json"
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(json.dumps({"psnr_pathtrace_clean": clean, **{f"choice_{k}": v for k, v in held.items()}}))

    result("test-000000", bench.DEFAULT_VARIANT, 33.0)  # the PBR start's result there
    result("test-000001", "default_choose_lmrm_start", 30.0, validation_psnr_uniform=24.0,
           select_lmrm_psnr_textured=23.0)  # fmt: skip
    result("test-000001", bench.NEW, 35.0)  # the LMRM's start's result there
    result("test-000002", "default_choose_lmrm_start", 30.0, validation_psnr_uniform=24.0,
           select_lmrm_psnr_textured=25.0)  # fmt: skip
    sides = bench.sides_of([choose.parents[1]], "default_choose_lmrm_start")
    assert set(sides) == {"test-000000", "test-000001"}  # object 2 lacks the PBR start's plain run
    assert sides["test-000000"]["gap"] == pytest.approx(3.0) and sides["test-000001"]["gap"] == pytest.approx(-1.0)
    result("test-000003", bench.DEFAULT_VARIANT, 31.0)  # no choice ran there: the PBR start alone is its plain run
    margins = bench.with_margins({}, sides, [0.0, 5.0], [choose.parents[1]])
    assert margins["margin 0"]["psnr_pathtrace_clean"] == {"test-000000": 36.0, "test-000001": 30.0}
    assert margins["margin 5"]["psnr_pathtrace_clean"] == {"test-000000": 33.0, "test-000001": 30.0}
    assert margins["pbr_start"]["psnr_pathtrace_clean"] == {"test-000000": 33.0, "test-000001": 30.0,
                                                            "test-000003": 31.0}
    assert margins["lmrm_start"]["psnr_pathtrace_clean"] == {"test-000000": 36.0, "test-000001": 35.0}
    assert bench.with_margins({}, sides, [])["pbr_start"]["psnr_pathtrace_clean"] == {"test-000000": 33.0,
                                                                                       "test-000001": 30.0}


def test_the_cycles_benchmark_keeps_another_lmrms_scores_apart_and_pairs_them_with_the_shipped_ones(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    # bench/cycles_extract.py --lmrm-weights: each variant is paired per capture with its latest scores under the
    # shipped LMRM, the default ("neural") read from its two bases' sides as bench/basis_choice.py reads it; a work
    # folder whose stages hold another LMRM's prediction is refused; --stored is the shipped LMRM's.
    import json

    cycles = bench_module("cycles_extract")
    choice = bench_module("basis_choice")
    monkeypatch.setattr(choice, "RESULTS_DIR", tmp_path)
    own, other = bench_module("variants_clean").basis_sides(cycles.DEFAULT_VARIANT)

    def scores(photos: float, relit: float, held_out: float | None = None) -> dict[str, Any]:
        picked = {"selection": {"uniform_kept": 0.0, "validation_photos": 4.0, "validation_psnr_uniform": 0.0,
                                "validation_psnr_textured": held_out}} if held_out is not None else {}
        return {"photos_clean_db": photos, "relit_clean_db": relit, **picked}

    # capture a: the other basis wins on held-out photos by 1 dB, so the default is its scores; capture b: no sides
    rows = [{"capture": "a", "preset": "coat", "pbr": scores(25.0, 24.0), own: scores(30.0, 28.0, 20.0),
             other: scores(31.0, 29.5, 21.0)},
            {"capture": "b", "preset": "coat", "pbr": scores(26.0, 25.0)}]
    (tmp_path / "cycles_extract.jsonl").write_text(json.dumps({"rows": rows}) + "\n")
    shipped = cycles.shipped_scores()
    assert shipped["a"]["neural"] == {"photos_clean_db": 31.0, "relit_clean_db": 29.5}
    assert shipped["b"]["pbr"]["relit_clean_db"] == 25.0 and "neural" not in shipped["b"]
    # the candidate's rows, paired with the shipped LMRM's per capture under SHIPPED
    ours = [{"capture": c, "preset": "coat", "neural": scores(p, r), "pbr": scores(p - 5, r - 5)}
            for c, p, r in (("a", 31.5, 29.0), ("c", 40.0, 40.0))]
    tables = cycles.against_shipped(ours, ["pbr", "neural"], shipped)
    assert tables[f"pbr against {cycles.SHIPPED}"]["coat"]["captures"] == ["a"]  # b has no candidate row, c no pair
    assert tables[f"pbr against {cycles.SHIPPED}"]["coat"]["relit_clean_db"]["diff"] == pytest.approx(0.0)
    table = tables[f"neural against {cycles.SHIPPED}"]["coat"]
    assert table["captures"] == ["a"]
    assert table["photos_clean_db"]["diff"] == pytest.approx(0.5)
    assert table["relit_clean_db"]["diff"] == pytest.approx(-0.5)
    assert f"neural against {cycles.SHIPPED}" in capsys.readouterr().out
    assert cycles.by_preset(ours)["coat"]["relit_clean_db"]["diff"] == pytest.approx(5.0)  # against pbr as before
    # a work folder scored with the shipped LMRM is refused to a candidate, and the other way round
    cand = {"lmrm_weights": "cand.safetensors", "lmrm_readout": "shipped"}
    kept = tmp_path / "work" / "a" / "scores.json"
    kept.parent.mkdir(parents=True)
    args = ["cycles_extract.py", "--work", str(tmp_path / "work"), str(tmp_path / "a")]
    for extra, kept_row in (([], {**rows[0], "lmrm": cand}),
                            (["--lmrm-weights", "cand.safetensors", "--lmrm-readout", "shipped"], rows[0])):
        kept.write_text(json.dumps(kept_row))
        monkeypatch.setattr(sys, "argv", args[:1] + extra + args[1:])
        with pytest.raises(SystemExit) as stop:
            cycles.main()
        assert stop.value.code == 2 and "give another --work" in capsys.readouterr().err
    monkeypatch.setattr(sys, "argv", args[:1] + ["--stored", "--lmrm-weights", "x"] + args[1:])
    with pytest.raises(SystemExit):
        cycles.main()
    assert "--stored pairs with the shipped LMRM" in capsys.readouterr().err


def test_the_fallback_benchmarks_refit_of_a_kept_asset_is_the_fallback_that_fit_exports(tmp_path: Path) -> None:
    """bench/cycles_fallback.py scores a fit variant by fitting the kept asset's baked textures again (`refit`), so
    that a new variant needs no TTO: that must be the fallback an export with that fit makes, bit for bit, also after
    the asset was kept with torch.save."""
    from asset_fixtures import make_asset
    from conftest import MESHES

    from neumatex_core.assets.pbr_fit import PBRFitConfig
    from neumatex_core.geometry.mesh import load_mesh

    refit = bench_module("cycles_fallback").refit
    mesh, basis = load_mesh(MESHES / "suzanne.obj").normalized(), load_basis()
    sparse = PBRFitConfig(cosine_directions=6, albedo="split_sum")
    shipped = make_asset(mesh, basis, resolution=32, steps=20)
    torch.save(shipped, tmp_path / "asset.pt")
    kept = torch.load(tmp_path / "asset.pt", weights_only=False)
    exported = make_asset(mesh, basis, resolution=32, steps=20, pbr=sparse)
    again = refit(kept, sparse)
    assert torch.equal(again.pbr_texture, exported.pbr_texture)
    assert again.pbr_fit_loss == exported.pbr_fit_loss
    assert not torch.equal(again.pbr_texture, shipped.pbr_texture)  # the two fits differ, so the test can fail
    assert torch.equal(again.material_texture, shipped.material_texture)
