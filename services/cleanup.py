"""Removing stored work: a capture (with its finished jobs), a finished job's asset and work folder, and the
retention pass that removes finished jobs' work folders older than work_retention_s (run by the reaper).

Active (queued or running) jobs are never touched: deleting a capture that one uses, or an active job's asset, is a
409. A job whose work folder is gone keeps its record; a retry then starts again from the first stage whose output
is missing (`kept_stages`).
"""

from __future__ import annotations

import logging
import time
from datetime import timedelta

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from neumatex_core.pipeline import DONE
from services.core.config import get_settings
from services.errors import ApiError
from services.models import ACTIVE, TERMINAL, Capture, Event, Job, StageRun, WebhookDelivery, now
from services.storage import StorageError, get_storage

log = logging.getLogger("neumatex.cleanup")


def remove(key: str) -> int:
    """Delete a storage key (file or folder); returns the bytes freed."""
    storage = get_storage()
    freed = storage.usage(key)
    storage.delete(key)
    return freed


def delete_job_files(job_id: str) -> int:
    return remove(f"work/{job_id}") + remove(f"assets/{job_id}")


def delete_asset(s: Session, job: Job) -> int:
    """A finished job's asset and work folder (the record stays); 409 while it is queued or running."""
    if job.state in ACTIVE:
        raise ApiError(409, f"job {job.id} is {job.state}; cancel it before deleting its asset and work folder")
    freed = delete_job_files(job.id)
    job.asset_key = None
    s.add(Event(job_id=job.id, kind="deleted", data={"what": "asset and work folder", "bytes": freed}))
    return freed


def delete_capture(s: Session, cap: Capture) -> tuple[list[str], int]:
    """The capture's files and record, and its finished jobs (records, events, work folders, assets); 409 while a
    job of it is queued or running. Returns (the jobs removed, bytes freed)."""
    jobs = list(s.scalars(select(Job).where(Job.capture_id == cap.id)))
    active = [j.id for j in jobs if j.state in ACTIVE]
    if active:
        raise ApiError(409, f"capture {cap.id} is used by {len(active)} queued or running job(s) "
                       f"({', '.join(active[:5])}); cancel them before deleting the capture")
    ids = [j.id for j in jobs]
    freed = sum(delete_job_files(j) for j in ids)
    if ids:
        s.execute(delete(Event).where(Event.job_id.in_(ids)))
        s.execute(delete(StageRun).where(StageRun.job_id.in_(ids)))
        s.execute(delete(WebhookDelivery).where(WebhookDelivery.job_id.in_(ids)))
        s.execute(delete(Job).where(Job.id.in_(ids)))
    freed += remove(cap.storage_key)
    s.delete(cap)
    return ids, freed


def kept_stages(job: Job) -> list[str]:
    """The job's finished stages whose outputs are still stored (their done.json, written last), in order, up to
    the first missing one."""
    storage = get_storage()
    kept = []
    for stage in job.stages_done or []:
        if not storage.is_file(f"work/{job.id}/{stage}/{DONE}"):
            break
        kept.append(stage)
    return kept


def clean_work() -> int:
    """Remove the work folders of jobs that finished more than work_retention_s ago, and work folders no job owns
    once they are that old; returns how many were removed (0 when work_retention_s is 0: kept forever)."""
    keep = get_settings().work_retention_s
    if keep <= 0:
        return 0
    from services.core.db import session_scope

    try:
        folders = get_storage().ages("work")  # job id -> last modified
    except StorageError as exc:
        log.warning("retention: cannot list the work folders: %s", exc)
        return 0
    if not folders:
        return 0
    cutoff = now() - timedelta(seconds=keep)
    removed = 0
    with session_scope() as s:
        states = dict(s.execute(select(Job.id, Job.state).where(Job.id.in_(list(folders)))).all())
        old = set(s.scalars(select(Job.id).where(Job.state.in_(TERMINAL), Job.finished_at < cutoff)))
    for name, mtime in folders.items():
        orphan = name not in states and time.time() - mtime > keep
        if name in old or orphan:
            remove(f"work/{name}")
            removed += 1
            log.info("retention: removed the work folder of %s", name)
    return removed
