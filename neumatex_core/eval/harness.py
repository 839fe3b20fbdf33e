"""One synthetic object under one TTO variant: the numbers of the paper's tables (the per-object step of
`neumatex eval`).

    metrics = evaluate_variant(object_dir, work, "ours", ExtractConfig.preset("cpu"))

The shared stages (validate, prepare_views, lmrm) run once per object through `pipeline.run_stage` in `work`;
each variant's TTO runs from the stored prediction (`variant_config` on the config's TTO preset) and is scored:
PSNR_BaseColor and PSNR_Latents against the ground-truth G-buffers of the preset views, PSNR_PathTrace of the
orbital views (tonemapped, covered pixels, against the stored photos: the same sample count on both sides and a
fixed seed), and the TTO's minutes (wall and CPU). A PBR result's BaseColor is its Lambertian base colour rho_d, the
truth's quantity (`pbr_base_colour`: black under a metal, not the metal's F0).

When the object has references (`eval/references.py`, `neumatex references`), every variant also gets
psnr_pathtrace_clean / psnr_relight_clean: the variant rendered twice per view with independent seeds
(`clean_spp_half` samples each) against the ground-truth material's two reference halves, with the Monte Carlo
noise of both sides subtracted (`references.clean_psnr`; pooled over the covered pixels of the scored views).
The truth row scores the exact ground-truth material (`references.truth_field`) there.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neumatex_core.capture import load_capture
from neumatex_core.eval.gbuffers import GroundTruth, gbuffer_psnr, ground_truth, truth_lookup
from neumatex_core.eval.metrics import psnr
from neumatex_core.eval.references import clean_metrics, coverage_mask, harness_envmap, has_references, truth_field
from neumatex_core.eval.variants import variant_config
from neumatex_core.geometry.camera import PRESET_ORBIT_VIEWS
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import NeuralBasis, load_basis
from neumatex_core.materials.pbr_to_neural import pbr_to_neural
from neumatex_core.pipeline import ExtractConfig, load_prediction, run_stage
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.tto import PhotoSet, solve
from neumatex_core.tto.params import NeuralTriplane, Parametrisation, PBRTriplane


def _render_psnr(object_dir: Path, field: MaterialField, views: Sequence[int], spp: int, max_bounces: int,
                 seed: int, mesh_uv: Any = None) -> float:
    """Mean PSNR_PathTrace (dB) of `field` on the capture's frames `views` against its stored photos."""
    cap = load_capture(object_dir)
    mesh = mesh_uv if mesh_uv is not None else cap.load_mesh()
    env_scene = Scene(mesh, harness_envmap(cap), field)
    tracer = PathTracer(PathTracerConfig(spp=spp, max_bounces=max_bounces))
    scores = []
    for v in views:
        cam = cap.frames[v].camera
        with torch.no_grad():
            image = cap.tonemap_of(v).apply(tracer.render(env_scene, cam, seed=seed + v)).cpu()
        mask = torch.as_tensor(coverage_mask(cap, mesh, v))
        scores.append(psnr(image, torch.as_tensor(cap.load_image(v)), mask))
    return float(sum(scores) / len(scores))


def pbr_base_colour(values: torch.Tensor, basis: NeuralBasis) -> torch.Tensor:
    """[N, 3 + K]: the Lambertian base colour rho_d of PBR points (`values` [N, 5]: base colour, roughness, metallic)
    and NaN latents (K: the basis's latent size). The truth's G-buffer holds rho_d, the colour under the layers (near
    black under a metal), while a PBR base colour is the specular colour F0 where metallic is 1; so a PBR point is
    scored on its rho_d in the layered model (materials/pbr_to_neural.py: b (1 - m) over the specular layer's
    transmission), as the neural TTO's start reads it."""
    rho_d, _ = pbr_to_neural(basis, values[:, :3], values[:, 3], values[:, 4])
    return torch.cat([rho_d, torch.full((values.shape[0], basis.arch.latent_dim), math.nan, device=values.device)], -1)


def _gbuffer_fn(params: Parametrisation | None, pred: LMRMPrediction, gt: GroundTruth, uv_mesh: Any,
                basis: NeuralBasis) -> Any:
    """points -> [N, 3 + K] (rho_d, the K latents of the basis) for the G-buffer metrics (PBR: `pbr_base_colour`)."""
    if params is None:
        return lambda p: torch.cat(pred.material_decoder(pred.triplane.features(p)), dim=-1)
    if isinstance(params, NeuralTriplane):
        return lambda p: params.gbuffer(p, None)
    if isinstance(params, PBRTriplane):
        return lambda p: pbr_base_colour(params.gbuffer(p, None), basis)
    # UV fields: read the texture at the uv of the nearest point of the unwrapped mesh's vertices' triangles.

    pool, pool_uv = uv_mesh.sample_surface(1 << 16, seed=1)
    assert pool_uv is not None

    def uv_values(p: torch.Tensor) -> torch.Tensor:
        nearest = torch.cat([torch.cdist(p[s:s + 4096], pool).argmin(1) for s in range(0, p.shape[0], 4096)])
        values = params.gbuffer(p, pool_uv[nearest])
        return pbr_base_colour(values, basis) if values.shape[-1] == 5 else values

    return uv_values


def evaluate_variant(object_dir: str | Path, work: str | Path, variant: str, config: ExtractConfig,
                     render_views: Sequence[int] = tuple(range(PRESET_ORBIT_VIEWS)), render_spp: int | None = None,
                     render_bounces: int = 3, relight_views: Sequence[int] = (),
                     figure_dir: str | Path | None = None, clean_spp_half: int = 32,
                     capture_dir: str | Path | None = None) -> dict[str, float]:
    """The table numbers of one variant on one synthetic object (see the module docstring). `render_spp`
    defaults to the sample count the object's photos were made with (its synth.json / meta.json content).

    capture_dir: the capture the extraction reads (stages and TTO photos); default the object itself (its 23 preset
    views). E.g. its random-pose variant (`<object>/random_pose`, `neumatex synth-random-pose`): the scores stay the
    object's (its views, references and ground truth), so the two are paired.

    relight_views: frames of each held-out lighting (`relight/K` of the object) to score as `psnr_relight`
    (mean over maps and frames, at the relight photos' own sample count); empty: none.
    figure_dir: when given, writes the variant's pictures of preset view 0 there (`render.png` tonemapped,
    `basecolor.png` sRGB, `latent.png` channels 0-2 as (l + 1) / 2; uncovered pixels white).
    clean_spp_half: samples per pixel of each of the two renders per view of the clean scoring (module
    docstring; only for objects with references; 0: none). Adds psnr_pathtrace_clean (`render_views`) and
    psnr_relight_clean (`relight_views` of every held-out lighting), each with _raw / _mse / _se
    (`references.clean_metrics`)."""
    object_dir, work = Path(object_dir), Path(work)
    source = object_dir if capture_dir is None else Path(capture_dir)
    for stage in ("validate", "prepare_views", "lmrm"):
        run_stage(stage, source, work, config)
    if variant == TRUTH:
        return _evaluate_truth(object_dir, render_views, render_spp, render_bounces, relight_views, config.seed,
                               clean_spp_half)
    pred, record = load_prediction(work)
    if not record["trained"]:
        raise ValueError(f"{work}: evaluation needs a trained LMRM (the lmrm stage fell back to a random start)")
    if render_spp is None:
        meta = json.loads((object_dir / "meta.json").read_text())
        render_spp = int(meta["content"]["spp"])
    gt = ground_truth(object_dir)
    tto = variant_config(variant, config.variant_base())
    cap = load_capture(source)
    mesh = cap.load_mesh()
    env = harness_envmap(cap)
    t0, c0 = time.perf_counter(), time.process_time()
    params: Parametrisation | None = None
    scene_mesh = mesh
    choice: dict[str, float] = {}
    if tto is not None:
        photos = PhotoSet.of_capture(cap, mesh)
        truth = truth_lookup(gt) if tto.reg == "oracle" else None
        result = solve(tto, mesh, env, photos, cap.tonemap, pred, load_basis(basis_id=tto.basis), truth=truth)
        params, scene_mesh = result.params, result.mesh or mesh
        choice = {f"choice_{k}": v for k, v in result.selection.items()}  # select_anchor / select_uniform's record
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    basis = load_basis()
    from neumatex_core.fields.neural_field import TriplaneMaterialField

    field = params.field() if params is not None else TriplaneMaterialField(pred.triplane, pred.material_decoder, basis)
    gfn = _gbuffer_fn(params, pred, gt, scene_mesh, basis)
    scores = gbuffer_psnr(gfn, gt)
    result_basis = getattr(field, "basis", None)
    if result_basis is not None and result_basis.basis_id != basis.basis_id:
        # another basis's latents (TTOConfig.basis, alternative_basis) against the truth's in that basis
        scores["psnr_latents"] = gbuffer_psnr(gfn, ground_truth(object_dir, basis=result_basis))["psnr_latents"]
    path = _render_psnr(object_dir, field, render_views, render_spp, render_bounces, config.seed, scene_mesh)
    out = {**scores, "psnr_pathtrace": path, "tto_minutes": seconds / 60, "tto_cpu_minutes": cpu / 60, **choice}
    if relight_views:
        out["psnr_relight"] = _relight_psnr(object_dir, field, relight_views, render_spp, render_bounces, config.seed,
                                            scene_mesh)  # fmt: skip
    out.update(clean_metrics(object_dir, field, scene_mesh, render_views, relight_views, clean_spp_half, config.seed))
    if figure_dir is not None:
        write_figures(Path(figure_dir), cap, field, gfn, scene_mesh, render_spp, render_bounces, config.seed)
    return out


TRUTH = "truth"  # the reference row: the object's own ground-truth material through the same scoring


class GroundTruthField(MaterialField):
    """The ground-truth neural material of a synthetic object as a field: each surface point takes the (rho_d,
    latent) of the nearest covered pixel centre of the stored preset-view G-buffers (a k-d tree over them)."""

    def __init__(self, gt: GroundTruth, basis: Any) -> None:
        from scipy.spatial import cKDTree

        self.tree, self.values, self.basis = cKDTree(gt.points.numpy()), gt.values, basis

    def at(self, si: Any) -> Any:
        from neumatex_core.materials.neural_basis import NeuralMaterial

        _, idx = self.tree.query(si.position.detach().cpu().numpy())
        v = self.values[torch.from_numpy(idx)].to(si.position.device)
        return NeuralMaterial(self.basis, v[:, :3], v[:, 3:])


def _evaluate_truth(object_dir: Path, render_views: Sequence[int], render_spp: int | None, render_bounces: int,
                    relight_views: Sequence[int], seed: int, clean_spp_half: int = 0) -> dict[str, float]:
    """PSNR PathTrace / Relight of the ground-truth material (the ceiling set by Monte Carlo noise and the
    G-buffers' pixel sampling); BaseColor / Latents are not scored (inf by definition). The clean numbers (objects
    with references) use the exact ground-truth field (`references.truth_field`)."""
    meta = json.loads((object_dir / "meta.json").read_text())
    spp = int(meta["content"]["spp"]) if render_spp is None else render_spp
    field = GroundTruthField(ground_truth(object_dir), load_basis())
    mesh = load_capture(object_dir).load_mesh()
    out = {"psnr_pathtrace": _render_psnr(object_dir, field, render_views, spp, render_bounces, seed, mesh)}
    if relight_views:
        out["psnr_relight"] = _relight_psnr(object_dir, field, relight_views, spp, render_bounces, seed, mesh)
    if clean_spp_half > 0 and has_references(object_dir):
        out.update(clean_metrics(object_dir, truth_field(object_dir), mesh, render_views, relight_views,
                                 clean_spp_half, seed))  # fmt: skip
    return out


def _relight_psnr(object_dir: Path, field: MaterialField, views: Sequence[int], spp: int, bounces: int, seed: int,
                  mesh: Any) -> float:
    """Mean PSNR of `field` on frames `views` of every held-out lighting (`relight/K`) of the object, at the relight
    photos' own sample count (meta.json content.relight_spp, else `spp`); NaN when the object has none."""
    content = json.loads((object_dir / "meta.json").read_text())["content"]
    relight_spp = int(content.get("relight_spp", spp))
    maps = sorted(p for p in (object_dir / "relight").glob("*") if (p / "transforms.json").is_file())
    scores = [_render_psnr(m, field, views, relight_spp, bounces, seed, mesh) for m in maps]
    return float(sum(scores) / len(scores)) if scores else math.nan


def write_figures(folder: Path, cap: Any, field: MaterialField, gfn: Any, mesh: Any, spp: int, bounces: int,
                  seed: int, view: int = 0) -> None:
    """render.png, basecolor.png, latent.png of frame `view` of `cap` (see `evaluate_variant`); latent.png shows
    the first three latent numbers, whatever the basis's size (`gfn` gives rho_d and the latents, [N, 3 + K])."""
    from neumatex_core.capture.tonemap import srgb_oetf_numpy
    from neumatex_core.imageio import write_image

    folder.mkdir(parents=True, exist_ok=True)
    cam = cap.frames[view].camera
    tracer = PathTracer(PathTracerConfig(spp=spp, max_bounces=bounces))
    with torch.no_grad():
        image = cap.tonemap_of(view).apply(tracer.render(Scene(mesh, harness_envmap(cap), field), cam,
                                                         seed=seed + view)).cpu()
        g = render_gbuffer(mesh, cam)
        mask = g.mask.reshape(-1)
        covered = gfn(g.position.reshape(-1, 3)[mask]).float().cpu() if bool(mask.any()) else torch.ones(0, 6)
        values = torch.ones(mask.shape[0], covered.shape[1])
        values[mask] = covered
    h, w = cam.height, cam.width
    white = ~mask.reshape(h, w).numpy()
    rho = srgb_oetf_numpy(np.clip(values[:, :3].reshape(h, w, 3).numpy(), 0, 1))
    lat = np.clip((values[:, 3:6].reshape(h, w, 3).numpy() + 1) / 2, 0, 1)
    lat = np.nan_to_num(lat, nan=0.5)  # PBR variants have no latents: mid grey
    img = image.numpy()[:, :, :3].copy()
    for name, pic in (("render", img), ("basecolor", rho), ("latent", lat)):
        pic = pic.copy()
        pic[white] = 1.0
        write_image(folder / f"{name}.png", np.clip(pic, 0, 1).astype(np.float32))
