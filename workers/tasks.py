"""The Celery tasks, a thin wrapper over services/lifecycle.py (the one owner of the job lifecycle).

`neumatex.stage` (job, stage, attempt): `lifecycle.claim` (stale messages dropped; a live holder wins), the stage's
inputs fetched, `pipeline.run_stage` with progress (`lifecycle.record_progress`, throttled), a heartbeat thread and
should_stop (`lifecycle.holder_problem`: canceled, or the reaper gave the job to another worker), the outputs
stored, then `lifecycle.advance` (next stage or completed), `fail` or `stopped`. `neumatex.reap`: one reaper pass
(services/reaper.py), sent by Celery beat.

Only `neumatex_core.pipeline` is used from the core library.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from typing import Any

from celery.exceptions import SoftTimeLimitExceeded
from celery.signals import worker_process_init

from neumatex_core import pipeline
from services import lifecycle, queue, reaper, stage_io
from services.core.config import get_settings
from services.core.db import get_engine
from services.jobconfig import build_config
from workers.celery_app import celery_app

log = logging.getLogger("neumatex.workers")
_POOL_PARENT: int | None = None  # the worker's main process, when this is a prefork child


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
                lifecycle.heartbeat(self.job_id, self.worker)
            except Exception as exc:  # a busy database: the next beat retries
                log.warning("heartbeat of %s failed: %s", self.job_id, exc)


class JobContext:
    """The pipeline's progress and should_stop callbacks for one stage run, throttled (progress_every_s,
    cancel_poll_s)."""

    def __init__(self, job_id: str, stage: str, attempt: int, worker: str):
        self.job_id, self.stage, self.attempt, self.worker = job_id, stage, attempt, worker
        st = get_settings()
        self.progress_every, self.poll_every = st.progress_every_s, st.cancel_poll_s
        self._last_progress = 0.0
        self._last_poll = 0.0
        self.stop_reason = ""
        self.partial: stage_io.PartialOutputs | None = None  # set once the stage's local folders exist

    def progress(self, p: pipeline.StageProgress) -> None:
        t = time.monotonic()
        if p.fraction < 1.0 and t - self._last_progress < self.progress_every:
            return
        self._last_progress = t
        lifecycle.record_progress(self.job_id, self.stage, self.attempt, self.worker, p)
        if self.partial is not None:
            try:
                self.partial.store_changed()
            except Exception as exc:  # the storage briefly away: the next call tries again
                log.warning("could not store the partial outputs of %s/%s: %s", self.job_id, self.stage, exc)

    def should_stop(self) -> bool:
        t = time.monotonic()
        if self.stop_reason or t - self._last_poll < self.poll_every:
            return bool(self.stop_reason)
        self._last_poll = t
        self.stop_reason = lifecycle.holder_problem(self.job_id, self.attempt, self.worker)
        return bool(self.stop_reason)


@celery_app.task(name=queue.STAGE_TASK, bind=True, acks_late=True, reject_on_worker_lost=True)
def run_stage_task(self: Any, job_id: str, stage: str, attempt: int) -> str:
    """Run one stage of one job; returns what happened (for the worker's log)."""
    st = get_settings()
    me = worker_name()
    got = lifecycle.claim(job_id, stage, attempt, me)
    if isinstance(got, str):
        log.info("%s/%s attempt %d dropped: %s", job_id, stage, attempt, got)
        return got
    ctx = JobContext(job_id, stage, attempt, me)
    beat = Heartbeat(job_id, me, st.heartbeat_s)
    beat.start()
    try:
        config = build_config(got.preset, got.overrides)
        # local folders for this run: the storage's own (local storage), or a temporary copy (S3), removed after
        with stage_io.stage_paths(job_id, got.capture_key, stage) as (capture, work):
            ctx.partial = stage_io.PartialOutputs(job_id, work, stage, st.partial_store_every_s)
            metrics = pipeline.run_stage(stage, capture, work, config, ctx.progress, ctx.should_stop)
            stage_io.store_stage(job_id, work, stage)  # done.json last
            asset_key = stage_io.publish_asset(job_id, work) if stage == pipeline.STAGES[-1] else None
    except pipeline.Cancelled as exc:
        lifecycle.stopped(job_id, stage, me, got.run_id, ctx.stop_reason or "superseded", str(exc))
        return "stopped"
    except pipeline.PipelineError as exc:
        lifecycle.fail(job_id, stage, attempt, me, got.run_id, str(exc))
        return "failed"
    except SoftTimeLimitExceeded:
        lifecycle.fail(job_id, stage, attempt, me, got.run_id, f"stage {stage} ran past its time limit of "
                       f"{st.time_limit(stage):.0f} s; retry with a smaller preset or raise "
                       "NEUMATEX_STAGE_TIME_LIMITS")  # fmt: skip
        return "timed out"
    except Exception as exc:
        log.exception("stage %s of %s crashed", stage, job_id)
        lifecycle.fail(job_id, stage, attempt, me, got.run_id,
                       f"internal error in stage {stage}: {type(exc).__name__}: {exc}")
        return "crashed"
    finally:
        beat.stopped.set()
    return lifecycle.advance(job_id, stage, attempt, me, got.run_id, metrics, asset_key)


@celery_app.task(name=queue.REAP_TASK, acks_late=False)
def reap_task(clean: bool = False) -> dict[str, object]:
    """One reaper pass (services/reaper.py), sent by Celery beat."""
    return reaper.reap_pass(clean)
