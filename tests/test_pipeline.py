"""The extraction pipeline: idempotent stages, resume after an interruption without re-running finished stages,
clear errors for bad captures, and `neumatex extract` end to end (tiny preset on the bundled example capture)."""

from __future__ import annotations

import json
import math
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from tto_fixtures import EXAMPLE

from neumatex_core.assets import read_asset
from neumatex_core.cli import main
from neumatex_core.imageio import read_image
from neumatex_core.lmrm import LMRMConfig, LMRMNet, save_lmrm
from neumatex_core.materials.neural_basis import BASIS_V2, BASIS_V4, BASIS_V6, basis_latent_dim, load_basis
from neumatex_core.pipeline import (
    STAGES,
    Cancelled,
    ExtractConfig,
    PipelineError,
    StageProgress,
    default_work,
    extract,
    read_done,
    run_stage,
    stage_dir,
)
from neumatex_core.tto.fallback_choice import PBR_PHASE_METHOD

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def tiny_lmrm(tmp_path_factory) -> Path:
    """A small, untrained LMRM checkpoint (the pipeline path of a trained one without depending on the shipped)."""
    folder = tmp_path_factory.mktemp("lmrm")
    torch.manual_seed(0)
    net = LMRMNet(LMRMConfig(view_resolution=32, view_channels=8, view_layers=1, feature_channels=8,
                             plane_resolution=16, plane_channels=8, triplane_channels=8, decoder_hidden=16))
    save_lmrm(net, folder / "lmrm.safetensors", folder / "lmrm.json", load_basis(), {"note": "test"})
    return folder / "lmrm.safetensors"


def config(lmrm: Path, **kw) -> ExtractConfig:
    return ExtractConfig.preset("tiny", lmrm_weights=str(lmrm), device="cpu", **kw)


def done_times(work: Path) -> dict[str, int]:
    return {s: (stage_dir(work, s) / "done.json").stat().st_mtime_ns for s in STAGES
            if (stage_dir(work, s) / "done.json").is_file()}  # fmt: skip


def test_stages_are_idempotent_and_resume_after_an_interruption(tmp_path, tiny_lmrm):
    work, out = tmp_path / "work", tmp_path / "asset"
    cfg = config(tiny_lmrm, init="lmrm")  # one TTO phase (init "pbr" runs two: tests/test_tto.py)
    assert ExtractConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg  # what a task message carries
    metrics = run_stage("validate", EXAMPLE, work, cfg)
    assert metrics["frames"] == 23 and metrics["faces"] > 0
    before = done_times(work)
    assert run_stage("validate", EXAMPLE, work, cfg) == metrics  # stored metrics, not re-run
    assert done_times(work) == before
    # A later stage refuses to run before its inputs exist.
    with pytest.raises(PipelineError, match="prepare_views"):
        run_stage("lmrm", EXAMPLE, work, cfg)
    # Interrupt the TTO after 5 steps.
    seen: list[StageProgress] = []

    def progress(p: StageProgress) -> None:
        seen.append(p)

    def stop() -> bool:
        return any(p.stage == "tto" and p.metrics.get("step", 0) >= 5 for p in seen)

    with pytest.raises(Cancelled):
        extract(EXAMPLE, out, cfg, progress, stop, work)
    assert set(done_times(work)) == {"validate", "prepare_views", "lmrm"}
    assert (stage_dir(work, "tto") / "checkpoint.pt").is_file() and not out.exists()
    assert all(0.0 <= p.fraction <= 1.0 for p in seen)
    finished = done_times(work)
    again: list[StageProgress] = []
    path = extract(EXAMPLE, out, cfg, again.append, None, work)
    assert path == out
    assert {s: done_times(work)[s] for s in finished} == finished  # finished stages were not re-run
    assert {p.stage for p in again} == {"tto", "export"}
    steps = [int(p.metrics["step"]) for p in again if p.stage == "tto" and "step" in p.metrics]
    assert steps[0] == 6 and steps[-1] == cfg.tto.steps  # resumed after step 5, not from the start
    history = json.loads((stage_dir(work, "tto") / "history.json").read_text())
    assert [int(r["step"]) for r in history] == list(range(1, cfg.tto.steps + 1))
    lmrm = json.loads((stage_dir(work, "lmrm") / "prediction.json").read_text())
    assert lmrm["trained"] and lmrm["source"] == "lmrm"
    asset = read_asset(out)
    assert asset.field_kind == "triplane" and set(asset.decoders) == {"material", "uncertainty", "pbr"}
    assert asset.metrics["tto_steps"] == cfg.tto.steps and "psnr_photos" in asset.metrics
    page = (out / "report" / "index.html").read_text()
    assert (out / "report" / "curves.png").is_file()
    # every G-buffer tile under its own caption, its PNG beside the page
    for caption in ("view 0 ours base colour", "view 0 LMRM base colour", "view 4 LMRM std, mean over channels"):
        assert f"<figcaption>{caption}" in page, caption
    for src in re.findall(r"<img src='([^']+)'", page):
        assert (out / "report" / src).is_file(), src


@pytest.mark.parametrize("basis_id", [BASIS_V2, BASIS_V6], ids=["v2", "v6-16-latents"])
def test_extraction_in_another_installed_basis_writes_an_asset_that_names_it(tmp_path, tiny_lmrm, basis_id):
    """TTOConfig.basis: the neural TTO from the PBR solution in basis v2 (6 latents), or in v6 (16 latents, the
    material decoder resized and fine-tuned); the asset names the basis, holds its latent size and reads back in it.
    A start or anchor from the LMRM (whose latents are the default basis's) is refused with the reason."""
    from neumatex_core.tto.config import TTOConfig

    k = basis_latent_dim(basis_id)
    tto = TTOConfig.preset("tiny", steps=4, pbr_steps=4, reg="none", basis=basis_id, train_decoder=k != 6,
                           decoder_in_other_basis=k != 6)
    with pytest.raises(ValueError, match="another basis needs init 'pbr' or 'random'"):
        config(tiny_lmrm, init="lmrm", tto=tto).check()
    out = extract(EXAMPLE / "photos", tmp_path / "asset", config(tiny_lmrm, init="pbr", tto=tto))
    asset = read_asset(out)
    assert asset.basis.basis_id == basis_id != load_basis().basis_id
    assert asset.material_texture.shape[-1] == 3 + k and asset.decoders["material"].latent_dim == k
    assert torch.isfinite(asset.material_texture).all() and torch.isfinite(asset.pbr_texture).all()


def test_the_basis_the_tto_chose_is_the_assets_and_the_report_says_why(tmp_path, tiny_lmrm):
    """TTOConfig.alternative_basis (every preset: basis v4): where the TTO takes it (forced here by a negative
    margin), the tto stage records it, the asset is exported in it and the report gives the scores that chose it;
    where it keeps the configured basis the report says so too. Without the PBR start there is nothing to choose."""

    preset = config(tiny_lmrm, init="pbr", variation="textured")
    assert preset.tto_config().alternative_basis == BASIS_V4
    assert config(tiny_lmrm, init="random").tto_config().alternative_basis == ""
    forced = replace(preset, tto=replace(preset.tto, basis_margin_db=-100.0))
    out = extract(EXAMPLE, tmp_path / "asset", forced)
    tto = read_done(default_work(out), "tto")
    assert tto["basis"] == BASIS_V4 and tto["basis_switched"] == 1.0
    assert read_asset(out).basis.basis_id == BASIS_V4
    page = (out / "report" / "index.html").read_text()
    assert f"neural basis {BASIS_V4}, chosen because the PBR solution (" in page
    kept = extract(EXAMPLE, tmp_path / "kept", replace(preset, tto=replace(preset.tto, basis_margin_db=100.0)))
    assert read_done(default_work(kept), "tto")["basis"] == load_basis().basis_id == read_asset(kept).basis.basis_id
    assert f"neural basis {load_basis().basis_id} (the PBR solution " in (kept / "report" / "index.html").read_text()


def test_the_variation_sets_the_consistency_term_and_the_report_names_the_choice(tmp_path, tiny_lmrm, capsys):
    """ExtractConfig.variation: "textured" is the presets' TTO config, "uniform" adds the base colours' values to
    the consistency term, "choose" (the default) makes the TTO pick one on held-out photos, and the report says
    which it chose and why. "uniform" needs the PBR start: with another init it is refused (by `neumatex extract`
    too), not ignored; "choose" is then "textured", and the report says so."""
    from neumatex_core.tto.config import UNIFORM_RHO_VALUE

    base = config(tiny_lmrm, init="pbr", variation="textured")
    assert base.tto_config().consistency_rho_value == 0.0 and not base.tto_config().select_uniform
    uniform = config(tiny_lmrm, init="pbr", variation="uniform").tto_config()
    assert uniform == replace(base.tto_config(), consistency_rho_value=UNIFORM_RHO_VALUE)
    choose = config(tiny_lmrm, init="pbr", variation="choose")
    assert choose.tto_config() == replace(base.tto_config(), select_uniform=True, select_reuse_start=True,
                                          select_basis=BASIS_V6,  # v6 tried in the choice (design note 80)
                                          alternative_basis="")  # in its place for v1's start (note 81)
    for tto, alternative in ((replace(choose.tto, alternative_basis=BASIS_V2), BASIS_V2),  # named: kept beside v6
                             (replace(choose.tto, select_basis=""), BASIS_V4)):  # v6 not tried: v4 for the start
        assert config(tiny_lmrm, init="pbr", tto=tto).tto_config().alternative_basis == alternative
    assert base.tto_config().select_basis == ""  # no choice, so the configured basis alone
    assert config(tiny_lmrm, init="pbr") == choose  # the default
    for init in ("random", "lmrm"):
        with pytest.raises(ValueError, match="variation='uniform'"):
            config(tiny_lmrm, init=init, variation="uniform").check()
        lenient = config(tiny_lmrm, init=init)
        lenient.check()
        assert lenient.tto_config() == config(tiny_lmrm, init=init, variation="textured").tto_config()
    assert main(["extract", str(EXAMPLE / "photos"), "--out", str(tmp_path / "x"), "--preset", "tiny", "--init",
                 "random", "--variation", "uniform", "--no-progress"]) == 2  # fmt: skip
    assert "variation='uniform'" in capsys.readouterr().err and not (tmp_path / "x").exists()

    seen: list[StageProgress] = []
    out = extract(EXAMPLE, tmp_path / "asset", choose, seen.append)
    total = choose.tto_config().run_steps()  # the choice's steps, then the TTO's: one progress bar
    steps = [round(p.fraction * total) for p in seen if p.stage == "tto" and "step" in p.metrics]
    assert steps == list(range(1, total + 1))
    tto = read_done(default_work(out), "tto")
    assert tto["variation"] == "choose" and tto["uniform_kept"] in (0.0, 1.0) and tto["validation_photos"] == 4
    assert tto["select_basis_taken"] in (0.0, 1.0)  # basis v6's candidates were scored too (design note 80)
    page = (out / "report" / "index.html").read_text()
    # the PBR fallback chosen on the same held-out photos between the fit and the TTO's PBR phase (stored beside
    # the result), and the report says which and why
    asset = read_asset(out)
    assert (stage_dir(default_work(out), "tto") / "pbr_solution.safetensors").is_file()
    from_phase = asset.metrics["fallback_from_pbr_phase"] == 1.0
    assert from_phase == (asset.metrics["fallback_psnr_pbr_phase"] > asset.metrics["fallback_psnr_fit"])
    assert (asset.pbr_method == PBR_PHASE_METHOD) == from_phase and math.isfinite(asset.pbr_fit_loss)
    kept = "the TTO&#x27;s PBR phase" if from_phase else "the fit to the neural material"
    assert f"PBR fallback: {kept} (the fit to the neural material {asset.metrics['fallback_psnr_fit']:.2f} dB" in page
    if tto["select_basis_taken"]:
        chosen = "uniform" if tto["select_basis_uniform_kept"] else "textured"
        assert f"material variation choose ({chosen} in this basis chosen on 4 held-out photos: uniform " in page
    else:
        chosen = "uniform" if tto["uniform_kept"] else "textured"
        assert f"material variation choose ({chosen} chosen on 4 held-out photos: uniform " in page
        assert "in the other basis tried uniform" in page


def test_the_report_says_which_basis_the_choice_on_held_out_photos_took():
    """With TTOConfig.select_basis the report names the candidate and basis kept, both bases' held-out scores, and
    why the asset's basis is the one it is (design note 80)."""
    from neumatex_core.pipeline import _basis_note, _choice_note

    metrics = {"validation_photos": 4.0, "uniform_kept": 1.0, "validation_psnr_uniform": 25.66,
               "validation_psnr_textured": 25.62, "select_basis_psnr_uniform": 26.60,
               "select_basis_psnr_textured": 26.68, "select_basis_uniform_kept": 0.0, "select_basis_taken": 1.0,
               "basis": BASIS_V6, "basis_pbr_psnr": 24.20, "basis_start_psnr": 20.56,
               "basis_alternative_psnr": 23.68, "basis_switched": 1.0}  # fmt: skip
    assert _choice_note(metrics) == (" (textured in this basis chosen on 4 held-out photos: uniform 26.60 dB, textured "
                                     "26.68 dB; in the configured basis uniform 25.66 dB, textured 25.62 dB)")
    assert _basis_note(metrics) == (f"; neural basis {BASIS_V6}, taken because its candidates reproduced the held-out "
                                    "photos better (the PBR solution 24.20 dB on the scoring photos, its start in the "
                                    "configured basis 20.56 dB, in the alternative 23.68 dB)")
    kept = {**metrics, "select_basis_psnr_uniform": 25.10, "select_basis_psnr_textured": 25.20,
            "select_basis_taken": 0.0, "basis": "nmx-basis-v4-2b82d9690606"}  # v6's candidates scored worse
    assert _choice_note(kept) == (" (uniform chosen on 4 held-out photos: uniform 25.66 dB, textured 25.62 dB; in the "
                                  "other basis tried uniform 25.10 dB, textured 25.20 dB)")
    assert _basis_note(kept).startswith("; neural basis nmx-basis-v4-2b82d9690606, chosen because the PBR solution")


def test_bad_capture_raises_a_pipeline_error_naming_the_file(tmp_path, tiny_lmrm):
    capture = tmp_path / "capture"
    shutil.copytree(EXAMPLE, capture, ignore=shutil.ignore_patterns("photos", "gbuffers"))
    (capture / "images" / "003.png").write_bytes(b"not a png")
    with pytest.raises(PipelineError, match=r"images/003\.png"):
        run_stage("validate", capture, tmp_path / "work", config(tiny_lmrm))
    assert not (stage_dir(tmp_path / "work", "validate") / "done.json").exists()
    with pytest.raises(PipelineError, match="not found"):
        run_stage("validate", tmp_path / "missing", tmp_path / "work2", config(tiny_lmrm))


def test_lmrm_init_without_a_checkpoint_fails_clearly(tmp_path):
    cfg = ExtractConfig.preset("tiny", lmrm_weights=str(tmp_path / "none.safetensors"), init="lmrm", device="cpu")
    work = tmp_path / "work"
    for stage in ("validate", "prepare_views"):
        run_stage(stage, EXAMPLE / "photos", work, cfg)
    with pytest.raises(PipelineError, match="init='random'"):
        run_stage("lmrm", EXAMPLE / "photos", work, cfg)


def test_cli_extract_end_to_end_from_photos(tmp_path, capsys):
    out = tmp_path / "asset"
    # The photos/ capture has 6 photos at random poses: the preset views are blended (lumigraph).
    # With the progress bars (stderr).
    code = main(["extract", str(EXAMPLE / "photos"), "--out", str(out), "--preset", "tiny", "--init", "random",
                 "--device", "cpu"])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "wrote" in captured.out and "tto" in captured.err and "export" in captured.err
    asset = read_asset(out)
    assert asset.mesh.num_faces > 0 and asset.material_texture.shape[-1] == 9
    views = json.loads((tmp_path / ".asset.work" / "prepare_views" / "views.json").read_text())
    assert views["source"].startswith("blended from 6 photos")
    page = (out / "report" / "index.html").read_text()
    assert page.count("<img") >= 3
    assert "material variation choose (textured: without the PBR start there is nothing to choose from)" in page
    # Rerunning is a no-op resume; a bad capture is an error message and exit code 2, not a traceback.
    assert main(["extract", str(EXAMPLE / "photos"), "--out", str(out), "--preset", "tiny", "--init", "random",
                 "--no-progress"]) == 0  # fmt: skip
    assert main(["extract", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x"), "--preset", "tiny",
                 "--no-progress"]) == 2  # fmt: skip
    assert "nowhere" in capsys.readouterr().err


def test_evaluate_variant_scores_a_synthetic_object(tmp_path, tiny_lmrm):
    from neumatex_core.eval import gbuffer_psnr, ground_truth
    from neumatex_core.eval.harness import evaluate_variant
    from neumatex_core.pipeline import load_prediction

    cfg = config(tiny_lmrm)
    work = tmp_path / "work"
    base = evaluate_variant(EXAMPLE, work, "t3a_no_tto", cfg, render_views=(0,), render_spp=2)
    pred, _ = load_prediction(work)
    direct = gbuffer_psnr(lambda p: torch.cat(pred.material_decoder(pred.triplane.features(p)), -1),
                          ground_truth(EXAMPLE))  # fmt: skip
    assert base["psnr_basecolor"] == pytest.approx(direct["psnr_basecolor"], abs=1e-6)
    assert base["tto_cpu_minutes"] < 0.01
    ours = evaluate_variant(EXAMPLE, work, "ours", cfg, render_views=(0,), render_spp=2)
    assert set(ours) == {"psnr_basecolor", "psnr_latents", "psnr_pathtrace", "tto_minutes", "tto_cpu_minutes"}
    assert all(math.isfinite(v) for v in ours.values()) and ours["tto_minutes"] > 0
    assert ours["psnr_basecolor"] != base["psnr_basecolor"]  # the TTO moved the material
    # a result in another basis (here basis v4) is scored against the truth's latents in that basis
    in_v4 = evaluate_variant(EXAMPLE, work, "pbr_start_v4", cfg, render_views=(0,), render_spp=2)
    assert math.isfinite(in_v4["psnr_latents"]) and math.isfinite(in_v4["psnr_basecolor"])
    # ... and its figures drawn, whatever the basis's latent size (v6: 16 numbers; the first three are shown)
    figures = tmp_path / "figures"
    in_v6 = evaluate_variant(EXAMPLE, work, "default_v6", cfg, render_views=(0,), render_spp=2, figure_dir=figures)
    assert math.isfinite(in_v6["psnr_latents"])
    sizes = {read_image(figures / f"{name}.png").shape for name in ("render", "basecolor", "latent")}
    assert len(sizes) == 1 and next(iter(sizes))[2] == 3  # three RGB pictures of the same frame
    with pytest.raises(ValueError, match="unknown variant"):
        evaluate_variant(EXAMPLE, work, "nope", cfg)


def test_the_truths_latents_in_another_basis_encode_each_regions_parameters():
    """ground_truth(basis=...): a synthetic object's latents in a basis other than the one it was made in (here v6,
    16 latents) are that basis's encoding of each pixel's region's layered parameters, as the stored ones are the
    shipped basis's encoding of the same parameters; the base colour is unchanged."""
    from neumatex_core.eval import ground_truth
    from neumatex_core.materials.layered import PARAMETER_NAMES

    v1, v6 = load_basis(), load_basis("cpu", BASIS_V6)
    stored, in_v6 = ground_truth(EXAMPLE, [0, 5]), ground_truth(EXAMPLE, [0, 5], v6)
    assert in_v6.values.shape == (stored.values.shape[0], 3 + 16)
    assert torch.equal(in_v6.values[:, :3], stored.values[:, :3]) and torch.equal(in_v6.points, stored.points)
    regions = json.loads((EXAMPLE / "material.json").read_text())["regions"]
    params = torch.tensor([[r["params"][name] for name in PARAMETER_NAMES] for r in regions])
    with torch.no_grad():
        enc1, enc6 = v1.encode(params), v6.encode(params)
    # each pixel's region, from its stored latent (the shipped basis's encoding of its region's parameters)
    region = torch.cdist(stored.values[:, 3:], enc1).argmin(1)
    assert torch.allclose(stored.values[:, 3:], enc1[region], atol=1e-6) and len(region.unique()) == len(regions) > 1
    assert torch.equal(in_v6.values[:, 3:], enc6[region])
    assert torch.equal(ground_truth(EXAMPLE, [0, 5], v1).values, stored.values)  # its own basis: the stored buffers


def test_a_pbr_result_is_scored_on_its_lambertian_base_colour():
    """The truth's BaseColor is rho_d, black under a metal; a PBR point's base colour is F0 where metallic is 1, so
    PBR is scored on its rho_d in the layered model (pbr_to_neural), not on its base colour."""
    from neumatex_core.eval.harness import pbr_base_colour
    from neumatex_core.materials.neural_basis import load_basis

    gold, plastic = [0.9, 0.7, 0.3, 0.3, 1.0], [0.6, 0.3, 0.2, 0.5, 0.0]  # base rgb, roughness, metallic
    out = pbr_base_colour(torch.tensor([gold, plastic]), load_basis())
    assert out.shape == (2, 9) and torch.isnan(out[:, 3:]).all()
    assert out[0, :3].abs().max() < 1e-6  # a metal has no Lambertian base
    # a dielectric's base colour, raised by the specular layer's transmission (0.9-1): the same hue
    ratio = out[1, :3] / torch.tensor([0.6, 0.3, 0.2])
    assert ratio.min() >= 1.0 and ratio.max() <= 1.12 and ratio.max() - ratio.min() < 1e-3


def test_eval_suite_scores_tables_resumes_and_writes_the_results_page(tmp_path, tiny_lmrm):
    from neumatex_core.eval.suite import EvalConfig, distinct_variants, run_eval

    data = tmp_path / "split"
    shutil.copytree(EXAMPLE, data / "test-000000")
    doc = tmp_path / "docs" / "results.md"
    cfg = EvalConfig(data=str(data), out=str(tmp_path / "eval"), tables="table1,table3", preset="tiny",
                     render_views=1, relight_views="", device="cpu", lmrm_weights=str(tiny_lmrm), doc=str(doc),
                     figures=1, progress=False, record=str(tmp_path / "eval.jsonl"))  # fmt: skip
    canon = distinct_variants(["table1", "table3"])
    assert canon["t3c_unc"] == "ours" and canon["ours"] == "ours"  # identical settings run once
    seen: list[tuple[int, int]] = []
    result = run_eval(cfg, lambda done, total, last: seen.append((done, total)))
    assert result["complete"] and result["objects"] == 1
    runs = sorted(p.stem for p in (tmp_path / "eval" / "results" / "test-000000").glob("*.json"))
    assert runs == sorted({"pbr", "ours", "t3a_no_tto", "t3b_no_reg", "t3d_oracle", "truth"})
    assert seen[-1] == (6, 6) and [d for d, _ in seen] == sorted(d for d, _ in seen)
    page = doc.read_text()
    assert "Table 1" in page and "Table 3" in page and "oracle" in page and "holds" in page
    assert (doc.parent / "results" / "grid.png").is_file()
    assert "![paired differences](results/differences.png)" in page
    assert "| dusty | 1 |" in page and "| fuzzy | 1 |" in page  # Table 1 by the example's two families
    assert (doc.parent / "results" / "differences.png").stat().st_size > 0
    ours = json.loads((tmp_path / "eval" / "results" / "test-000000" / "ours.json").read_text())
    assert math.isfinite(ours["psnr_pathtrace"]) and ours["psnr_basecolor"] > 0
    truth = json.loads((tmp_path / "eval" / "results" / "test-000000" / "truth.json").read_text())
    assert truth["psnr_pathtrace"] > ours["psnr_pathtrace"]  # the true material is the ceiling
    # one machine-readable line per written page: means and the headline paired differences
    record = json.loads((tmp_path / "eval.jsonl").read_text().splitlines()[-1])
    assert record["objects"] == 1 and record["means"]["ours"]["psnr_pathtrace"] == ours["psnr_pathtrace"]
    mean, _, n = record["paired"]["ours - pbr"]["psnr_pathtrace"]
    pbr = json.loads((tmp_path / "eval" / "results" / "test-000000" / "pbr.json").read_text())
    assert n == 1 and mean == pytest.approx(ours["psnr_pathtrace"] - pbr["psnr_pathtrace"])
    # resume: nothing is recomputed
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "eval" / "results").rglob("*.json")}
    run_eval(cfg)
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "eval" / "results").rglob("*.json")} == stamps
    # report only: the stored run's settings and results, nothing recomputed, whatever this command says
    doc2 = tmp_path / "docs2" / "results.md"
    report = run_eval(EvalConfig(out=str(tmp_path / "eval"), tables="table2", preset="gpu", doc=str(doc2),
                                 figures=1, report_only=True, progress=False))  # fmt: skip
    assert report["doc"] == doc2 and "Table 3" in doc2.read_text() and "Table 2" not in doc2.read_text()
    assert "--preset tiny" in doc2.read_text() and "--report-only" not in doc2.read_text()
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "eval" / "results").rglob("*.json")} == stamps
    # ... and with the split gone (a fresh machine): the objects and their families come from eval.json
    data.rename(tmp_path / "split-elsewhere")
    doc3 = tmp_path / "docs3" / "results.md"
    report = run_eval(EvalConfig(out=str(tmp_path / "eval"), doc=str(doc3), figures=1, report_only=True,
                                 progress=False))  # fmt: skip
    assert report["objects"] == 1 and "| dusty | 1 |" in doc3.read_text() and "| fuzzy | 1 |" in doc3.read_text()
    (tmp_path / "split-elsewhere").rename(data)
    with pytest.raises(ValueError, match="no stored evaluation"):
        run_eval(EvalConfig(out=str(tmp_path / "nothing"), report_only=True, progress=False))
    with pytest.raises(ValueError, match="unknown table"):
        run_eval(EvalConfig(data=str(data), tables="table9", progress=False))


def test_resuming_with_other_settings_is_refused_naming_them(tmp_path, tiny_lmrm):
    work = tmp_path / "work"
    extract(EXAMPLE, tmp_path / "asset", config(tiny_lmrm), work=work)
    from dataclasses import replace

    extract(EXAMPLE, tmp_path / "asset", replace(config(tiny_lmrm), device="auto"), work=work)  # resumes
    with pytest.raises(PipelineError, match="init"):
        extract(EXAMPLE, tmp_path / "asset2", config(tiny_lmrm, init="random"), work=work)


def test_orderings_use_paired_differences_with_standard_errors():
    from neumatex_core.eval.suite import difference_rows, orderings, paired_difference

    # Two objects far apart in difficulty; ours beats PBR by 1.5 and 2.5 dB on them: paired mean 2.0,
    # std(ddof=1) 0.707, standard error 0.5. A third object has only PBR and must not enter the pair.
    res = {"ours": {"psnr_pathtrace": {"a": 31.5, "b": 20.5}},
           "pbr": {"psnr_pathtrace": {"a": 30.0, "b": 18.0, "c": 25.0}}}
    mean, se, n = paired_difference(res, "ours", "pbr", "psnr_pathtrace")
    assert n == 2 and mean == pytest.approx(2.0) and se == pytest.approx(0.5)
    claims = {claim: (ok, detail) for claim, ok, detail in orderings(res)}
    ok, detail = claims["neural material beats the PBR baseline on PathTrace by a wide margin (>= 1 dB)"]
    assert ok is True and "+2.00 ± 0.50 dB (paired, n=2)" in detail
    assert all(ok is None for c, (ok, _) in claims.items() if "PBR" not in c)  # nothing else was measured
    res["pbr"]["psnr_pathtrace"] = {"a": 31.0, "b": 19.0}  # +0.5, +1.5: mean 1.0, se 0.5: within 2 se
    assert "not resolved" in dict((c, d) for c, _, d in orderings(res))[next(iter(claims))]
    # the chart's rows carry the same per-object differences; unmeasured comparisons have none
    rows = {r.label: r for r in difference_rows(res)}
    assert sorted(rows["ours - PBR, PathTrace"].values) == pytest.approx([0.5, 1.5])
    assert rows["ours - PBR, PathTrace"].thresholds == (1.0,)
    assert sum(1 for r in rows.values() if r.values) == 1


def test_family_table_pairs_within_the_objects_of_each_family(tmp_path):
    from neumatex_core.eval.suite import TRUTH, family_lines, object_families

    for obj, fams in (("a", ["metal", "coated"]), ("b", ["metal"]), ("c", [])):
        (tmp_path / obj).mkdir()
        regions = [{"family": f} for f in fams]
        (tmp_path / obj / "meta.json").write_text(json.dumps({"spec": {"material": {"regions": regions}}}))
    families = object_families(tmp_path, ["a", "b", "c"])
    assert families == {"a": ["coated", "metal"], "b": ["metal"]}
    pt, bc = "psnr_pathtrace", "psnr_basecolor"
    res = {"ours": {pt: {"a": 21.0, "b": 23.0}, bc: {"a": 15.0, "b": 16.0}},
           "pbr": {pt: {"a": 20.0, "b": 24.0}, bc: {"a": 12.0, "b": 13.0}},
           TRUTH: {pt: {"a": 22.0, "b": 25.0}, bc: {}}}
    rows = {line.split(" | ")[0].strip("| "): line for line in family_lines(res, families)[2:]}
    # coated: object a alone (+1); metal: a and b, differences +1 and -1: mean 0, std 1.414, se 1
    assert rows["coated"] == "| coated | 1 | +1.00 | +2.00 | +3.00 |"
    assert rows["metal"] == "| metal | 2 | +0.00 ± 1.00 | +1.50 ± 0.50 | +3.00 ± 0.00 |"


def test_difference_chart_draws_each_object_and_the_mean_bar(tmp_path):
    from PIL import Image

    from neumatex_core.eval.plots import LABEL_WIDTH, DifferenceRow, difference_chart

    # resolved above zero (green bar), unresolved (grey), resolved below zero (red); the scale spans -3..3
    rows = [DifferenceRow("up", [1.0, 2.0, 3.0], (1.0,)), DifferenceRow("flat", [-1.0, 1.0]),
            DifferenceRow("down", [-3.0, -2.9, -3.1])]
    difference_chart(rows, tmp_path / "d.png")
    img = np.asarray(Image.open(tmp_path / "d.png").convert("RGB")).astype(int)
    plot = img[:, LABEL_WIDTH:]

    def where(colour: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        return np.nonzero((plot == np.asarray(colour)).all(-1))

    green, red, grey, orange = (where(c) for c in ((44, 160, 44), (214, 39, 40), (110, 110, 110), (255, 127, 14)))
    assert all(w[0].size for w in (green, red, grey, orange))
    assert green[0].max() < grey[0].min() and grey[0].max() < red[0].min()  # rows in order
    assert green[1].min() > red[1].max()  # "up" above and right of "down"


def test_bias_only_psnr_takes_the_reference_rows_noise_out():
    from neumatex_core.eval.suite import TRUTH, bias_only_psnr

    # reference MSE 1e-3 (30 dB) is the noise; a variant at MSE 2e-3 has bias^2 = 1e-3: 30 dB without the noise.
    res = {TRUTH: {"psnr_pathtrace": {"a": 30.0}}, "v": {"psnr_pathtrace": {"a": -10 * math.log10(2e-3)}}}
    value, n = bias_only_psnr(res, "v")
    assert n == 1 and value == pytest.approx(30.0, abs=1e-9)
    res["v"]["psnr_pathtrace"]["a"] = 30.0  # as good as the reference: clamped, not infinite
    assert bias_only_psnr(res, "v")[0] == pytest.approx(60.0)


def test_every_eval_table_is_described_and_valid():
    """Each table of eval/variants.py has its page title, its metric columns and a row name per variant, and every
    variant is a valid TTO config on the cpu preset (a table added in one place only fails here, not after an
    hour of evaluation)."""
    from neumatex_core.eval.suite import ROW_NAMES, TABLE_METRICS, TABLE_TITLES
    from neumatex_core.eval.variants import TABLES, variant_config
    from neumatex_core.tto.config import TTOConfig

    for table, names in TABLES.items():
        assert table in TABLE_TITLES and table in TABLE_METRICS, table
        for name in names:
            assert name in ROW_NAMES, (table, name)
            config = variant_config(name, TTOConfig.preset("cpu"))
            if config is not None:
                config.check()
    # A variant's regulariser does not follow the extraction's default: "ours" is the paper's anchor at TTOConfig's
    # weight on every preset, and the default's own variant is the extraction's TTO.
    from neumatex_core.pipeline import ExtractConfig

    # The variants are defined on the extraction's variant base (the TTO preset's steps); the extraction's own neural
    # phase runs neural_steps_scale times as many
    extraction, base = ExtractConfig.preset("cpu").tto_config(), ExtractConfig.preset("cpu").variant_base()
    assert base == replace(extraction, steps=TTOConfig.preset("cpu").steps) and extraction.steps == 900
    assert variant_config("ours", base) == variant_config("ours", TTOConfig.preset("cpu"))
    ours = variant_config("ours", base)
    assert ours is not None and (ours.reg, ours.lambda_reg, ours.lambda_consistency) == ("uncertainty", 0.02, 0.0)
    assert variant_config("pbr", base).steps == 400  # type: ignore[union-attr]
    # the default's own variant (since 2026-12-05, design note 81) is the extraction's TTO; the one before it differs
    # only in the alternative basis for v1's start, the one before that only in the other basis tried, the one
    # before that only in its choice's margin, the five
    # before that only in their settling's length, the one before those also in its settling's rate, the one before
    # that also in its settling steps' loss, the one before that also in the settling phase, and the one before that
    # also in the choice's length; the variants measured against those build on them
    from neumatex_core.eval.variants import DEFAULT_VARIANT

    assert DEFAULT_VARIANT == "default_choose_v6_alone" and DEFAULT_VARIANT in TABLES["default"]
    assert variant_config(DEFAULT_VARIANT, TTOConfig.preset("cpu")) == extraction
    assert variant_config(DEFAULT_VARIANT, base) == extraction
    tiny = ExtractConfig.preset("tiny")
    assert variant_config(DEFAULT_VARIANT, tiny.variant_base()) == tiny.tto_config()  # the same scale on every preset
    assert extraction.settle_photo_loss == "decorrelated_debiased" and extraction.settle_lr == 1.0
    # 200 high-rate steps in each, then 700, 600, 500, 400, 300 or 200 settling; the choice's candidates 100 steps each
    assert (extraction.steps, extraction.settle_fraction, extraction.select_fraction) == (900, 7 / 9, 1 / 9)
    assert extraction.settle_start() == 200 and extraction.select_steps() == 100
    assert extraction.select_margin_db == 0.0  # textured kept whenever it scores better on the held-out photos
    assert extraction.select_basis == BASIS_V6  # v6's candidates in the choice too (design note 80)
    assert extraction.alternative_basis == ""  # and v1's start in v1 alone: v6 holds what v4 was there for (note 81)
    choose_v6 = variant_config("default_choose_v6", base)
    assert choose_v6 == replace(extraction, alternative_basis=BASIS_V4)
    assert variant_config("default_v1", base) == replace(extraction, select_basis="")
    m0 = variant_config("pbr_start_default_settle_decdb_slr10_s900_m0", base)
    assert m0 == replace(choose_v6, select_basis="")
    for variation in ("textured", "uniform"):  # no choice on held-out photos: v1, and v4 where v1 cannot hold
        made = ExtractConfig.preset("cpu", variation=variation).variant_base()  # the PBR start
        assert (made.select_basis, made.alternative_basis) == ("", BASIS_V4), variation
    s900 = variant_config("pbr_start_default_settle_decdb_slr10_s900", base)
    assert s900 == replace(m0, select_margin_db=0.25)
    for forced, margin in (("uniform", 100.0), ("textured", -100.0)):  # the choice forced, for both branches
        assert variant_config(f"pbr_start_default_settle_decdb_slr10_s900_{forced}", base) == replace(
            s900, select_margin_db=margin)
    s800 = variant_config("pbr_start_default_settle_decdb_slr10_s800", base)
    assert s800 == replace(s900, steps=800, settle_fraction=3 / 4, select_fraction=1 / 8)
    s700 = variant_config("pbr_start_default_settle_decdb_slr10_s700", base)
    assert s700 == replace(s800, steps=700, settle_fraction=5 / 7, select_fraction=1 / 7)
    s600 = variant_config("pbr_start_default_settle_decdb_slr10_s600", base)
    assert s600 == replace(s700, steps=600, settle_fraction=2 / 3, select_fraction=1 / 6)
    s500 = variant_config("pbr_start_default_settle_decdb_slr10_s500", base)
    assert s500 == replace(s600, steps=500, settle_fraction=0.6, select_fraction=0.2)
    slr10 = variant_config("pbr_start_default_settle_decdb_slr10", base)
    assert slr10 == replace(s500, steps=400, settle_fraction=0.5, select_fraction=0.25)
    assert variant_config("pbr", base).settle_photo_loss == ""  # type: ignore[union-attr]
    decdb = variant_config("pbr_start_default_settle_decdb", base)
    assert decdb == replace(slr10, settle_lr=TTOConfig().settle_lr)
    assert variant_config("pbr_start_default_settle_decdb_slr03", base) == replace(decdb, settle_lr=0.3)
    settle05 = variant_config("pbr_start_default_settle05", base)
    assert settle05 == replace(decdb, settle_photo_loss="")
    assert slr10.settle_fraction == 0.5 and variant_config("pbr", base).settle_fraction == 0.0
    assert variant_config("pbr_start_default_f025", base) == replace(settle05, settle_fraction=0.0)
    # the default with a smoothness term on its neural phase (design note 52); no other variant smooths
    assert variant_config("pbr_start_default_smooth01", base) == replace(settle05, lambda_smooth=0.1)
    assert extraction.lambda_smooth == 0.0 and variant_config("pbr", replace(slr10, lambda_smooth=1.0)) == \
        variant_config("pbr", base)
    # the default with coarse high-rate moves (design note 56); no other variant coarsens
    assert variant_config("pbr_start_default_coarse8", base) == replace(settle05, coarse_factor=8)
    assert extraction.coarse_factor == 1 and variant_config("pbr", replace(slr10, coarse_factor=8)) == \
        variant_config("pbr", base)
    default = variant_config("pbr_start_default_alt_frozen", TTOConfig.preset("cpu"))
    assert default == replace(settle05, select_fraction=0.5, settle_fraction=0.0)
    # its choices scored with fewer samples, or on fewer pixels (tried 2026-11-28, design note 42)
    assert variant_config("pbr_start_default_spp16", base) == replace(default, validation_spp=16)
    assert variant_config("pbr_start_default_stride2", base) == replace(default, validation_stride=2)
    # that default with another seed, and its start fitted in a quarter of the time (design note 46)
    assert variant_config("pbr_start_default_seed1", base) == replace(default, seed=1)
    fit750 = variant_config("pbr_start_default_fit750", base)
    assert fit750 == replace(default, pbr_fit_steps=750, pbr_fit_lr=0.3, pbr_fit_batch=4096)
    # the default before the material decoder was left frozen in basis v4 (2026-11-28)
    reuse = variant_config("pbr_start_default_reuse", base)
    assert reuse == replace(default, decoder_in_other_basis=True)
    # the default before the TTO after the choice went on from the choice's start (2026-11-28)
    tuned = variant_config("pbr_start_default_tuned_0001", base)
    assert tuned == replace(reuse, select_reuse_start=False)
    # the default before the decoder was fine-tuned (2026-11-27)
    frozen = variant_config("pbr_start_consistent_select_uniform_f05_alt_v4_m3", base)
    assert frozen == replace(reuse, train_decoder=False, decoder_lr=TTOConfig().decoder_lr, select_reuse_start=False)
    textured = replace(slr10, select_uniform=False, select_reuse_start=False)
    assert ExtractConfig.preset("cpu", variation="textured").tto_config() == replace(
        extraction, select_uniform=False, select_reuse_start=False, select_basis="", alternative_basis=BASIS_V4)
    # the default before 2026-11-27's "choose" and alternative basis; the baseline runs in the one basis
    assert variant_config("pbr_start_consistent_01", base) == replace(
        textured, alternative_basis="", train_decoder=False, decoder_lr=0.1, decoder_in_other_basis=True,
        settle_fraction=0.0, settle_photo_loss="", settle_lr=TTOConfig().settle_lr)
    assert variant_config("pbr", base).alternative_basis == ""  # type: ignore[union-attr]
    assert not variant_config("pbr", base).train_decoder  # type: ignore[union-attr]


def test_without_a_trained_lmrm_the_tto_tries_no_start_from_it() -> None:
    """effective_tto: an LMRM that is not trained gives no anchor (reg "none") and no start to choose
    (select_lmrm_start off), so a job config asking for that choice still runs instead of failing its TTO check."""
    from neumatex_core.pipeline import effective_tto

    config = ExtractConfig.preset("tiny")
    config = replace(config, tto=replace(config.tto, select_lmrm_start=True))
    trained = effective_tto(config, True)
    assert trained.select_lmrm_start and trained.reg == "start"
    untrained = effective_tto(config, False)
    assert not untrained.select_lmrm_start and untrained.reg == "none"
    untrained.check()
    with pytest.raises(ValueError, match="select_lmrm_start"):
        replace(untrained, select_lmrm_start=True).check()
