"""The worker's side of the storage (services/storage.py): local folders for one stage run of a job, the stage's
outputs stored afterwards, and the finished asset published.

    with stage_paths(job_id, capture_key, stage) as (capture_dir, work_dir):
        metrics = pipeline.run_stage(stage, capture_dir, work_dir, config, progress, should_stop)
        store_stage(job_id, work_dir, stage)
        asset_key = publish_asset(job_id, work_dir) if stage == STAGES[-1] else None

Local storage: `capture_dir` and `work_dir` are the storage's own folders (captures/<id>, work/<job>), read and
written in place; storing the stage is then nothing to do. S3: a fresh temporary folder per stage run (under
Settings.scratch_dir) mirrors the keys: `<tmp>/captures/<id>/` (the capture, downloaded) and `<tmp>/work/<job>/`
(the outputs of this stage and the stages before it that are stored, downloaded); it is removed afterwards, so a
worker needs no shared disk. `store_stage` uploads work/<stage>/ with done.json LAST: a stage half-uploaded (a
worker killed meanwhile) has no done.json in the storage, so it never looks finished and runs again.

A stage stopped by should_stop (canceled, or superseded) keeps its outputs so far (the TTO's checkpoint) in the
storage, without done.json, so its next run resumes from them, as on local storage. While a stage runs,
`PartialOutputs.store_changed` (called from the worker's progress callback) stores its changed files, except
done.json, at most every `partial_store_every_s`: a worker killed (kill -9) mid-TTO then loses at most that much
work, and the stage resumes on another worker from the last stored checkpoint. Known cost on S3: the capture is
downloaded for every stage run (five per job).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from neumatex_core import pipeline
from neumatex_core.atomic import is_temporary
from services.redact import redact_text
from services.storage import Storage, get_storage

TEXT_SUFFIXES = (".json", ".html", ".htm", ".txt", ".md")
log = logging.getLogger("neumatex.stage_io")


@contextmanager
def stage_paths(job_id: str, capture_key: str, stage: str,
                storage: Storage | None = None) -> Iterator[tuple[Path, Path]]:
    """(capture_dir, work_dir): local folders for running `stage` of the job (see the module docstring)."""
    storage = storage or get_storage()
    work_key = f"work/{job_id}"
    capture_dir, work_dir = storage.local_path(capture_key), storage.local_path(work_key)
    if capture_dir is not None and work_dir is not None:
        work_dir.mkdir(parents=True, exist_ok=True)
        yield capture_dir, work_dir
        return
    tmp = storage.workspace(f"stage-runs/{job_id}-{stage}-{uuid.uuid4().hex[:12]}")
    try:
        capture_dir, work_dir = tmp / capture_key, tmp / work_key
        storage.get_tree(capture_key, capture_dir)
        work_dir.mkdir(parents=True, exist_ok=True)
        names = pipeline.STAGES
        for earlier in names[:names.index(stage) + 1] if stage in names else names:
            storage.get_tree(f"{work_key}/{earlier}", work_dir / earlier)
        try:
            yield capture_dir, work_dir
        except pipeline.Cancelled:
            _keep_partial(storage, job_id, work_dir, stage)
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _keep_partial(storage: Storage, job_id: str, work_dir: Path, stage: str) -> None:
    """A stopped stage's outputs so far (the TTO's checkpoint), stored without done.json so that the stage's next
    run (on any worker) resumes from them instead of starting over."""
    folder = pipeline.stage_dir(work_dir, stage)
    if not folder.is_dir() or (folder / pipeline.DONE).exists():
        return
    try:
        storage.put_tree(folder, f"work/{job_id}/{stage}")
    except Exception as exc:  # the stop itself must not fail: the stage then starts over
        log.warning("could not keep the partial outputs of %s/%s: %s", job_id, stage, exc)


class PartialOutputs:
    """A running stage's outputs so far, stored (without done.json) when they changed, at most every `every_s`
    seconds; nothing to do on local storage, where the stage writes in place."""

    def __init__(self, job_id: str, work_dir: Path, stage: str, every_s: float, storage: Storage | None = None):
        self.storage = storage or get_storage()
        self.key, self.every_s = f"work/{job_id}/{stage}", every_s
        self.folder = pipeline.stage_dir(work_dir, stage)
        self.active = self.storage.local_path(self.key) is None
        self._stored: dict[str, tuple[int, int]] = {}  # relative name -> (mtime_ns, size) when stored
        self._last = time.monotonic()

    def store_changed(self) -> int:
        """Store the files that changed since they were last stored (when every_s has passed); returns how many."""
        if not self.active or time.monotonic() - self._last < self.every_s or not self.folder.is_dir():
            return 0
        self._last = time.monotonic()
        n = 0
        for p in sorted(self.folder.rglob("*")):
            rel = p.relative_to(self.folder).as_posix()
            if not p.is_file() or rel == pipeline.DONE or is_temporary(p.name):
                continue
            st = p.stat()
            if self._stored.get(rel) != (st.st_mtime_ns, st.st_size):
                try:
                    self.storage.put_file(p, f"{self.key}/{rel}")
                except FileNotFoundError:  # replaced meanwhile (an atomic rewrite): the next call stores it
                    continue
                self._stored[rel] = (st.st_mtime_ns, st.st_size)
                n += 1
        return n


def store_stage(job_id: str, work_dir: Path, stage: str, storage: Storage | None = None) -> None:
    """Store the finished stage's folder work_dir/<stage>/ as work/<job>/<stage>/, its done.json after every other
    file (nothing to do when work_dir is the storage's own folder)."""
    storage = storage or get_storage()
    key = f"work/{job_id}/{stage}"
    if storage.local_path(key) is not None:
        return
    folder = pipeline.stage_dir(work_dir, stage)
    if not (folder / pipeline.DONE).is_file():
        raise pipeline.PipelineError(f"stage {stage} of job {job_id} has not finished: {folder / pipeline.DONE} "
                                     "is missing, so its outputs are not stored")
    storage.put_tree(folder, key, last=(pipeline.DONE,))


def without_server_paths(folder: Path, prefixes: tuple[str, ...] = ()) -> None:
    """Rewrite the asset's text files (manifest, report) without server paths (services/redact.py): they are
    downloaded through the API. `prefixes` (a stage run's temporary folder) are removed first, so a path inside
    it reads as its storage key, as on local storage. Files whose checksum the manifest records are left as they
    are."""
    manifest = folder / "manifest.json"
    hashed = set(json.loads(manifest.read_text()).get("files", {})) if manifest.is_file() else set()
    for p in folder.rglob("*"):
        if p.is_file() and p.suffix.lower() in TEXT_SUFFIXES and p.relative_to(folder).as_posix() not in hashed:
            text = p.read_text(errors="surrogateescape")
            shown = text
            for prefix in prefixes:
                shown = shown.replace(prefix.rstrip("/") + "/", "")
            shown = redact_text(shown)
            if shown != text:
                p.write_text(shown, errors="surrogateescape")


def publish_asset(job_id: str, work_dir: Path, storage: Storage | None = None) -> str:
    """Copy the export stage's asset to assets/<job>/asset (without server paths) and zip it to
    assets/<job>/asset.zip; returns "assets/<job>". Each appears whole: built in a local workspace, then one
    rename each (local), or uploaded with manifest.json last and the zip as one object (S3). A viewer bundle of an
    earlier asset is removed (it would show the old one)."""
    storage = storage or get_storage()
    key = f"assets/{job_id}"
    tmp = storage.workspace(f"{key}/.tmp-{uuid.uuid4().hex[:12]}")
    try:
        source = pipeline.asset_path(work_dir)
        if not (source / "manifest.json").is_file():
            raise pipeline.PipelineError(f"the export stage of job {job_id} finished but its asset is missing "
                                         f"({source / 'manifest.json'})")  # fmt: skip
        shutil.copytree(source, tmp / "asset")
        run_dir = work_dir.parent.parent  # <tmp>/work/<job> -> <tmp> (S3), or the storage folder (local)
        without_server_paths(tmp / "asset", (str(run_dir),))
        shutil.make_archive(str(tmp / "asset"), "zip", root_dir=tmp / "asset")
        storage.delete(f"{key}/viewer")
        storage.commit_tree(tmp / "asset", f"{key}/asset", last=("manifest.json",), replace=True)
        storage.commit_file(tmp / "asset.zip", f"{key}/asset.zip")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return key
