"""The stage task. For (job, stage, attempt) it: drops stale messages (older attempt, finished stage, ended job);
claims the job (one conditional UPDATE; a live holder wins); runs `pipeline.run_stage` with progress written to
the job row and events (throttled), a heartbeat thread, and should_stop reading the database (cancellation, or
the reaper having given the job to another worker); then records the stage and sends the next one.

Only `neumatex_core.pipeline` is used from the core library.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import threading
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_process_init
from sqlalchemy import select, update

from neumatex_core import pipeline
from services import crud
from services.core.config import STAGE_NAMES, get_settings
from services.core.db import get_engine, session_scope
from services.jobconfig import build_config
from services.models import Capture, Job, StageRun, now
from services.redact import redact_text
from services.storage import get_storage
from workers.celery_app import TASK, celery_app, dispatch

log = logging.getLogger("neumatex.workers")
_POOL_PARENT: int | None = None  # the worker's main process, when this is a prefork child
TEXT_SUFFIXES = (".json", ".html", ".htm", ".txt", ".md")


@worker_process_init.connect
def _child_init(**_: Any) -> None:
    global _POOL_PARENT
    _POOL_PARENT = os.getppid()
    get_engine().dispose(close=False)  # never share the parent's database connections
    threads = get_settings().torch_threads
    if threads > 0:
        import torch

        torch.set_num_threads(threads)


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class Heartbeat(threading.Thread):
    """Writes job.heartbeat_at every heartbeat_s while this worker holds the job; if the worker's main process
    died (kill -9), exits this orphaned pool process at once so no stage runs twice."""

    def __init__(self, job_id: str, worker: str, interval: float):
        super().__init__(daemon=True, name=f"heartbeat-{job_id}")
        self.job_id, self.worker, self.interval = job_id, worker, interval
        self.stopped = threading.Event()

    def run(self) -> None:
        while not self.stopped.wait(self.interval):
            if _POOL_PARENT is not None and os.getppid() != _POOL_PARENT:
                log.error("worker main process vanished; pool process %s exits", os.getpid())
                os._exit(70)
            try:
                with session_scope() as s:
                    s.execute(update(Job).where(Job.id == self.job_id, Job.worker == self.worker)
                              .values(heartbeat_at=now()))  # fmt: skip
            except Exception as exc:  # a busy database: the next beat retries
                log.warning("heartbeat of %s failed: %s", self.job_id, exc)


class JobContext:
    """Progress, cancellation and bookkeeping of one stage run."""

    def __init__(self, job_id: str, stage: str, attempt: int, worker: str):
        self.job_id, self.stage, self.attempt, self.worker = job_id, stage, attempt, worker
        st = get_settings()
        self.progress_every, self.poll_every = st.progress_every_s, st.cancel_poll_s
        self._last_progress = 0.0
        self._last_poll = 0.0
        self._stop = False
        self.stop_reason = ""

    def holds(self, job: Job) -> bool:
        return job.state == "running" and job.attempt == self.attempt and job.worker == self.worker

    def progress(self, p: pipeline.StageProgress) -> None:
        t = time.monotonic()
        if p.fraction < 1.0 and t - self._last_progress < self.progress_every:
            return
        self._last_progress = t
        overall = crud.overall_progress(self.stage, p.fraction)
        with session_scope() as s:
            job = s.get(Job, self.job_id)
            if job is None or not self.holds(job):
                return
            job.progress = max(job.progress, overall)
            job.stage_fraction = p.fraction
            job.message = p.message
            job.heartbeat_at = now()
            crud.add_event(s, self.job_id, "progress", stage=self.stage, fraction=p.fraction, progress=job.progress,
                           message=p.message, metrics=p.metrics, attempt=self.attempt)  # fmt: skip

    def should_stop(self) -> bool:
        t = time.monotonic()
        if self._stop or t - self._last_poll < self.poll_every:
            return self._stop
        self._last_poll = t
        with session_scope() as s:
            job = s.get(Job, self.job_id)
            if job is None:
                self._stop, self.stop_reason = True, "the job was deleted"
            elif job.state == "canceled":
                self._stop, self.stop_reason = True, "canceled"
            elif not self.holds(job):
                self._stop, self.stop_reason = True, "superseded"
        return self._stop


def _without_server_paths(folder: Path) -> None:
    """Rewrite the asset's text files (manifest, report) without server paths (services/redact.py): they are
    downloaded through the API. Files whose checksum the manifest records are left as they are."""
    manifest = folder / "manifest.json"
    hashed = set(json.loads(manifest.read_text()).get("files", {})) if manifest.is_file() else set()
    for p in folder.rglob("*"):
        if p.is_file() and p.suffix.lower() in TEXT_SUFFIXES and p.relative_to(folder).as_posix() not in hashed:
            text = p.read_text(errors="surrogateescape")
            shown = redact_text(text)
            if shown != text:
                p.write_text(shown, errors="surrogateescape")


def _publish_asset(job_id: str, work: Path) -> str:
    """Copy the export stage's asset to assets/<job>/asset (without server paths) and zip it (each appears by one
    rename)."""
    storage = get_storage()
    key = f"assets/{job_id}"
    base = storage.path(key)
    base.mkdir(parents=True, exist_ok=True)
    tmp = base / f".tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        shutil.copytree(pipeline.asset_path(work), tmp / "asset")
        _without_server_paths(tmp / "asset")
        shutil.make_archive(str(tmp / "asset"), "zip", root_dir=tmp / "asset")
        shutil.rmtree(base / "asset", ignore_errors=True)
        os.replace(tmp / "asset", base / "asset")
        os.replace(tmp / "asset.zip", base / "asset.zip")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return key


def _numbers(metrics: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in metrics.items() if isinstance(v, int | float | str | bool)}


def _end_run(run_id: int, status: str) -> None:
    with session_scope() as s:
        run = s.get(StageRun, run_id)
        if run is not None:
            run.status, run.finished_at = status, now()
            run.seconds = (run.finished_at - run.started_at).total_seconds()


def _fail(job_id: str, attempt: int, worker: str, stage: str, run_id: int, error: str) -> None:
    _end_run(run_id, "failed")
    with session_scope() as s:
        r = s.execute(update(Job).where(Job.id == job_id, Job.attempt == attempt, Job.worker == worker,
                                        Job.state == "running")
                      .values(state="failed", error=error, worker=None, finished_at=now(),
                              message=f"{stage} failed"))  # fmt: skip
        if r.rowcount:  # type: ignore[attr-defined]
            crud.add_event(s, job_id, "state", state="failed", stage=stage, error=error)


@celery_app.task(name=TASK, bind=True, acks_late=True, reject_on_worker_lost=True)
def run_stage_task(self: Any, job_id: str, stage: str, attempt: int) -> str:
    st = get_settings()
    me = worker_name()
    if stage not in STAGE_NAMES:
        log.error("unknown stage %r for %s", stage, job_id)
        return "unknown stage"
    with session_scope() as s:
        job = s.get(Job, job_id)
        if job is None or job.attempt != attempt or job.state not in ("queued", "running"):
            return "stale"
        if stage in (job.stages_done or []) or crud.next_stage(job) != stage:
            return "not next"
        if not crud.claim(s, job_id, attempt, stage, me, now() - timedelta(seconds=st.stale_after_s)):
            return "held by another worker"
        run = StageRun(job_id=job_id, stage=stage, attempt=attempt, worker=me)
        s.add(run)
        crud.add_event(s, job_id, "stage", stage=stage, status="started", worker=me, attempt=attempt)
        if stage == STAGE_NAMES[0] or job.state == "queued":
            crud.add_event(s, job_id, "state", state="running", stage=stage, progress=job.progress)
        s.flush()
        run_id = run.id
        capture = s.get(Capture, job.capture_id)
        assert capture is not None
        capture_key, preset, overrides = capture.storage_key, job.preset, dict(job.config or {})
    storage = get_storage()
    capture_path, work = storage.path(capture_key), storage.path(f"work/{job_id}")
    work.mkdir(parents=True, exist_ok=True)
    ctx = JobContext(job_id, stage, attempt, me)
    beat = Heartbeat(job_id, me, st.heartbeat_s)
    beat.start()
    try:
        config = build_config(preset, overrides)
        metrics = pipeline.run_stage(stage, capture_path, work, config, ctx.progress, ctx.should_stop)
    except pipeline.Cancelled as exc:
        _end_run(run_id, "canceled" if ctx.stop_reason == "canceled" else "superseded")
        with session_scope() as s:
            s.execute(update(Job).where(Job.id == job_id, Job.worker == me).values(worker=None))
            crud.add_event(s, job_id, "worker", worker=me, stage=stage, status="stopped", reason=ctx.stop_reason,
                           message=str(exc))  # fmt: skip
        return "stopped"
    except pipeline.PipelineError as exc:
        _fail(job_id, attempt, me, stage, run_id, str(exc))
        return "failed"
    except SoftTimeLimitExceeded:
        _fail(job_id, attempt, me, stage, run_id, f"stage {stage} ran past its time limit of "
              f"{st.time_limit(stage):.0f} s; retry with a smaller preset or raise NEUMATEX_STAGE_TIME_LIMITS")
        return "timed out"
    except Exception as exc:
        log.exception("stage %s of %s crashed", stage, job_id)
        _fail(job_id, attempt, me, stage, run_id, f"internal error in stage {stage}: {type(exc).__name__}: {exc}")
        return "crashed"
    finally:
        beat.stopped.set()
    last = stage == STAGE_NAMES[-1]
    asset_key = _publish_asset(job_id, work) if last else None
    _end_run(run_id, "finished")
    nxt = None
    with session_scope() as s:
        job = s.get(Job, job_id)
        if job is None or not ctx.holds(job):
            return "finished, job no longer ours"
        done = [*job.stages_done, stage]
        values: dict[str, Any] = {
            "stages_done": done, "metrics": {**job.metrics, stage: _numbers(metrics)},
            "timings": {**job.timings, stage: float(metrics.get("seconds", 0.0))}, "worker": None,
            "stage_fraction": 1.0, "progress": max(job.progress, crud.overall_progress(stage, 1.0)),
            "message": f"{stage} done"}  # fmt: skip
        if last:
            values.update(state="completed", asset_key=asset_key, finished_at=now(), progress=1.0)
        else:
            nxt = STAGE_NAMES[STAGE_NAMES.index(stage) + 1]
            values.update(stage=nxt, stage_fraction=0.0, dispatched_at=None)
        r = s.execute(update(Job).where(Job.id == job_id, Job.attempt == attempt, Job.worker == me,
                                        Job.state == "running").values(**values))  # fmt: skip
        if not r.rowcount:  # type: ignore[attr-defined]
            return "finished, job no longer ours"
        crud.add_event(s, job_id, "stage", stage=stage, status="finished", worker=me, attempt=attempt,
                       seconds=float(metrics.get("seconds", 0.0)), progress=values["progress"])  # fmt: skip
        if last:
            crud.add_event(s, job_id, "state", state="completed", stage=stage, progress=1.0)
    if nxt is not None and dispatch(job_id, nxt, attempt, _queue(job_id)):
        with session_scope() as s:
            crud.mark_dispatched(s, job_id, attempt)
    return "finished"


def _queue(job_id: str) -> str:
    with session_scope() as s:
        return s.scalar(select(Job.queue).where(Job.id == job_id)) or "cpu"
