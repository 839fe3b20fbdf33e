"""The reaper: re-queues running jobs whose worker stopped sending heartbeats (killed, machine gone), resuming
from the first unfinished stage with a new attempt, and sends again the jobs whose next message never reached
the broker. Runs as a thread in the API process (every API replica may run one: each change is a conditional
UPDATE, so one wins). Once a minute it also removes upload sessions and staging folders older than upload_ttl_s,
and finished jobs' work folders older than work_retention_s (services/cleanup.py)."""

from __future__ import annotations

import logging
import threading
import time
from datetime import timedelta

from sqlalchemy import update

from services import crud
from services.core.config import get_settings
from services.core.db import session_scope
from services.models import StageRun, now

log = logging.getLogger("neumatex.reaper")


def reap_once() -> list[str]:
    """One pass; returns the ids of the jobs sent again."""
    from workers.celery_app import dispatch

    st = get_settings()
    to_send: list[tuple[str, str, int, str]] = []
    with session_scope() as s:
        for job in crud.stale_jobs(s, now() - timedelta(seconds=st.stale_after_s)):
            worker, stage = job.worker, job.stage
            got = crud.requeue(s, job, f"worker {worker} stopped sending heartbeats during {stage}; re-queued")
            if got is None:
                continue
            s.execute(update(StageRun).where(StageRun.job_id == job.id, StageRun.worker == worker,
                                             StageRun.status == "running")
                      .values(status="lost", finished_at=now()))  # fmt: skip
            to_send.append((job.id, got[1], got[0], job.queue))
            log.warning("job %s: worker %s vanished during %s; re-queued as attempt %d", job.id, worker, stage, got[0])
    with session_scope() as s:
        for job in crud.undispatched_jobs(s, timedelta(seconds=st.redispatch_after_s)):
            nxt = crud.next_stage(job)
            if nxt is not None:
                to_send.append((job.id, nxt, job.attempt, job.queue))
    sent = []
    for job_id, stage, attempt, queue in to_send:
        if dispatch(job_id, stage, attempt, queue):
            with session_scope() as s:
                crud.mark_dispatched(s, job_id, attempt)
            sent.append(job_id)
    return sent


def clean_staging() -> int:
    """Remove upload sessions older than upload_ttl_s and staging folders no session owns (a request that died
    mid-upload) once they are that old; returns how many folders were removed."""
    import shutil

    from sqlalchemy import delete, select

    from services.models import Upload
    from services.storage import get_storage

    st = get_settings()
    cutoff = now() - timedelta(seconds=st.upload_ttl_s)
    with session_scope() as s:
        s.execute(delete(Upload).where(Upload.created_at < cutoff))
        live = set(s.scalars(select(Upload.id)))
    staging = get_storage().path("staging")
    removed = 0
    if staging.is_dir():
        for folder in staging.iterdir():
            if folder.name not in live and time.time() - folder.stat().st_mtime > st.upload_ttl_s:
                shutil.rmtree(folder, ignore_errors=True)
                removed += 1
    return removed


class Reaper(threading.Thread):
    def __init__(self) -> None:
        super().__init__(daemon=True, name="neumatex-reaper")
        self.stopped = threading.Event()
        self.cleaned = 0.0

    def run(self) -> None:
        every = get_settings().reaper_every_s
        while not self.stopped.wait(every):
            try:
                reap_once()
                if time.monotonic() - self.cleaned > 60:
                    self.cleaned = time.monotonic()
                    clean_staging()
                    from services.cleanup import clean_work

                    clean_work()
            except Exception as exc:  # database or broker briefly away: next pass
                log.warning("reaper pass failed: %s", exc)
