"""A synthetic dataset: many objects, made in parallel, resumable, sharded, with a manifest.

`generate(cfg)` makes objects 0..n-1 of a split into `cfg.out`:

- each object is written into `.tmp-<id>-<pid>/` and renamed to `<id>/` when complete (meta.json is its last
  file), so a folder `<id>/` with meta.json is finished; a rerun skips those (resume), and stale temporary folders
  of this shard are removed first;
- `--shard I/K` makes only indices with index % K == I, so K machines (or runs) share one output folder;
- objects are spread over `workers` processes (spawned; one torch thread each), and an object's files depend only
  on (split, index, seed) and the content options, never on the worker, the shard or the order;
- `synth.json` records the content options, the basis and the shared files the first run used; a later run with
  other ones is refused (it would mix two datasets);
- `manifest.json` is rebuilt from the finished objects' meta.json after every run: per object its shape,
  material families, lighting and the SHA-256 of its file listing, and `complete` once all n exist. It holds no
  times or paths, so regenerating a split gives the same manifest byte for byte (docs/benchmark.md);
- `timings.jsonl` gets one line per object made: wall-clock seconds in total and per stage (rays, material,
  write, ...), and the same as CPU seconds of the worker process (`cpu_seconds`, `stages_cpu`).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import torch

from neumatex_core.atomic import write_json_atomic
from neumatex_core.synth.config import SynthConfig
from neumatex_core.synth.profile import StageTimes
from neumatex_core.synth.spec import (
    ENVMAP_SUFFIXES,
    HELD_OUT_MESHES,
    MESH_SUFFIXES,
    object_id,
    object_spec,
    shared_names,
)
from neumatex_core.synth.writer import ObjectWriter

FORMAT = "neumatex-synth-1"
MANIFEST = "manifest.json"
SETTINGS = "synth.json"
TIMINGS = "timings.jsonl"


@dataclass
class GenerateResult:
    """made: ids written by this run; skipped: finished before; seconds: wall clock; manifest: its path."""

    made: list[str] = field(default_factory=list)
    skipped: int = 0
    seconds: float = 0.0
    manifest: Path | None = None
    complete: bool = False


def is_finished(folder: Path) -> bool:
    return (folder / "meta.json").is_file()


def shared_files(cfg: SynthConfig) -> tuple[list[str], list[str]]:
    """(mesh file names, envmap file names) of the shared folders; ValueError when a folder is missing."""
    for what, folder in (("meshes", cfg.meshes_dir()), ("envmaps", cfg.envmaps_dir())):
        if not folder.is_dir():
            raise ValueError(f"{folder}: shared {what} folder not found (set --{what} or NEUMATEX_SHARED)")
    return shared_names(cfg.meshes_dir(), MESH_SUFFIXES), shared_names(cfg.envmaps_dir(), ENVMAP_SUFFIXES)


def _settings(cfg: SynthConfig, basis_id: str, basis_sha: str, meshes: list[str], envmaps: list[str]
              ) -> dict[str, Any]:
    return {"format": FORMAT, "content": cfg.content(), "basis": {"id": basis_id, "sha256": basis_sha},
            "meshes": meshes, "envmaps": envmaps}  # fmt: skip


def _check_settings(out: Path, settings: dict[str, Any]) -> None:
    path = out / SETTINGS
    if path.is_file():
        old = json.loads(path.read_text())
        if old != settings:
            keys = sorted({*old, *settings, *old.get("content", {}), *settings["content"]})
            differ = [k for k in keys if _lookup(old, k) != _lookup(settings, k)]
            raise ValueError(f"{out}: made with other settings ({', '.join(differ)} differ: see {path}); "
                             "use a new --out or the same options")
    else:
        path.write_text(json.dumps(settings, indent=1, sort_keys=True) + "\n")


def _lookup(d: dict[str, Any], key: str) -> Any:
    return d[key] if key in d else d.get("content", {}).get(key)


# -- one object, in whichever process ------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(cfg: SynthConfig, mesh_files: list[str], envmap_files: list[str]) -> None:
    from neumatex_core.materials.neural_basis import load_basis

    torch.set_num_threads(cfg.threads)
    _WORKER.update(cfg=cfg, meshes=mesh_files, envmaps=envmap_files, basis=load_basis())


def _make_object(index: int) -> dict[str, Any]:
    """Write object `index` (temporary folder, then rename); returns its timing record."""
    cfg: SynthConfig = _WORKER["cfg"]
    spec = object_spec(cfg.split, index, cfg.seed, _WORKER["meshes"], _WORKER["envmaps"], cfg.relight_maps)
    out = Path(cfg.out)
    tmp = out / f".tmp-{spec.id}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    times = StageTimes()
    start, cpu = time.perf_counter(), time.process_time()
    ObjectWriter(spec, cfg, _WORKER["basis"], times).write(tmp)
    final = out / spec.id
    if final.exists():  # another run finished it meanwhile: keep theirs (identical by construction)
        shutil.rmtree(tmp)
    else:
        os.rename(tmp, final)
    return {"id": spec.id, "seconds": round(time.perf_counter() - start, 3), "stages": times.as_dict(),
            "cpu_seconds": round(time.process_time() - cpu, 3), "stages_cpu": times.cpu_dict(),
            "pid": os.getpid()}  # fmt: skip


# -- the dataset -----------------------------------------------------------------------------------------------
def manifest(cfg: SynthConfig, settings: dict[str, Any]) -> dict[str, Any]:
    """The manifest of what is finished in cfg.out (see the module docstring)."""
    out = Path(cfg.out)
    objects = []
    for index in range(cfg.n):
        folder = out / object_id(cfg.split, index)
        if not is_finished(folder):
            continue
        meta = json.loads((folder / "meta.json").read_text())
        spec = meta["spec"]
        regions = spec["material"]["regions"]
        objects.append({
            "id": meta["id"], "index": index, "shape": meta["shape"]["kind"], "mesh": spec["shape"]["mesh"],
            "faces": meta["faces"], "region_mode": spec["material"]["mode"], "regions": len(regions),
            "families": [r["family"] for r in regions],
            "lighting": {**spec["lighting"], "envmap_scale": meta["lighting"]["envmap_scale"]},
            "relight": [{"kind": r["kind"], "map": r["map"]} for r in spec["relight"]],
            "coverage": meta["coverage"], "tree_sha256": meta["tree_sha256"],
        })  # fmt: skip
    used_meshes = sorted({o["mesh"] for o in objects if o["mesh"]})
    return {**settings, "split": cfg.split, "seed": cfg.seed, "n": cfg.n, "held_out_meshes": list(HELD_OUT_MESHES),
            "meshes_used": used_meshes, "complete": len(objects) == cfg.n, "objects": objects}  # fmt: skip


def generate(cfg: SynthConfig, progress: Callable[[int, int, dict[str, Any] | None], None] | None = None
             ) -> GenerateResult:
    """Make the missing objects of cfg's shard, then rewrite the manifest. progress(done, total, record): once with
    (0, objects to make, None) before the first, then after each object with its timing record."""
    from neumatex_core.materials.neural_basis import load_basis

    cfg.check()
    start = time.perf_counter()
    mesh_files, envmap_files = shared_files(cfg)
    basis = load_basis()
    settings = _settings(cfg, basis.basis_id, basis.content_hash, mesh_files, envmap_files)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    _check_settings(out, settings)
    shard, shards = cfg.shard_range()
    mine = [i for i in range(cfg.n) if i % shards == shard]
    ids = {object_id(cfg.split, i) for i in mine}
    for stale in out.glob(".tmp-*"):
        if stale.name[len(".tmp-"):].rsplit("-", 1)[0] in ids:
            shutil.rmtree(stale, ignore_errors=True)
    todo = [i for i in mine if not is_finished(out / object_id(cfg.split, i))]
    result = GenerateResult(skipped=len(mine) - len(todo))
    workers = min(cfg.workers or os.cpu_count() or 1, max(len(todo), 1))
    records: list[dict[str, Any]] = []
    if progress is not None:
        progress(0, len(todo), None)

    def done(record: dict[str, Any]) -> None:
        records.append(record)
        result.made.append(record["id"])
        with open(out / TIMINGS, "a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")
        if progress is not None:
            progress(len(records), len(todo), record)

    if todo and workers <= 1:
        threads = torch.get_num_threads()
        try:
            _init_worker(cfg, mesh_files, envmap_files)
            for index in todo:
                done(_make_object(index))
        finally:
            torch.set_num_threads(threads)
    elif todo:
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker,
                                 initargs=(cfg, mesh_files, envmap_files)) as pool:  # fmt: skip
            futures = [pool.submit(_make_object, i) for i in todo]
            for fut in as_completed(futures):
                done(fut.result())
    data = manifest(cfg, settings)
    path = out / MANIFEST
    write_json_atomic(path, data)
    result.manifest, result.complete = path, bool(data["complete"])
    result.seconds = time.perf_counter() - start
    return result
