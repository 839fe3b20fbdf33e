"""`neumatex extract`: a capture -> a neural material asset through `pipeline.extract`, with a progress bar.

Ctrl-C asks the pipeline to stop (the TTO checkpoints between steps); finished stages stay in the work folder and
rerunning the same command resumes. A second Ctrl-C interrupts at once (finished stages are still kept).
"""

from __future__ import annotations

import signal
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from types import FrameType
from typing import Any, Literal

import torch

from neumatex_core.config import option


@dataclass
class ExtractCommandConfig:
    """`neumatex extract`: extract a neural material asset (latent textures + universal basis) from a capture:
    validate, prepare the 23 preset views, LMRM prediction, test-time optimisation through the path tracer, export
    (asset package + HTML report in ASSET/report/index.html). Interrupt with Ctrl-C; rerun to resume."""

    capture: str = option("", "capture folder, transforms.json or .zip", positional=True)
    out: str = option("", "output asset folder (or .zip)")
    preset: Literal["cpu", "gpu", "tiny"] = option("cpu", "cpu: minutes on 2 cores; gpu: quality; tiny: seconds")
    work: str = option("", "folder for the stages' outputs (default: .<out name>.work beside --out); keep it to resume")
    init: Literal["auto", "lmrm", "pbr", "random"] = option(
        "auto", "start the neural TTO from a PBR fit (pbr: the PBR TTO from the LMRM's PBR head first; the best "
        "measured), from the LMRM's prediction (lmrm) or a random triplane; pbr and lmrm fail without a usable LMRM "
        "checkpoint; auto: pbr when the LMRM checkpoint loads, else random (and says so)")
    variation: Literal["default", "textured", "uniform", "choose"] = option(
        "default", "how the object's material varies over its surface: choose (both tried, in the configured basis "
        "and in basis v6, 4 held-out photos decide; ~2x the TTO time), textured (several materials or textures) or "
        "uniform (one material all over: a coat, a sheen; its base colour is kept even over the surface); uniform and "
        "choose need the PBR start (--init pbr or auto; choose is textured without it); default: the extract "
        "config's (choose)")
    threads: int = option(1, "torch CPU threads (0: torch's default); one is fastest on a shared machine")
    steps: int = option(0, "neural TTO steps (0: the preset's)")
    photo_exposure: bool = option(False, "fit each photo's exposure in TTO (hand-held photos; docs/capture-format.md)")
    device: Literal["auto", "cpu", "cuda"] = option("auto", "torch device")
    seed: int = option(0, "random seed")
    progress: bool = option(True, "show a progress bar")
    compare_pbr: bool = option(False, "also run the PBR baseline's TTO (eval variant 'pbr', as many steps) and write "
                               "its photo PSNR beside the neural one in the asset's metrics and report")
    allow_outside_paths: bool = option(False, "the capture folder's transforms.json may name files outside it (e.g. "
                                       "../mesh.obj shared by several captures; never for zips or uploads)")


def lmrm_available(device: str = "auto") -> bool:
    """Whether the shipped LMRM checkpoint loads (present, intact, made for this basis and this code)."""
    from neumatex_core.device import resolve_device
    from neumatex_core.lmrm import LMRMError, load_lmrm

    try:
        load_lmrm(resolve_device(device))
    except LMRMError:
        return False
    return True


def run_extract(cfg: ExtractCommandConfig) -> int:
    from tqdm import tqdm

    from neumatex_core.pipeline import Cancelled, ExtractConfig, PipelineError, StageProgress, default_work, extract

    if not cfg.capture or not cfg.out:
        raise ValueError("give the capture and the output: neumatex extract CAPTURE --out ASSET")
    if cfg.compare_pbr and Path(cfg.out).suffix.lower() == ".zip":
        raise ValueError("--compare-pbr writes its scores into an asset folder: give --out a folder, not a .zip")
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    init = cfg.init
    if init == "auto":
        init = "pbr" if lmrm_available(cfg.device) else "random"
        if init == "random":
            print("note: no usable LMRM checkpoint; starting from a random triplane (--init random)", file=sys.stderr)
    variation = {} if cfg.variation == "default" else {"variation": cfg.variation}
    config = ExtractConfig.preset(cfg.preset, init=init, device=cfg.device, seed=cfg.seed, **variation)
    if cfg.steps:  # the neural TTO's steps, as given (not scaled by the preset's neural_steps_scale)
        config = replace(config, neural_steps_scale=1.0, tto=replace(config.tto, steps=cfg.steps))
    if cfg.photo_exposure:
        config = replace(config, tto=replace(config.tto, photo_exposure=cfg.photo_exposure))
    config.check()
    out = Path(cfg.out)
    work = Path(cfg.work) if cfg.work else default_work(out)
    state: dict[str, Any] = {"stop": False, "bar": None, "stage": None}

    def on_sigint(signum: int, frame: FrameType | None) -> None:
        if state["stop"]:
            raise KeyboardInterrupt
        state["stop"] = True
        print("\nstopping after the current step (Ctrl-C again to interrupt at once) ...", file=sys.stderr)

    def progress(p: StageProgress) -> None:
        if not cfg.progress:
            return
        tto = p.stage == "tto"
        if state["stage"] != p.stage:
            if state["bar"] is not None:
                state["bar"].close()
            total = config.tto_config().run_steps() if tto else 100
            # initial: a resumed TTO starts at its checkpoint's step, so the rate and ETA count only new steps
            state["bar"] = tqdm(total=total, initial=round(p.fraction * total), desc=p.stage,
                                unit="step" if tto else "%", file=sys.stderr)  # fmt: skip
            state["stage"] = p.stage
        bar = state["bar"]
        bar.update(round(p.fraction * bar.total) - bar.n)
        if tto and "step" in p.metrics:
            bar.set_postfix(loss=f"{p.metrics['loss']:.4g}", psnr=f"{p.metrics['psnr']:.2f}")
        else:
            bar.set_postfix_str(p.message[:60])

    from neumatex_core.capture.loader import allow_outside_paths

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        with allow_outside_paths(cfg.allow_outside_paths):
            path = extract(Path(cfg.capture), out, config, progress, lambda: bool(state["stop"]), work)
    except Cancelled as exc:
        print(f"stopped: {exc}. Finished stages are in {work}; rerun the same command to resume.", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print(f"interrupted. Finished stages are in {work}; rerun the same command to resume.", file=sys.stderr)
        return 130
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        signal.signal(signal.SIGINT, previous)
        if state["bar"] is not None:
            state["bar"].close()
    from neumatex_core.pipeline import read_done

    metrics = read_done(work, "export")
    if cfg.compare_pbr:
        from neumatex_core.compare_pbr import compare_pbr

        print("running the PBR baseline's TTO (--compare-pbr) ...", file=sys.stderr)
        try:
            with allow_outside_paths(cfg.allow_outside_paths):
                added = compare_pbr(Path(cfg.capture), path, work, config)
        except PipelineError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(f"PBR baseline TTO ({int(added['pbr_baseline_steps'])} steps): photo PSNR "
              f"{added['psnr_photos_pbr_baseline']:.2f} dB (neural {metrics.get('psnr_photos', float('nan')):.2f} dB)")
    tto = read_done(work, "tto")
    print(f"wrote {path} (report: {path / 'report' / 'index.html' if path.is_dir() else 'inside the zip'}); "
          f"TTO {config.tto_config().run_steps()} steps in {tto['minutes']:.2f} min, photo PSNR "
          f"{metrics.get('psnr_photos', float('nan')):.2f} dB")
    return 0
