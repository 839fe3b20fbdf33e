"""Small helpers shared by the benchmarks: machine info, timing, and one JSON line per run.

Each benchmark appends one JSON object per run to `bench/results/<name>.jsonl`, with the time (UTC, ISO
8601), the git commit of the working tree (None outside a git checkout; `dirty` says whether files differ
from it), the machine (CPU count and model, torch version and threads, device) and the benchmark's own
figures.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import statistics
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"
REPO_ROOT = Path(__file__).resolve().parent.parent


def git_commit() -> dict[str, Any]:
    """{"commit": HEAD's hash or None, "dirty": uncommitted changes (None when unknown)}."""
    def _git(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout.strip() if out.returncode == 0 else None

    commit = _git("rev-parse", "HEAD")
    status = _git("status", "--porcelain") if commit else None
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux, else platform.processor())."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine_info(device: str = "cpu") -> dict[str, Any]:
    """CPU count and model, Python, torch version and intra-op threads, and the torch device used."""
    import torch

    info: dict[str, Any] = {
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "device": str(device),
    }
    if str(device).startswith("cuda") and torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def _busy_cpu_seconds() -> float | None:
    """CPU seconds all processes on the machine have spent busy since boot (Linux /proc/stat), or None."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return None
    ticks = [int(x) for x in fields]
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)  # idle + iowait
    busy = sum(ticks[:8]) - idle  # user nice system idle iowait irq softirq steal (guest counted in user)
    return busy / os.sysconf("SC_CLK_TCK")


def _own_cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


def time_repeats(fn: Callable[[], Any], repeats: int = 3, warmup: int = 0,
                 sync: Callable[[], None] | None = None, budget_s: float | None = None) -> dict[str, Any]:
    """Wall-clock seconds of `fn()` over `repeats` calls after `warmup` untimed calls (fewer calls when the
    timed ones together pass `budget_s` seconds; at least one is made).

    `sync` (e.g. torch.cuda.synchronize) runs before each clock read so asynchronous work is counted.
    Returns {"min", "median", "times", "foreign_cpu"}; benchmarks report the min unless they say otherwise.
    foreign_cpu: per call, the fraction of the machine's CPUs that OTHER processes kept busy meanwhile
    (Linux only, else None); well above 0 means the figure was taken under contention.
    """
    for _ in range(warmup):
        fn()
    times, foreign = [], []
    ncpu = os.cpu_count() or 1
    for _ in range(max(1, repeats)):
        if sync is not None:
            sync()
        busy0, own0 = _busy_cpu_seconds(), _own_cpu_seconds()
        start = time.perf_counter()
        fn()
        if sync is not None:
            sync()
        elapsed = time.perf_counter() - start
        busy1, own1 = _busy_cpu_seconds(), _own_cpu_seconds()
        times.append(elapsed)
        if busy0 is None or busy1 is None or elapsed < 0.2:  # clock ticks are 10 ms: too coarse below this
            foreign.append(None)
        else:
            other = (busy1 - busy0) - (own1 - own0)
            foreign.append(round(min(1.0, max(0.0, other / (elapsed * ncpu))), 3))
        if budget_s is not None and sum(times) > budget_s:
            break
    return {"min": min(times), "median": statistics.median(times), "times": times, "foreign_cpu": foreign}


def argument_parser(doc: str | None) -> argparse.ArgumentParser:
    """A benchmark's command line: its module docstring's first paragraph as the description and the rest, kept as
    written (the commands it shows, what it writes), after the options in `--help`."""
    first, _, rest = (doc or "").strip().partition("\n\n")
    return argparse.ArgumentParser(description=" ".join(first.split()), epilog=rest or None,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)


def mean_se(values: Any) -> tuple[float, float]:
    """Mean and its standard error (nan with fewer than two values) of values (a list or an array)."""
    a = np.asarray(values, dtype=float)
    return float(a.mean()), float(a.std(ddof=1) / math.sqrt(len(a))) if len(a) > 1 else math.nan


def write_result(name: str, record: dict[str, Any], device: str = "cpu") -> Path:
    """Append `record` (with timestamp, git commit and machine info added) as one line to
    bench/results/<name>.jsonl; returns the file's path."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    line = {
        "benchmark": name,
        "timestamp": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        **git_commit(),
        "machine": machine_info(device),
        **record,
    }
    path = RESULTS_DIR / f"{name}.jsonl"
    with path.open("a") as f:
        f.write(json.dumps(line, sort_keys=False) + "\n")
    return path


def prepared_capture(capture: Path, work: Path, **overrides: Any) -> tuple[Any, Any, Any, Any, Any]:
    """The cpu extract preset's stages before the TTO (validate, prepare_views, lmrm) run on `capture` in `work`
    (idempotent: kept stages are reused), then (the preset, the LMRM prediction, the capture, its mesh, its photos
    as a PhotoSet). `overrides` are ExtractConfig fields (lmrm_weights, lmrm_readout: another LMRM)."""
    from neumatex_core.capture import load_capture
    from neumatex_core.pipeline import ExtractConfig, load_prediction, run_stage
    from neumatex_core.tto.data import PhotoSet

    config = ExtractConfig.preset("cpu", device="cpu", **overrides)
    for stage in ("validate", "prepare_views", "lmrm"):
        run_stage(stage, capture, work, config)
    prediction, _ = load_prediction(work)
    cap = load_capture(capture)
    mesh = cap.load_mesh()
    return config, prediction, cap, mesh, PhotoSet.of_capture(cap, mesh)
