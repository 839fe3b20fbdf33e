"""`neumatex references`: the reference renders of every object of a synthetic split (`eval/references.py`).

    neumatex references data/benchmark-test [--spp-half 128 --shard I/K --objects every:5 --workers 2]

Objects run one after another (or over `--workers` spawned processes, `--threads` torch threads each, like
`neumatex eval`); each writes into its own `references/` folder, every image atomically, so a stopped run resumes
where it was and K shards (`--shard I/K`: the selected objects at positions i with i mod K == I) may share one
split. One process per object at a time: a run removes the temporary files it finds in the object's folder."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from neumatex_core.config import option, parse_shard


@dataclass
class ReferencesConfig:
    """`neumatex references`: the ground-truth material of each object of a synthetic split rendered twice (two
    independent halves of --spp-half samples) from the 17 orbital views under the capture's and every held-out
    lighting, into <object>/references/, for the noise-corrected PSNR of `neumatex eval`. Resumable, sharded."""

    data: str = option("data/benchmark-test", "synthetic split (a `neumatex synth` folder)", positional=True)
    spp_half: int = option(128, "samples per pixel of each half")
    max_bounces: int = option(3, "surface interactions per path (as `neumatex eval` renders)")
    objects: str = option("all", "'all', 'first:N', 'every:K' (objects 0, K, 2K, ...) or comma-separated ids")
    shard: str = option("0/1", "I/K: only the selected objects at positions i with i mod K == I")
    workers: int = option(1, "processes (objects in parallel)")
    threads: int = option(1, "torch CPU threads per process")
    progress: bool = option(True, "show a progress bar")

    def shard_range(self) -> tuple[int, int]:
        """(I, K) of --shard, checked."""
        return parse_shard(self.shard)

    def check(self) -> None:
        """ValueError naming the first bad option."""
        for name in ("spp_half", "max_bounces", "workers", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        self.shard_range()


def _one(object_dir: str, spp_half: int, max_bounces: int, threads: int) -> dict[str, Any]:
    """Worker: the references of one object; returns {'id', 'seconds', 'complete'}."""
    import torch

    from neumatex_core.eval.references import render_references

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    start = time.perf_counter()
    try:
        record = render_references(object_dir, spp_half, max_bounces)
    finally:
        torch.set_num_threads(before)
    return {"id": Path(object_dir).name, "seconds": round(time.perf_counter() - start, 1),
            "complete": bool(record["complete"])}  # fmt: skip


def make_references(cfg: ReferencesConfig, progress: Callable[[int, int, dict[str, Any] | None], None] | None = None
                    ) -> dict[str, Any]:
    """Render the missing references of cfg's objects; returns {'objects', 'made', 'skipped', 'seconds'}.
    progress(done, total, record): once with (0, objects, None), then after each object with its record."""
    from neumatex_core.eval.references import FOLDER, has_references, reference_settings
    from neumatex_core.eval.suite import select_objects

    cfg.check()
    start = time.perf_counter()
    data = Path(cfg.data)
    shard, shards = cfg.shard_range()
    objects = [o for i, o in enumerate(select_objects(data, cfg.objects)) if i % shards == shard]
    todo = []
    for obj in objects:  # refuse other settings before rendering anything
        meta = data / obj / FOLDER / "meta.json"
        if meta.is_file():
            stored = json.loads(meta.read_text()).get("settings", {})
            wanted = reference_settings(data / obj, cfg.spp_half, cfg.max_bounces)
            if stored != wanted:
                differ = sorted(k for k in {*stored, *wanted} if stored.get(k) != wanted.get(k))
                raise ValueError(f"{meta.parent}: references made with other settings ({', '.join(differ)} differ: "
                                 f"see {meta}); use the same options or delete the folder")
        if not has_references(data / obj):
            todo.append(obj)
    if progress is not None:
        progress(0, len(todo), None)
    made: list[dict[str, Any]] = []

    def done(record: dict[str, Any]) -> None:
        made.append(record)
        if progress is not None:
            progress(len(made), len(todo), record)

    jobs = [(str(data / obj), cfg.spp_half, cfg.max_bounces) for obj in todo]
    if cfg.workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            done(_one(*job, threads=cfg.threads))
    else:
        with ProcessPoolExecutor(min(cfg.workers, len(jobs)), mp_context=get_context("spawn")) as pool:
            for fut in as_completed([pool.submit(_one, *job, threads=cfg.threads) for job in jobs]):
                done(fut.result())
    return {"objects": len(objects), "made": [r["id"] for r in made], "skipped": len(objects) - len(todo),
            "seconds": time.perf_counter() - start}  # fmt: skip
