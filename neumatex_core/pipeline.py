"""Extraction: capture -> neural material asset, in five resumable stages. The one entry used by the CLI
(`neumatex extract`) and by the service workers (one task per stage).

    STAGES = ("validate", "prepare_views", "lmrm", "tto", "export")
    metrics = run_stage("tto", capture, work, ExtractConfig.preset("cpu"), progress, should_stop)
    asset = extract(capture, out, ExtractConfig.preset("cpu"), progress, should_stop, work)

Each stage reads the capture and the previous stages' stored outputs under `work/`, writes its own under
`work/<stage>/` and `done.json` last (atomic rename), so it is idempotent (a finished stage returns its stored
metrics) and a killed stage re-runs cleanly (the TTO resumes from its last checkpoint). Stage outputs:

- validate/       done.json (frames, faces, envmap size)
- prepare_views/  views.safetensors (display [23, R, R, 3], mask, observed), views.json (normalisation, source),
                  views.png
- lmrm/           prediction.safetensors (triplane planes, decoder weights), prediction.json (source, decoder
                  architectures and ids, whether it is a trained LMRM's)
- tto/            checkpoint.pt (while running), result.safetensors (the optimised tensor), history.json
- export/         asset/ (the package; report/index.html inside)

Errors: bad input raises PipelineError with the file and the problem in plain words; should_stop() returning
true raises Cancelled (checked between stages and between TTO steps; the TTO checkpoints first).
"""

from __future__ import annotations

import copy
import json
import logging
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import torch

from neumatex_core.atomic import write_json_atomic
from neumatex_core.capture import Capture, CaptureError, load_capture, validate_capture
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.config import Range, check_choices, check_known_keys, check_ranges
from neumatex_core.device import resolve_device
from neumatex_core.fields.decoders import DECODERS, MaterialDecoder, PBRDecoder, UncertaintyDecoder, module_id
from neumatex_core.fields.triplane import Triplane
from neumatex_core.geometry.camera import Camera, preset_views
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.lmrm.inference import LMRM, LMRMPrediction
from neumatex_core.materials.neural_basis import BASIS_V4, BASIS_V6, load_basis
from neumatex_core.tto.config import PRESETS, UNIFORM_RHO_VALUE, TTOConfig  # extract presets use TTO presets
from neumatex_core.tto.data import PhotoSet
from neumatex_core.tto.fallback_choice import choose_fallback
from neumatex_core.tto.optimise import decoder_for
from neumatex_core.tto.params import Parametrisation, PBRTriplane
from neumatex_core.tto.pbr_start import CHOICES, solve, validation_frames

STAGES = ("validate", "prepare_views", "lmrm", "tto", "export")
DONE = "done.json"
ASSET_DIR = "asset"
PRESET_TOLERANCE = 1e-3  # max |c2w difference| for a frame to count as a preset view
RANDOM_TRIPLANE = (16, 48)  # channels, resolution of the random triplane when no LMRM is available
SHIPPED_LMRM = "shipped"  # ExtractConfig.lmrm_readout's name for the shipped checkpoint
# What every extract preset runs after the PBR TTO (ExtractConfig.init "pbr"): the neural TTO from its start, the
# PBR solution in the basis, where points that start alike must change alike (the consistency term, weight 0.1;
# no pull towards the start's values). It lets the neural phase add a coat or a sheen to a whole material and keeps
# it from painting the capture's light onto parts of it. On the Cycles captures (4 meshes, clean, relit - PBR) coat
# +2.98, sheen +1.26, diffuse +2.11 dB, where the anchor to the start's values (lambda_reg 0.1, the default before)
# gave +1.91, +0.14 and -0.01 (docs/design-notes.md, items 26 and 34). The neural phase starts in basis v4 where the
# default basis cannot hold the PBR solution (Cycles metals, held-out photos / relit - PBR: +0.73 / -0.56 dB, where
# the default basis gave -3.92 / -4.88; item 38). Both phases fine-tune a copy of their decoder (the LMRM's PBR head,
# its material decoder) at 1/1000 of the planes' learning rate: the frozen decoder caps what the triplane can
# express (item 24); on the 12 benchmark objects measured, clean PathTrace +0.86 dB over the frozen one, and on
# the Cycles sheens +9.31 dB relit over PBR (item 39). The material decoder is tuned only in the default basis, the
# one the LMRM trained it for: tuned in basis v4 it cost the Cycles metals 0.6-2.3 dB relit (item 41). The neural
# phase's last half settles (TTOConfig.settle_fraction: the same rays at 32 spp, a tenth of the rate): Adam moves
# every parameter by about its rate whatever share of its gradient is noise, and the settling phase lets the
# weakly constrained ones rest; on all 40 benchmark objects, clean, PathTrace +0.44 +- 0.13 and Relight +0.69 +- 0.20
# dB over the same recipe without it (item 50). The settling steps take the debiased decorrelated loss (tto/loss.py):
# the L2 of a tonemapped render is least where the material is brighter than a noise-free photo, and the settling
# fits the end to the photo itself; on all 40 objects, clean, PathTrace +0.18 +- 0.07 and Relight +0.16 +- 0.04 dB
# over the L2 settling at the same cost (items 53, 58 and 59). The settling's cosine starts again from the full rate
# (settle_lr 1.0, not a tenth): on all 40 objects, clean, PathTrace +0.15 +- 0.13 and Relight +0.73 +- 0.14 dB over
# a tenth, and on the 16 Cycles captures relit +0.55 (coat) to +5.23 dB (sheen), at the same cost (items 62-65).
# The settling is three and a half times as long as the high-rate steps before it (ExtractConfig.neural_steps_scale
# 2.25 with settle_fraction 7/9: on the cpu preset 200 high-rate steps, then 700 settling; the choice's candidates
# keep a ninth, 100 steps each). Each 100 settling steps added gained clean PathTrace +0.38, +0.24, +0.35, +0.20,
# +0.15 dB on all 40 objects for about 10% more TTO steps, and did not lose relit on the Cycles coats, sheens and
# metals (items 66-74 give the figures). The choice keeps the textured material whenever it scores better on the
# held-out photos (select_margin_db 0, not TTOConfig's 0.25): both branches run on all 40 objects, the 12 whose
# margin lay in (0, 0.25] gained clean PathTrace +0.33 +- 0.11 and Relight +0.19 +- 0.14 dB over the 40, and no
# Cycles capture's margin lies there (item 75). The choice also runs both candidates in basis v6 (16 latent
# numbers, every sphere family >= 35 dB; its decoder fine-tuned) from the same PBR solution and takes v6 where its
# kept candidate scores better on the held-out photos (select_basis): over the plain TTO in v1/v4, on all 40
# objects, clean, PathTrace +0.89 +- 0.21 and Relight +1.13 +- 0.29 dB, and on the 16 Cycles captures it keeps v1
# on every sheen (which v6 alone loses by 4.9 dB) and takes v6 on most metals (relit +1.85 +- 0.73); 200 neural
# steps more, a start fit more (item 80). With v6 in that choice, v1's start has no alternative basis: v6 holds the
# metals v4 was there for, and without v4 the demo is 14-16 s faster, all 40 objects PathTrace +0.03 +- 0.02 and the
# Cycles metals relit +0.54 (item 81). Where no other basis is tried (ALTERNATIVE_BASIS) v4 stays.
NEURAL_FROM_PBR: dict[str, Any] = {"reg": "start", "lambda_reg": 0.0, "lambda_consistency": 0.1,
                                   "train_decoder": True, "decoder_lr": 0.001,
                                   "decoder_in_other_basis": False, "settle_fraction": 7 / 9, "select_fraction": 1 / 9,
                                   "settle_photo_loss": "decorrelated_debiased", "settle_lr": 1.0,
                                   "select_margin_db": 0.0, "select_basis": BASIS_V6}
NEURAL_STEPS_SCALE = 2.25  # ExtractConfig.neural_steps_scale's default (above)
# The start's alternative basis where the TTO runs in the default basis (v1), tries no other basis on held-out photos
# (no select_basis: the variations textured and uniform, which make no choice) and its config names none: v1 cannot
# hold a coloured metal's PBR solution, v4 can (docs/design-notes.md items 38, 81)
ALTERNATIVE_BASIS = BASIS_V4
# ExtractConfig.variation: what each says about the object's surface sets in the TTO config. "uniform" also compares
# the base colours' values of points that start alike, which removes the capture's light that the PBR phase painted
# into a uniform material's base colour (Cycles captures, relit - PBR: sheen +2.09, coat +3.71 dB, against +1.26,
# +2.98 for "textured"), and costs a textured object 1.2-1.8 dB; "choose" (the default since 2026-11-27) tries both
# on all photos but four and keeps uniform unless textured reproduces those clearly better, then goes on from the
# choice's start on every photo (docs/design-notes.md, items 35-37 and 40). Without a PBR start there is nothing to
# choose: "choose" is then "textured" (ExtractConfig.tto_config).
VARIATIONS: dict[str, dict[str, Any]] = {"textured": {}, "uniform": {"consistency_rho_value": UNIFORM_RHO_VALUE},
                                         "choose": {"select_uniform": True, "select_reuse_start": True}}
# The allowed values of ExtractConfig's numeric fields (ExtractConfig.check; the job service's bounds).
RANGES: dict[str, Range] = {
    "view_resolution": Range(16, 1024), "blend_k": Range(1, 64), "texture_resolution": Range(16, 8192),
    "preview_resolution": Range(16, 4096), "preview_spp": Range(1, 4096), "eval_photos": Range(0, 1000),
    "eval_spp": Range(1, 4096), "seed": Range(0, 2**31 - 1), "neural_steps_scale": Range(0.1, 10)}  # fmt: skip


class PipelineError(Exception):
    """Bad input or an unusable stage output; the message names the file and the problem in plain words."""


class Cancelled(Exception):
    """should_stop() returned true; finished stages (and the TTO checkpoint) are kept for a later resume."""


@dataclass
class StageProgress:
    """stage: one of STAGES; fraction: of this stage done, in [0, 1]; message: one line for people; metrics: the
    stage's numbers so far (TTO: step, loss, photo, reg, psnr, lr)."""

    stage: str
    fraction: float
    message: str
    metrics: dict[str, float] = field(default_factory=dict)


Progress = Callable[[StageProgress], None]
ShouldStop = Callable[[], bool]


@dataclass
class ExtractConfig:
    """preset_name: the preset this config came from; tto: the TTO schedule and variant; init: "pbr" (the default: the
    PBR baseline's TTO from the LMRM's PBR head, then the neural TTO from its solution; tto/pbr_start.py), "lmrm" (the
    paper's start: the LMRM's triplane; both need the shipped LMRM checkpoint, or `lmrm_weights`) or "random". The
    presets regularise the neural TTO against its PBR start (`NEURAL_FROM_PBR`), not against the LMRM (with the
    shipped LMRM that anchor costs 3-4 dB of clean PathTrace; docs/design-notes.md, items 26 and 34);
    neural_steps_scale: the neural TTO from the PBR start runs this many times `tto.steps` (its settling the longer;
    `NEURAL_STEPS_SCALE`), while the evaluation's variants and the PBR baseline are defined on `tto.steps` itself
    (`variant_base`);
    view_resolution: size of the preset views made by prepare_views (pixels); blend_k: photos blended per pixel
    when views are synthesised; texture_resolution: baked asset textures; preview_resolution / preview_spp: preview
    renders; eval_photos / eval_spp: photos re-rendered at export for the photo PSNR (0: none); variation: how the
    object's material varies over its surface, which sets the neural phase's consistency term (`VARIATIONS`):
    "choose" (the default: both tried, held-out photos decide, in basis v6 too; 1500 TTO steps, not 1100, on cpu;
    "textured" without the PBR start), "textured" (several materials or textures) or "uniform" (one material all
    over; needs init "pbr");
    lmrm_weights: an LMRM .safetensors (its .json beside it) instead of the shipped one; lmrm_readout: an LMRM
    .safetensors (or "shipped": the shipped checkpoint) whose decoders read the prediction, restated per object
    through them (lmrm/restate.py; the fit follows `tto`'s start-fit schedule); "": the LMRM's own decoders;
    device: "auto", "cpu" or "cuda"; seed: every random draw; name: asset name (default: the capture folder's)."""

    preset_name: str = "cpu"
    tto: TTOConfig = field(default_factory=TTOConfig)
    init: Literal["lmrm", "random", "pbr"] = "pbr"
    neural_steps_scale: float = NEURAL_STEPS_SCALE
    view_resolution: int = 64
    blend_k: int = 3
    texture_resolution: int = 128
    preview_resolution: int = 128
    preview_spp: int = 32
    eval_photos: int = 4
    eval_spp: int = 16
    variation: Literal["textured", "uniform", "choose"] = "choose"
    lmrm_weights: str = ""
    lmrm_readout: str = ""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    seed: int = 0
    name: str = ""

    @classmethod
    def preset(cls, name: str, /, **overrides: Any) -> ExtractConfig:
        """'tiny' (tests: seconds), 'cpu' (default: minutes on 2 cores) or 'gpu' (quality), with field overrides
        (`name=` among them: the asset's name)."""
        if name == "tiny":
            base = cls(preset_name=name, tto=TTOConfig.preset("tiny", **NEURAL_FROM_PBR), view_resolution=32,
                       texture_resolution=64, preview_resolution=32, preview_spp=2, eval_photos=1,
                       eval_spp=2)  # fmt: skip
        elif name == "cpu":
            base = cls(preset_name=name, tto=TTOConfig.preset("cpu", **NEURAL_FROM_PBR), texture_resolution=128,
                       preview_resolution=128, preview_spp=32, eval_spp=32)  # fmt: skip
        elif name == "gpu":
            base = cls(preset_name=name, tto=TTOConfig.preset("gpu", **NEURAL_FROM_PBR), view_resolution=128,
                       texture_resolution=1024, preview_resolution=512, preview_spp=256, eval_photos=23,
                       eval_spp=128)  # fmt: skip
        else:
            raise ValueError(f"unknown extract preset {name!r} (expected one of {', '.join(PRESETS)})")
        return replace(base, **overrides)

    def check(self) -> None:
        """ValueError naming the first bad field of a config that is to make an asset: the numeric ranges, the
        choices, the TTO config, and no evaluation-only TTO variant (which the tto or export stage would refuse)."""
        check_ranges(self, RANGES, "config")
        check_choices(self, "config")
        tto = self.tto_config()
        problem = evaluation_only(tto)  # first: the reason that matters to whoever asked for it
        if problem:
            raise ValueError(problem)
        if self.variation == "uniform" and not self.has_pbr_start():
            raise ValueError(f"config variation={self.variation!r} sets the consistency term of the neural TTO from "
                             f"the PBR start: it needs init 'pbr' and tto.lambda_consistency > 0, got init "
                             f"{self.init!r} and lambda_consistency {self.tto.lambda_consistency}")
        tto.check()

    def has_pbr_start(self) -> bool:
        """Whether the neural TTO starts from the PBR solution with the consistency term, which the variations set."""
        return self.init == "pbr" and self.tto.lambda_consistency > 0

    def variant_base(self) -> TTOConfig:
        """The TTO config with this config's init switch, seed and variation ("choose" is "textured" where there is
        no PBR start). The other basis (select_basis) only where the variation chooses on held-out photos
        ("choose"); where the TTO runs in the default basis and no other basis is tried, the start's alternative
        basis is ALTERNATIVE_BASIS unless the TTO config names one (docs/design-notes.md item 81). The start anchor
        (reg "start") and the alternative basis only where there is a PBR start (init "pbr"), no anchor and the one
        basis otherwise. The schedule the evaluation's variants are defined on (eval/variants.py `variant_config`):
        its `steps` are `tto.steps`, not scaled."""
        variation = "textured" if self.variation == "choose" and not self.has_pbr_start() else self.variation
        tto = replace(self.tto, init=self.init, seed=self.seed, **VARIATIONS[variation])
        if not (tto.select_uniform or tto.select_anchor):  # no choice on held-out photos to try the other basis in
            tto = replace(tto, select_basis="")
        if not (tto.select_basis or tto.basis):  # the default basis, v6 not tried: v4 where it cannot hold the PBR
            tto = replace(tto, alternative_basis=tto.alternative_basis or ALTERNATIVE_BASIS)  # solution
        if tto.init != "pbr":  # the anchor to the start and the alternative basis's start need the PBR start
            tto = replace(tto, reg="none" if tto.reg == "start" else tto.reg, alternative_basis="")
        return tto

    def tto_config(self) -> TTOConfig:
        """The TTO the extraction runs: `variant_base()` with the neural phase from the PBR start
        `neural_steps_scale` times as long."""
        tto = self.variant_base()
        if tto.init == "pbr":
            tto = tto.steps_scaled(self.neural_steps_scale)
        return tto

    def torch_device(self) -> torch.device:
        return resolve_device(self.device)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (the TTO config nested), e.g. for a job record or a task message; `from_dict` inverts it."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ExtractConfig:
        check_known_keys(cls, data, "extract config")
        values = dict(data)
        if isinstance(values.get("tto"), dict):
            values["tto"] = TTOConfig.from_dict(values["tto"])
        return cls(**values)


# -- stage bookkeeping ------------------------------------------------------------------------------------------
def stage_dir(work: Path, stage: str) -> Path:
    return Path(work) / stage


def asset_path(work: Path) -> Path:
    """Where the export stage writes the asset package (a folder)."""
    return stage_dir(work, "export") / ASSET_DIR


def is_done(work: Path, stage: str) -> bool:
    return (stage_dir(work, stage) / DONE).is_file()


def read_done(work: Path, stage: str) -> dict[str, Any]:
    """The stored metrics of a finished stage (PipelineError if it is not finished or unreadable)."""
    path = stage_dir(work, stage) / DONE
    try:
        data = json.loads(path.read_text())
        return dict(data["metrics"])
    except FileNotFoundError:
        raise PipelineError(f"{path}: stage {stage!r} has not finished; run it first") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise PipelineError(f"{path}: unreadable stage record ({exc}); delete it to re-run the stage") from None


def _mark_done(work: Path, stage: str, metrics: dict[str, Any]) -> None:
    write_json_atomic(stage_dir(work, stage) / DONE, {"stage": stage, "metrics": metrics})


def _require(work: Path, *stages: str) -> None:
    for s in stages:
        if not is_done(work, s):
            raise PipelineError(f"{stage_dir(work, s)}: stage {s!r} has not finished; run the stages in order "
                                f"({', '.join(STAGES)})")  # fmt: skip


def _emit(progress: Progress | None, stage: str, fraction: float, message: str,
          metrics: dict[str, float] | None = None) -> None:
    if progress is not None:
        progress(StageProgress(stage, float(min(max(fraction, 0.0), 1.0)), message, dict(metrics or {})))


# -- the capture in the normalised frame ------------------------------------------------------------------------
def _open_capture(capture: Path) -> Capture:
    try:
        return load_capture(capture)
    except CaptureError as exc:
        raise PipelineError(f"{capture}: {exc}") from None


def normalisation(mesh: Mesh) -> tuple[np.ndarray, float]:
    """(centre [3], scale) into the unit sphere; the identity when the mesh is already inside it (synthetic
    objects and captures made in the preset frame keep their coordinates)."""
    if float(np.linalg.norm(mesh.vertices, axis=1).max()) <= 1.0 + PRESET_TOLERANCE:
        return np.zeros(3, dtype=np.float32), 1.0
    return mesh.normalization()


@dataclass
class _Normalised:
    capture: Capture
    mesh: Mesh
    cameras: list[Camera]
    envmap: EnvironmentMap
    centre: np.ndarray
    scale: float


def _normalised(cap: Capture, work: Path, device: torch.device) -> _Normalised:
    """The capture's mesh, cameras and lighting in the frame prepare_views chose (views.json)."""
    record = json.loads((stage_dir(work, "prepare_views") / "views.json").read_text())
    centre, scale = np.asarray(record["centre"], dtype=np.float32), float(record["scale"])
    raw = cap.load_mesh()
    mesh = Mesh(((raw.vertices - centre) * scale).astype(np.float32), raw.faces, raw.vertex_normals, raw.uvs)
    cameras = [c.normalized(centre, scale) for c in cap.cameras]
    envmap = EnvironmentMap(cap.load_envmap(), cap.envmap_to_world, 1.0, device)
    return _Normalised(cap, mesh, cameras, envmap, centre, scale)


def _display_tonemap(tonemap: Tonemap) -> Tonemap:
    """What the LMRM reads: the capture's exposure with the sRGB transfer."""
    return Tonemap(tonemap.exposure, "srgb")


def _preset_frames(cameras: list[Camera]) -> list[int] | None:
    """Frame index of each of the 23 preset views, if the capture has them all (any square resolution)."""
    from neumatex_core.novel_view.presets import match_preset_views

    return match_preset_views(cameras).frames


# -- stages ---------------------------------------------------------------------------------------------------
def _stage_validate(capture: Path, work: Path, config: ExtractConfig, progress: Progress | None) -> dict[str, Any]:
    _emit(progress, "validate", 0.0, f"validating {capture}")
    problems = validate_capture(capture)
    if problems:
        lines = "\n".join(f"  {p}" for p in problems)
        raise PipelineError(f"{capture}: {len(problems)} problem(s) with the capture:\n{lines}")
    with _open_capture(capture) as cap:
        mesh = cap.load_mesh()
        return {"frames": len(cap.frames), "faces": mesh.num_faces}


def _stage_prepare_views(capture: Path, work: Path, config: ExtractConfig,
                         progress: Progress | None) -> dict[str, Any]:
    from safetensors.torch import save_file

    from neumatex_core.imageio import write_image
    from neumatex_core.novel_view.lumigraph import Photo, blend_views
    from neumatex_core.render.views import contact_sheet

    out = stage_dir(work, "prepare_views")
    with _open_capture(capture) as cap:
        raw = cap.load_mesh()
        centre, scale = normalisation(raw)
        mesh = Mesh(((raw.vertices - centre) * scale).astype(np.float32), raw.faces, raw.vertex_normals, raw.uvs)
        cameras = [c.normalized(centre, scale) for c in cap.cameras]
        display_tm = _display_tonemap(cap.tonemap)
        from neumatex_core.novel_view.presets import match_preset_views

        match = match_preset_views(cameras)  # why not, when the photos look meant as preset views: said and kept
        frames = match.frames
        if frames is not None:
            source = "the capture's preset views"
            imgs, masks = [], []
            for k, i in enumerate(frames):
                lin = cap.tonemap_of(i).display_to_linear(cap.load_image(i))  # the frame's own exposure
                imgs.append(torch.as_tensor(display_tm.apply_numpy(lin)))
                m = cap.load_mask(i)
                cover = render_gbuffer(mesh, cameras[i]).mask
                masks.append(cover if m is None else cover & torch.as_tensor(m))
                _emit(progress, "prepare_views", (k + 1) / 23, f"preset view {k + 1}/23 from frame {i}")
            display = torch.stack(imgs).float()
            mask = torch.stack(masks)
            observed = mask.clone()
            resolution = int(display.shape[1])
        else:
            source = f"blended from {len(cap.frames)} photos (unstructured lumigraph)"
            if match.aimed:
                source += f"; {match.reason}"
                _emit(progress, "prepare_views", 0.0, match.reason)
                logging.getLogger("neumatex.pipeline").warning("%s: photos %s", capture, match.reason)
            photos = []
            for i in range(len(cap.frames)):
                lin = cap.tonemap_of(i).display_to_linear(cap.load_image(i))  # the frame's own exposure
                photos.append(Photo(lin.astype(np.float32), cameras[i], cap.load_mask(i)))
            resolution = config.view_resolution
            views = blend_views(mesh, photos, preset_views(resolution), k=config.blend_k,
                                progress=lambda d, n: _emit(progress, "prepare_views", d / n, f"blended view {d}/{n}"))
            display = display_tm.apply(views.images).float()
            mask, observed = views.mask, views.observed
    save_file({"display": display.contiguous(), "mask": mask.to(torch.uint8).contiguous(),
               "observed": observed.to(torch.uint8).contiguous()}, str(out / "views.safetensors"))  # fmt: skip
    write_image(out / "views.png", contact_sheet([d.numpy() for d in display], columns=6))
    write_json_atomic(out / "views.json", {"centre": [float(c) for c in centre], "scale": float(scale),
                                            "source": source, "resolution": resolution})  # fmt: skip
    return {"resolution": resolution, "observed_fraction": float(observed.sum() / mask.sum().clamp_min(1)),
            "source": source}


def _load_lmrm(weights: str, device: torch.device) -> LMRM:
    """The LMRM checkpoint at `weights` (.safetensors, its .json beside it), or the shipped one for "" or
    "shipped"."""
    from neumatex_core.lmrm import load_lmrm
    from neumatex_core.lmrm.inference import load_lmrm_from

    if weights in ("", SHIPPED_LMRM):
        return load_lmrm(device)
    return load_lmrm_from(Path(weights), Path(weights).with_suffix(".json"), device)


def _restated(pred: LMRMPrediction, readout: LMRM, norm: _Normalised, views: dict[str, torch.Tensor],
              config: ExtractConfig) -> tuple[LMRMPrediction, dict[str, Any]]:
    """`pred` read through `readout`'s decoders (lmrm/restate.py), fitted at the start fit's area samples and
    schedule; and what the record keeps of it: the readout's hash, each head's squared error before and after."""
    from neumatex_core.lmrm.restate import restate
    from neumatex_core.tto.pbr_start import FIT_POINTS

    base = readout.predict(views["display"].float(), preset_views(int(views["display"].shape[1])), norm.mesh,
                           norm.envmap)  # fmt: skip
    points, _ = norm.mesh.sample_surface(FIT_POINTS, seed=config.seed)
    tto, t0 = config.tto, time.perf_counter()
    restated, errors = restate(pred, base, points, steps=tto.pbr_fit_steps, lr=tto.pbr_fit_lr,
                               batch=tto.pbr_fit_batch, seed=config.seed)  # fmt: skip
    return restated, {"readout": {k: readout.record.get(k) for k in ("sha256", "basis_id")}, "fit": errors,
                      "seconds": time.perf_counter() - t0}


def _random_prediction(seed: int) -> LMRMPrediction:
    """A random triplane with freshly initialised (seeded, frozen) decoders: the start when no LMRM exists."""
    g = torch.Generator().manual_seed(seed)
    channels, resolution = RANDOM_TRIPLANE
    triplane = Triplane(channels, resolution, init_std=0.1, generator=g)
    torch.manual_seed(seed)
    decs = (MaterialDecoder(triplane.feature_dim), UncertaintyDecoder(triplane.feature_dim),
            PBRDecoder(triplane.feature_dim))  # fmt: skip
    for d in decs:
        d.requires_grad_(False)
    return LMRMPrediction(triplane, *decs)


def _stage_lmrm(capture: Path, work: Path, config: ExtractConfig, progress: Progress | None) -> dict[str, Any]:
    from safetensors.torch import load_file, save_file

    from neumatex_core.lmrm.inference import LMRMError

    out = stage_dir(work, "lmrm")
    device = config.torch_device()
    _emit(progress, "lmrm", 0.0, "loading the LMRM")
    try:
        lmrm: LMRM | None = _load_lmrm(config.lmrm_weights, device)
        readout = _load_lmrm(config.lmrm_readout, device) if config.lmrm_readout else None
    except LMRMError as exc:
        if config.init in ("lmrm", "pbr"):
            raise PipelineError(f"LMRM initialisation needs a trained LMRM checkpoint, which is not available: {exc}. "
                                "Extract with init='random' (--init random) until the checkpoint ships.") from None
        lmrm = None
    if lmrm is not None:
        views = load_file(str(stage_dir(work, "prepare_views") / "views.safetensors"))
        with _open_capture(capture) as cap:
            norm = _normalised(cap, work, device)
            resolution = int(views["display"].shape[1])
            t0 = time.perf_counter()
            pred = lmrm.predict(views["display"].float(), preset_views(resolution), norm.mesh, norm.envmap)
            seconds_predict = time.perf_counter() - t0
            info: dict[str, Any] = {k: lmrm.record.get(k) for k in ("sha256", "basis_id") if k in lmrm.record}
            if readout is not None:
                _emit(progress, "lmrm", 0.3, "restating the prediction through the readout's decoders")
                pred, info["restated"] = _restated(pred, readout, norm, views, config)
        source, trained = "lmrm", True
    else:
        pred = _random_prediction(config.seed)
        source, trained, info, seconds_predict = "random (no trained LMRM)", False, {}, 0.0
    tensors = {"triplane.planes": pred.triplane.planes.detach().cpu().contiguous()}
    decoders = {"material": pred.material_decoder, "uncertainty": pred.uncertainty_decoder, "pbr": pred.pbr_decoder}
    record: dict[str, Any] = {"source": source, "trained": trained, "lmrm": info, "decoders": {}}
    for kind, dec in decoders.items():
        for k, v in dec.state_dict().items():
            tensors[f"decoder.{kind}.{k}"] = v.detach().cpu().float().contiguous()
        record["decoders"][kind] = {"id": module_id(dec), "architecture": dec.architecture()}
    save_file(tensors, str(out / "prediction.safetensors"))
    write_json_atomic(out / "prediction.json", record)
    _emit(progress, "lmrm", 1.0, f"prediction: {source}")
    return {"trained": trained, "source": source, "predict_s": seconds_predict}


def load_prediction(work: Path, device: torch.device | str = "cpu") -> tuple[LMRMPrediction, dict[str, Any]]:
    """The lmrm stage's stored prediction (frozen decoders) and its record."""
    from safetensors.torch import load_file

    folder = stage_dir(work, "lmrm")
    record = json.loads((folder / "prediction.json").read_text())
    tensors = load_file(str(folder / "prediction.safetensors"))
    decs: dict[str, torch.nn.Module] = {}
    for kind, rec in record["decoders"].items():
        dec = DECODERS[kind](**rec["architecture"])
        prefix = f"decoder.{kind}."
        dec.load_state_dict({k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)})
        dec.requires_grad_(False)
        decs[kind] = dec.to(device)
    mat, unc, pbr = decs["material"], decs["uncertainty"], decs["pbr"]
    assert isinstance(mat, MaterialDecoder) and isinstance(unc, UncertaintyDecoder) and isinstance(pbr, PBRDecoder)
    triplane = Triplane.from_planes(tensors["triplane.planes"].to(device))
    triplane.requires_grad_(False)
    return LMRMPrediction(triplane, mat, unc, pbr), record


def _photo_set(norm: _Normalised, device: torch.device) -> PhotoSet:
    return PhotoSet.of_capture(norm.capture, norm.mesh, norm.cameras, device)


def evaluation_only(tto: TTOConfig) -> str:
    """Why the TTO variant `tto` makes no asset (an evaluation variant: `neumatex eval`), or "" when it does."""
    if tto.reg == "oracle":
        return "TTO reg='oracle' needs ground-truth G-buffers; it is an evaluation variant (neumatex eval)"
    if tto.material != "neural":
        return "TTO material='pbr' is the PBR baseline for evaluation; an asset holds a neural material"
    return ""


def effective_tto(config: ExtractConfig, trained: bool) -> TTOConfig:
    """The TTO config actually run: without a trained LMRM there is no anchor, so reg is "none", and no start from
    it to choose (select_lmrm_start off)."""
    tto = config.tto_config()
    return tto if trained else replace(tto, reg="none", select_lmrm_start=False)


def _stage_tto(capture: Path, work: Path, config: ExtractConfig, progress: Progress | None,
               should_stop: ShouldStop | None) -> dict[str, Any]:
    from safetensors.torch import save_file

    out = stage_dir(work, "tto")
    device = config.torch_device()
    pred, record = load_prediction(work, device)
    tto = effective_tto(config, bool(record["trained"]))
    if tto.reg == "oracle":
        raise PipelineError(evaluation_only(tto))
    with _open_capture(capture) as cap:
        norm = _normalised(cap, work, device)
        photos = _photo_set(norm, device)
        tonemap = cap.tonemap
    basis = load_basis(str(device), tto.basis)
    t0 = time.perf_counter()

    def on_step(step: int, total: int, row: dict[str, float]) -> None:
        _emit(progress, "tto", step / total, f"step {step}/{total} loss {row['loss']:.4g} PSNR {row['psnr']:.2f} dB",
              row)

    result = solve(tto, norm.mesh, norm.envmap, photos, tonemap, pred, basis, anchor_available=bool(record["trained"]),
                   progress=on_step, should_stop=should_stop, checkpoint_dir=out)  # fmt: skip
    if not result.finished:
        raise Cancelled(f"stopped at TTO step {result.steps_done}/{tto.steps}; the checkpoint {out / 'checkpoint.pt'} "
                        "resumes it")  # fmt: skip
    save_file(_parametrisation_tensors(result.params), str(out / "result.safetensors"))
    if result.pbr_solution is not None:  # a candidate for the asset's PBR fallback (export: `choose_fallback`)
        save_file(_parametrisation_tensors(result.pbr_solution), str(out / PBR_SOLUTION_FILE))
    write_json_atomic(out / "history.json", result.history)
    stops = {}
    if result.exposure is not None:  # TTOConfig.photo_exposure: the fitted multipliers, read by the export stage
        write_json_atomic(out / EXPOSURE_FILE, result.exposure)
        stops = {"exposure_stops_max": max(abs(math.log2(e)) for e in result.exposure)}
    tail = result.history[-max(1, len(result.history) // 10):]
    return {**stops, "steps": result.steps_done, "loss": float(np.mean([r["loss"] for r in tail])),
            "psnr_batch": float(np.mean([r["psnr"] for r in tail])), "photo_pixels": photos.size,
            "tto_s": time.perf_counter() - t0, "field": tto.field, "init": tto.init, "reg": tto.reg,
            "material": tto.material, "variation": config.variation,
            "basis": (result.basis or basis).basis_id, **result.selection}  # fmt: skip


EXPOSURE_FILE = "exposure.json"  # in the tto stage's folder: the fitted per-photo exposure multipliers
PBR_SOLUTION_FILE = "pbr_solution.safetensors"  # in the tto stage's folder: the PBR phase's planes (and decoder)


DecoderT = TypeVar("DecoderT", bound=torch.nn.Module)


def _parametrisation_tensors(params: Parametrisation) -> dict[str, torch.Tensor]:
    """What a TTO result is stored as: "tensor" (its planes or texture) and, where the TTO fine-tuned a copy of
    its decoder (TTOConfig.train_decoder), that decoder's weights as "decoder.<name>"."""
    tensors = {"tensor": params.tensor.detach().cpu().contiguous()}
    tuned = params.trained_decoder()
    if tuned is not None:
        for k, v in tuned.state_dict().items():
            tensors[f"decoder.{k}"] = v.detach().cpu().float().contiguous()
    return tensors


def _stored_decoder(stored: dict[str, torch.Tensor], decoder: DecoderT, device: torch.device) -> DecoderT:
    """`decoder`, or a frozen copy of it with the fine-tuned weights that `stored` holds
    (`_parametrisation_tensors`)."""
    tuned = {k.removeprefix("decoder."): v.to(device) for k, v in stored.items() if k.startswith("decoder.")}
    if not tuned:
        return decoder
    decoder = copy.deepcopy(decoder)
    decoder.load_state_dict(tuned)
    decoder.requires_grad_(False)
    return decoder


def fitted_exposures(work: Path) -> list[float] | None:
    """The per-photo exposure multipliers the TTO fitted (TTOConfig.photo_exposure; on top of the frames' given
    exposures, geometric mean 1), or None when it fitted none."""
    path = stage_dir(work, "tto") / EXPOSURE_FILE
    return [float(e) for e in json.loads(path.read_text())] if path.is_file() else None


def photo_tonemap(cap: Capture, i: int, fitted: list[float] | None = None) -> Tonemap:
    """The tonemap photo i was taken with: the capture's, times the frame's given exposure, times the TTO's fitted
    one when there is one (`fitted_exposures`)."""
    tonemap = cap.tonemap_of(i)
    return tonemap if fitted is None else replace(tonemap, exposure=tonemap.exposure * fitted[i])


def _gbuffer_images(field_gbuffer: Callable[[torch.Tensor], torch.Tensor], mesh: Mesh, camera: Camera,
                    unc: Callable[[torch.Tensor], torch.Tensor] | None) -> list[tuple[str, np.ndarray]]:
    gb = render_gbuffer(mesh, camera)
    idx = gb.mask.reshape(-1)
    h, w = camera.height, camera.width

    def image(values: torch.Tensor) -> np.ndarray:
        full = torch.ones(h * w, 3)
        full[idx] = values.detach().cpu().float()
        return full.reshape(h, w, 3).numpy()

    with torch.no_grad():
        pts = gb.position.reshape(-1, 3)[idx]
        g = field_gbuffer(pts).cpu()
        items = [("base colour", image(g[:, :3] ** (1 / 2.2))), ("latent 0-2", image((g[:, 3:6] + 1) / 2)),
                 ("latent 3-5", image((g[:, 6:9] + 1) / 2))]  # fmt: skip
        if unc is not None:
            from neumatex_core.report_images import colour_bar, scalar_map

            sd = torch.zeros(h * w)
            sd[idx] = torch.exp(0.5 * unc(pts).cpu()).mean(-1).float()
            sd_img, lo, hi = scalar_map(sd.reshape(h, w).numpy(), idx.reshape(h, w).cpu().numpy())
            items.append((f"std, mean over channels ({lo:.3g} to {hi:.3g})", sd_img))
            items.append((f"std colour scale: bottom {lo:.3g}, top {hi:.3g}", colour_bar(h, w)))
    return items


def _comparison_row(index: int, photo: np.ndarray, neural: np.ndarray, pbr: np.ndarray, psnr_neural: float,
                    psnr_pbr: float) -> list[tuple[str, np.ndarray]]:
    """One report row per photo: the photo, both re-renders with their PSNR (dB) and the gain, and x4 differences.

    Images [H, W, 3] display-referred in [0, 1]."""
    from neumatex_core.report_images import difference_image

    gain = psnr_neural - psnr_pbr
    return [(f"photo {index}", photo), (f"neural {index}: {psnr_neural:.2f} dB ({gain:+.2f} dB vs PBR)", neural),
            (f"PBR fallback {index}: {psnr_pbr:.2f} dB", pbr),
            (f"|neural - photo| x4, view {index}", difference_image(neural, photo)),
            (f"|PBR - photo| x4, view {index}", difference_image(pbr, photo))]  # fmt: skip


def _report_columns(sections: dict[str, list[tuple[str, np.ndarray]]]) -> dict[str, int]:
    """Grid columns per report section: 5 for the photo comparisons (one photo per row), 4 elsewhere."""
    return {name: 5 if name.startswith("Photo |") else 4 for name in sections}


def _stage_export(capture: Path, work: Path, config: ExtractConfig, progress: Progress | None) -> dict[str, Any]:
    from safetensors.torch import load_file

    from neumatex_core.assets import asset_from_textures, asset_from_triplane, write_asset
    from neumatex_core.assets.render import make_previews, render_asset, render_neural_and_pbr
    from neumatex_core.assets.uv_unwrap import unwrap
    from neumatex_core.eval.metrics import psnr
    from neumatex_core.fields.neural_field import TriplaneMaterialField
    from neumatex_core.render.path_tracer import PathTracerConfig
    from neumatex_core.report import ReportContent, write_report
    from neumatex_core.report_relight import relight_map_path, relit_images

    device = config.torch_device()
    pred, record = load_prediction(work, device)
    tto = effective_tto(config, bool(record["trained"]))
    if tto.material != "neural":
        raise PipelineError(evaluation_only(tto))
    stored = load_file(str(stage_dir(work, "tto") / "result.safetensors"))
    tensor = stored["tensor"].to(device)
    history = json.loads((stage_dir(work, "tto") / "history.json").read_text())
    stage_metrics = {s: read_done(work, s) for s in STAGES[:-1]}
    timings = {f"{s}_s": float(m.get("seconds", 0.0)) for s, m in stage_metrics.items()}
    timings.update({f"{s}_cpu_s": float(m.get("cpu_seconds", 0.0)) for s, m in stage_metrics.items()})
    # the basis the TTO's result is in: the config's, or the alternative it chose (TTOConfig.alternative_basis)
    basis = load_basis(str(device), str(stage_metrics["tto"].get("basis", tto.basis)))
    # resized where the basis's latent size is not 6; the TTO's fine-tuned copy where it made one
    material_decoder = _stored_decoder(stored, decoder_for(pred.material_decoder, basis), device)
    with _open_capture(capture) as cap:
        norm = _normalised(cap, work, device)
        name = config.name or cap.root.name
        provenance = {"capture": str(capture), "frames": len(cap.frames), "preset": config.preset_name,
                      "prediction": record["source"], "tto": tto.to_dict(),
                      "views": stage_metrics["prepare_views"].get("source", "")}  # fmt: skip
        _emit(progress, "export", 0.05, "baking textures and fitting the PBR fallback")
        metrics = {"tto_loss": float(stage_metrics["tto"]["loss"]),
                   "tto_psnr_batch": float(stage_metrics["tto"]["psnr_batch"]),
                   "tto_steps": float(stage_metrics["tto"]["steps"])}  # fmt: skip
        if tto.field == "triplane":
            triplane = Triplane.from_planes(tensor)
            triplane.requires_grad_(False)
            field_ = TriplaneMaterialField(triplane, material_decoder, basis)
            extra: dict[str, torch.nn.Module] = {"uncertainty": pred.uncertainty_decoder, "pbr": pred.pbr_decoder}
            asset = asset_from_triplane(name, norm.mesh, field_, config.texture_resolution, extra_decoders=extra,
                                        provenance=provenance, metrics=metrics, timings=timings)  # fmt: skip

            def gbuffer(p: torch.Tensor) -> torch.Tensor:
                return torch.cat(field_.gbuffer(p.to(device)), dim=-1)
        else:
            mesh = norm.mesh if norm.mesh.vertex_normals is not None else norm.mesh.with_smooth_normals()
            uv_mesh = unwrap(mesh, tto.uv_resolution)
            asset = asset_from_textures(name, uv_mesh, tensor.detach(), basis, provenance=provenance, metrics=metrics,
                                        timings=timings)  # fmt: skip
            gbuffer = None  # type: ignore[assignment]
        asset.centre, asset.scale = [float(c) for c in norm.centre], float(norm.scale)
        solution_file = stage_dir(work, "tto") / PBR_SOLUTION_FILE
        held_out = _held_out_frames(norm, tto, stage_metrics["tto"])
        if solution_file.is_file() and held_out:
            _emit(progress, "export", 0.3, f"choosing the PBR fallback on {len(held_out)} held-out photos")
            stored_pbr = load_file(str(solution_file))
            solution = PBRTriplane(Triplane.from_planes(stored_pbr["tensor"].to(device)),
                                   _stored_decoder(stored_pbr, pred.pbr_decoder, device))  # fmt: skip
            asset = choose_fallback(asset, solution, _photo_set(norm, device).subset(held_out), norm.envmap,
                                    cap.tonemap, tto)  # fmt: skip
        _emit(progress, "export", 0.4, "rendering previews")
        make_previews(asset, norm.envmap, config.preview_resolution, config.preview_spp, tonemap=cap.tonemap)
        fitted = fitted_exposures(work)
        photo_items: list[tuple[str, np.ndarray]] = []
        n_eval = min(config.eval_photos, len(cap.frames))
        if n_eval:
            _emit(progress, "export", 0.6, f"re-rendering {n_eval} photos")
            picks = np.linspace(0, len(cap.frames) - 1, n_eval).round().astype(int).tolist()
            cams = [norm.cameras[i] for i in picks]
            eval_tracer = PathTracerConfig(spp=config.eval_spp, max_bounces=max(tto.max_bounces, 2))
            renders, pbr_renders = render_neural_and_pbr(asset, norm.envmap, cams, eval_tracer, seed=config.seed)
            scores, pbr_scores = [], []
            for i, img, pbr_img in zip(picks, renders, pbr_renders, strict=True):
                photo = torch.as_tensor(cap.load_image(i))
                tonemap = photo_tonemap(cap, i, fitted)  # the photo's own exposure (given, and fitted by TTO)
                shown, pbr_shown = tonemap.apply(img.cpu()), tonemap.apply(pbr_img.cpu())
                m = render_gbuffer(norm.mesh, norm.cameras[i]).mask
                user = cap.load_mask(i)
                if user is not None:
                    m = m & torch.as_tensor(user)
                scores.append(psnr(shown, photo, m))
                pbr_scores.append(psnr(pbr_shown, photo, m))
                photo_items += _comparison_row(i, photo.numpy(), shown.numpy(), pbr_shown.numpy(),
                                               float(scores[-1]), float(pbr_scores[-1]))  # fmt: skip
            asset.metrics["psnr_photos"] = float(np.mean(scores))
            asset.metrics["psnr_photos_pbr"] = float(np.mean(pbr_scores))
            asset.metrics["psnr_gain_db"] = asset.metrics["psnr_photos"] - asset.metrics["psnr_photos_pbr"]
            asset.metrics["psnr_photos_spp"] = float(config.eval_spp)
        out = stage_dir(work, "export")
        target = out / ASSET_DIR
        _emit(progress, "export", 0.8, "writing the asset")
        write_asset(asset, target, overwrite=True)
        sections: dict[str, list[tuple[str, np.ndarray]]] = {
            "Preview renders (neural field, then PBR fallback)": sorted(asset.previews.items()),
            "Photo | neural | PBR fallback | |neural - photo| x4 | |PBR - photo| x4 (PSNR in dB)": photo_items,
        }
        relight_path = relight_map_path(cap.root / "envmap.exr")
        if relight_path is not None:
            _emit(progress, "export", 0.85, f"relighting under {relight_path.name}")
            relight_cams = [preset_views(config.preview_resolution)[v] for v in (0, 4)]

            def render_views(envmap: EnvironmentMap) -> list[tuple[int, np.ndarray]]:
                imgs = render_asset(asset, envmap, relight_cams, PathTracerConfig(spp=config.preview_spp,
                                    max_bounces=3), seed=config.seed)  # fmt: skip
                return [(v, cap.tonemap.apply(img.cpu()).numpy()) for v, img in zip((0, 4), imgs, strict=True)]

            sections["Relit (neural material under another shared map)"] = relit_images(render_views, relight_path,
                                                                                        str(device))
        if gbuffer is not None:
            def lmrm_unc(p: torch.Tensor) -> torch.Tensor:
                return pred.uncertainty_decoder(pred.triplane.features(p.to(device)))

            unc = lmrm_unc if record["trained"] else None
            def lmrm_gbuffer(p: torch.Tensor) -> torch.Tensor:
                return torch.cat(pred.material_decoder(pred.triplane.features(p.to(device))), dim=-1)

            gb_items = []
            for v in (0, 4):
                cam = preset_views(config.preview_resolution)[v]
                gb_items += [(f"view {v} ours {c}", img) for c, img in _gbuffer_images(gbuffer, norm.mesh, cam, None)]
                if record["trained"]:
                    gb_items += [(f"view {v} LMRM {c}", img)
                                 for c, img in _gbuffer_images(lmrm_gbuffer, norm.mesh, cam, unc)]  # fmt: skip
            sections["Material G-buffers (ours after TTO; the LMRM's prediction and uncertainty)"] = gb_items
        run_line = (f"Ran: preset {config.preset_name}, {tto.run_steps()} TTO steps, "
                    f"{sum(v for k, v in timings.items() if not k.endswith('_cpu_s')):.0f} s before export; "
                    f"neural {asset.metrics.get('psnr_photos', float('nan')):.2f} dB vs PBR fallback "
                    f"{asset.metrics.get('psnr_photos_pbr', float('nan')):.2f} dB on the photos.")  # fmt: skip
        notes = [run_line, f"Capture {capture}; {len(cap.frames)} photos; preset views: {provenance['views']}.",
                 f"Prediction: {record['source']}; TTO {tto.steps} steps"
                 + (f" after {tto.pbr_steps} PBR steps" if tto.init == "pbr" else "")
                 + f" of {tto.pixels} pixels x {tto.spp} spp, {tto.max_bounces} bounces; field {tto.field}, "
                 f"init {tto.init}, reg {tto.reg}; material variation {config.variation}"
                 + _choice_note(stage_metrics["tto"]) + _basis_note(stage_metrics["tto"]) + "."]  # fmt: skip
        fallback_note = _fallback_note(asset.metrics)
        if fallback_note:
            notes.append(fallback_note)
        if not record["trained"]:
            notes.append("No trained LMRM checkpoint was available: the triplane started from random values and the "
                         "TTO ran without the uncertainty regulariser.")  # fmt: skip
        report = write_report(ReportContent(f"NeuMatEx extraction: {name}", sections, history, asset.metrics,
                                            asset.timings, {"preset": config.preset_name, **tto.to_dict()}, notes,
                                            asset.metrics.get("psnr_photos_pbr"), _report_columns(sections),
                                            fitted),
                              target / "report")  # fmt: skip
    return {**asset.metrics, "asset": str(target), "report": str(report)}


def _held_out_frames(norm: _Normalised, tto: TTOConfig, tto_metrics: dict[str, Any]) -> list[int]:
    """The photos the TTO's choice held out (`validation_frames`, as `solve` picked them), [] where none were."""
    if not tto_metrics.get("validation_photos"):
        return []
    return validation_frames(norm.cameras, tto.validation_photos, norm.mesh.bounding_sphere()[0])


def _fallback_note(metrics: dict[str, float]) -> str:
    """The report's words for how the PBR fallback was chosen (`choose_fallback`), or "" when it was not."""
    if "fallback_from_pbr_phase" not in metrics:
        return ""
    scores = (f"the fit to the neural material {metrics['fallback_psnr_fit']:.2f} dB, the TTO's PBR phase "
              f"{metrics['fallback_psnr_pbr_phase']:.2f} dB on the held-out photos")
    kept = "the TTO's PBR phase" if metrics["fallback_from_pbr_phase"] else "the fit to the neural material"
    return f"PBR fallback: {kept} ({scores})."


def _choice_note(tto_metrics: dict[str, Any]) -> str:
    """The report's words for the choice the TTO made on held-out photos (TTOConfig.select_uniform /
    select_anchor, and select_basis's other basis, recorded in the tto stage's metrics), that variation "choose" was
    "textured" for want of a PBR start, or "" when there was no choice."""
    choice = next((c for c in CHOICES.values() if c.kept_key in tto_metrics), None)
    if choice is None:
        return " (textured: without the PBR start there is nothing to choose from)" if tto_metrics.get(
            "variation") == "choose" else ""
    a, b = choice.names
    if not tto_metrics["validation_photos"]:
        return f" ({choice.names[choice.fallback]}: the capture has no photos to hold out and choose on)"

    def scores(prefix: str) -> str:  # one basis's candidates' held-out scores
        return f"{a} {tto_metrics[prefix + a]:.2f} dB, {b} {tto_metrics[prefix + b]:.2f} dB"

    def kept(prefix: str) -> str:
        return a if tto_metrics[prefix + choice.kept_key] else b

    held = f"{tto_metrics['validation_photos']:.0f} held-out photos"
    if not tto_metrics.get("select_basis_taken"):
        tried = ("select_basis_taken" in tto_metrics and f"; in the other basis tried {scores('select_basis_psnr_')}"
                 ) or ""
        return f" ({kept('')} chosen on {held}: {scores('validation_psnr_')}{tried})"
    return (f" ({kept('select_basis_')} in this basis chosen on {held}: {scores('select_basis_psnr_')}; in the "
            f"configured basis {scores('validation_psnr_')})")


def _basis_note(tto_metrics: dict[str, Any]) -> str:
    """The report's words for the neural basis the TTO ran in and why: with TTOConfig.alternative_basis the photo
    PSNR of the PBR solution and of its start in each basis tried (tto/pbr_start.py `choose_basis`); with
    select_basis taken, that its candidates won on the held-out photos (`_choice_note` gives the scores)."""
    if "basis" not in tto_metrics:
        return ""
    note = f"; neural basis {tto_metrics['basis']}"
    if tto_metrics.get("select_basis_taken"):
        note += ", taken because its candidates reproduced the held-out photos better"
    if "basis_switched" not in tto_metrics:
        return note
    pbr, own = tto_metrics["basis_pbr_psnr"], tto_metrics["basis_start_psnr"]
    if tto_metrics.get("select_basis_taken"):
        other = tto_metrics.get("basis_alternative_psnr")
        tried = "" if other is None else f", in the alternative {other:.2f} dB"
        return (f"{note} (the PBR solution {pbr:.2f} dB on the scoring photos, its start in the configured basis "
                f"{own:.2f} dB{tried})")
    if tto_metrics["basis_switched"]:
        return (f"{note}, chosen because the PBR solution ({pbr:.2f} dB on the scoring photos) expressed in it "
                f"scored {tto_metrics['basis_alternative_psnr']:.2f} dB and in the configured basis {own:.2f} dB")
    tried = ("basis_alternative_psnr" in tto_metrics
             and f", the alternative's {tto_metrics['basis_alternative_psnr']:.2f} dB") or ""
    return f"{note} (the PBR solution {pbr:.2f} dB on the scoring photos, its start in this basis {own:.2f} dB{tried})"


_RUNNERS: dict[str, Callable[..., dict[str, Any]]] = {
    "validate": _stage_validate,
    "prepare_views": _stage_prepare_views,
    "lmrm": _stage_lmrm,
    "export": _stage_export,
}


def run_stage(stage: str, capture: Path, work: Path, config: ExtractConfig, progress: Progress | None = None,
              should_stop: ShouldStop | None = None) -> dict[str, Any]:
    """Run one stage (see the module docstring); returns its metrics (stored in work/<stage>/done.json).

    Idempotent: a finished stage returns its stored metrics. Raises PipelineError for bad input or missing earlier
    stages, Cancelled when should_stop() is true."""
    if stage not in STAGES:
        raise PipelineError(f"unknown stage {stage!r} (expected one of {', '.join(STAGES)})")
    capture, work = Path(capture), Path(work)
    if is_done(work, stage):
        return read_done(work, stage)
    _require(work, *STAGES[:STAGES.index(stage)])
    if should_stop is not None and should_stop():
        raise Cancelled(f"stopped before stage {stage!r}")
    stage_dir(work, stage).mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        if stage == "tto":
            metrics = _stage_tto(capture, work, config, progress, should_stop)
        else:
            metrics = _RUNNERS[stage](capture, work, config, progress)
    except (PipelineError, Cancelled):
        raise
    except (ValueError, OSError) as exc:  # our loaders' errors (CaptureError, MeshError, ...) name the file
        raise PipelineError(f"stage {stage}: {exc}") from exc
    metrics["seconds"] = time.perf_counter() - t0
    metrics["cpu_seconds"] = time.process_time() - c0  # all threads: the wall time on an idle machine is about
    # cpu_seconds / threads, whatever else the machine ran meanwhile
    if stage == "tto":
        metrics["minutes"] = metrics["seconds"] / 60
    _mark_done(work, stage, metrics)
    _emit(progress, stage, 1.0, f"{stage} done in {metrics['seconds']:.1f} s", _numbers(metrics))
    return metrics


def _numbers(metrics: dict[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items() if isinstance(v, int | float) and math.isfinite(float(v))}


WORK_CONFIG = "config.json"


def _check_work_config(work: Path, config: ExtractConfig) -> None:
    """Resuming is only sound with the configuration the finished stages were made with: the first `extract` into
    `work` records it (device aside: a run may resume on another device); a later one with other settings is refused
    with the differences named, rather than silently mixing stages made under two configurations."""
    current = {k: v for k, v in config.to_dict().items() if k != "device"}
    record = work / WORK_CONFIG
    if record.is_file():
        try:
            stored = json.loads(record.read_text())
        except ValueError:
            stored = None
        if stored is not None and stored != current and any(is_done(work, s) for s in STAGES):
            diff = sorted(k for k in set(stored) | set(current) if stored.get(k) != current.get(k))
            raise PipelineError(f"{work}: its finished stages were made with other settings ({', '.join(diff)} "
                                "differ); delete the folder to start over, or give another work folder")
    record.write_text(json.dumps(current, indent=1, sort_keys=True))


def default_work(out: Path) -> Path:
    """The work folder of an extraction into `out` when none is given: a sibling `.<name>.work`."""
    out = Path(out)
    return out.parent / f".{out.name}.work"


def extract(capture: Path, out: Path, config: ExtractConfig, progress: Progress | None = None,
            should_stop: ShouldStop | None = None, work: Path | None = None) -> Path:
    """Run every stage in order (finished ones are skipped), then copy the asset to `out` (a folder, or a .zip
    when out ends in .zip); returns out."""
    capture, out = Path(capture), Path(out)
    work = Path(work) if work is not None else default_work(out)
    work.mkdir(parents=True, exist_ok=True)
    _check_work_config(work, config)
    for stage in STAGES:
        run_stage(stage, capture, work, config, progress, should_stop)
    source = asset_path(work)
    if not (source / "manifest.json").is_file():
        raise PipelineError(f"{source}: the export stage finished but its asset is missing; delete "
                            f"{stage_dir(work, 'export') / DONE} to re-export")  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        if out.suffix.lower() == ".zip":
            made = Path(shutil.make_archive(str(tmp / "asset"), "zip", root_dir=source))
        else:
            made = tmp / "asset"
            shutil.copytree(source, made)
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.replace(made, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out
