"""Where the time of `make demo` goes: the demo's extraction (examples/coat-teapot, cpu preset, the LMRM's PBR start
when the shipped checkpoint loads, as `neumatex extract --init auto`) run stage by stage in one process, the TTO
timed by part.

    .venv/bin/python bench/demo.py [--capture examples/coat-teapot] [--threads 0]

The TTO's parts are timed by wrapping tto/pbr_start.py's functions: the PBR phase, the start fits (the PBR
solution expressed in a basis, `fit_start`), the choices' clean scores on held-out photos (`photo_psnr`) and the
neural phases (the two candidates', then the final one). Reference measured in the same run: forward and backward
of a 4 x 64 SiLU MLP (the basis decoder's shape) on 65,536 rows, the operation most of the TTO's time goes to
(linear and SiLU layers and their backward passes); the demo's time in those units compares machines, which differ
by 1.4x in seconds for the same code (docs/design-notes.md item 43). Prints the seconds per stage and part, the
ratio, and the result (the neural material's PSNR gain over its PBR fallback on the photos), and appends a JSON
line to bench/results/demo.jsonl. `make demo` adds about 3 s (make, the CLI's start and imports).
"""

from __future__ import annotations

import functools
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, time_repeats, write_result  # noqa: E402

from neumatex_core.extract_cli import lmrm_available  # noqa: E402
from neumatex_core.materials.neural_basis import mlp  # noqa: E402
from neumatex_core.pipeline import STAGES, ExtractConfig, run_stage  # noqa: E402
from neumatex_core.tto import pbr_start  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
TTO_PARTS = {"_pbr_phase": "pbr_phase", "fit_start": "start_fits", "photo_psnr": "choice_scores",
             "_neural_phase": "neural_phases"}  # fmt: skip
REFERENCE_ROWS = 1 << 16


def reference_mlp() -> Callable[[], None]:
    """Forward + backward of a 4 x 64 SiLU MLP (17 inputs, 3 outputs: the basis decoder's shape) on 65,536 rows."""
    g = torch.Generator().manual_seed(0)
    net = mlp(17, [64, 64, 64, 64], 3)
    x = torch.rand(REFERENCE_ROWS, 17, generator=g).requires_grad_(True)

    def run() -> None:
        net.zero_grad(set_to_none=True)
        x.grad = None
        net(x).square().mean().backward()

    return run


def timed_parts(times: dict[str, list[float]]) -> Callable[[], None]:
    """Wrap the TTO's parts (TTO_PARTS) so each call's seconds land in `times`; returns the undo."""
    originals = {name: getattr(pbr_start, name) for name in TTO_PARTS}

    def wrap(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def run(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                times.setdefault(TTO_PARTS[name], []).append(time.perf_counter() - start)
        return run

    def undo() -> None:
        for name, fn in originals.items():
            setattr(pbr_start, name, fn)

    for name, fn in originals.items():
        setattr(pbr_start, name, wrap(name, fn))
    return undo


def main() -> int:
    ap = argument_parser(__doc__)
    ap.add_argument("--capture", default=str(REPO / "examples" / "coat-teapot"))
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default, as `make demo`)")
    args = ap.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    capture = Path(args.capture)
    init = "pbr" if lmrm_available("auto") else "random"
    config = ExtractConfig.preset("cpu", init=init, device="auto", seed=0)
    reference = time_repeats(reference_mlp(), repeats=5, warmup=2)
    parts: dict[str, list[float]] = {}
    stages: dict[str, float] = {}
    metrics: dict[str, dict[str, Any]] = {}
    work = Path(tempfile.mkdtemp(prefix="bench-demo-"))
    undo = timed_parts(parts)
    try:
        def extract() -> None:
            for stage in STAGES:
                start = time.perf_counter()
                metrics[stage] = run_stage(stage, capture, work, config)
                stages[stage] = time.perf_counter() - start
                print(f"  {stage}: {stages[stage]:.1f} s", flush=True)

        run = time_repeats(extract, repeats=1)
    finally:
        undo()
        shutil.rmtree(work, ignore_errors=True)
    gain = float(metrics["export"]["psnr_gain_db"])
    total, ref = run["min"], reference["min"]
    record = {
        "config": {"capture": str(capture), "preset": "cpu", "init": init, "threads": torch.get_num_threads()},
        "extract_s": total, "stages_s": stages, "tto_parts_s": {k: sum(v) for k, v in parts.items()},
        "tto_part_calls_s": parts, "psnr_gain_db": gain, "reference_mlp_s": ref,
        "ratio_to_reference": total / ref, "foreign_cpu": run["foreign_cpu"],
    }  # fmt: skip
    path = write_result("demo", record)
    split = ", ".join(f"{k} {sum(v):.0f} s ({len(v)})" for k, v in parts.items())
    print(f"demo extraction ({init} start, {torch.get_num_threads()} threads): {total:.0f} s = {total / 60:.2f} min "
          f"(stages: {', '.join(f'{k} {v:.0f} s' for k, v in stages.items())}); TTO parts (calls): {split}; "
          f"neural {gain:+.2f} dB over its PBR fallback. Reference: the 4 x 64 MLP's forward and backward on "
          f"{REFERENCE_ROWS} rows takes {ref * 1e3:.1f} ms here, so the extraction costs {total / ref:.0f} of them "
          f"(other processes kept {run['foreign_cpu'][0]} of the CPUs busy)")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
