"""Database operations of the API, the workers and the reaper. State changes that can race (claiming a job,
re-queueing it, cancelling it) are single conditional UPDATEs on (id, attempt, ...) so exactly one side wins."""

from __future__ import annotations

import hashlib
import json
import time
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from services.core.config import STAGE_NAMES
from services.core.security import hash_api_key, new_api_key
from services.models import ACTIVE, TERMINAL, ApiKey, Event, Job, StageRun, Tenant, now

# Share of the overall progress per stage (TTO dominates).
STAGE_WEIGHTS = {"validate": 0.05, "prepare_views": 0.15, "lmrm": 0.05, "tto": 0.6, "export": 0.15}


def overall_progress(stage: str, fraction: float) -> float:
    i = STAGE_NAMES.index(stage)
    before = sum(STAGE_WEIGHTS[s] for s in STAGE_NAMES[:i])
    return min(1.0, before + STAGE_WEIGHTS[stage] * min(max(fraction, 0.0), 1.0))


# -- tenants and keys ------------------------------------------------------------------------------------------
def create_tenant(s: Session, name: str, key: str | None = None) -> tuple[Tenant, str]:
    """A tenant and its first API key (returned once; only the hash is stored)."""
    tenant = Tenant(name=name)
    s.add(tenant)
    s.flush()
    key = key or new_api_key()
    s.add(ApiKey(tenant_id=tenant.id, key_hash=hash_api_key(key), prefix=key[:8]))
    s.flush()
    return tenant, key


def ensure_tenant(s: Session, name: str, key: str) -> Tenant:
    """The tenant `name` with API key `key` (both created when missing)."""
    found = s.scalar(select(ApiKey).where(ApiKey.key_hash == hash_api_key(key)))
    if found is not None:
        tenant = s.get(Tenant, found.tenant_id)
        assert tenant is not None
        return tenant
    tenant = s.scalar(select(Tenant).where(Tenant.name == name))
    if tenant is None:
        return create_tenant(s, name, key)[0]
    s.add(ApiKey(tenant_id=tenant.id, key_hash=hash_api_key(key), prefix=key[:8]))
    return tenant


_KEY_CACHE: dict[str, tuple[float, str]] = {}  # key hash -> (expiry on the monotonic clock, tenant id)
KEY_CACHE_S = 10.0  # a revoked key stops working within this many seconds


def tenant_for_key(s: Session, key: str) -> Tenant | None:
    """The tenant of a valid, unrevoked key (positive answers cached for KEY_CACHE_S per process)."""
    digest = hash_api_key(key)
    hit = _KEY_CACHE.get(digest)
    if hit is not None and hit[0] > time.monotonic():
        return s.get(Tenant, hit[1])
    row = s.scalar(select(ApiKey).where(ApiKey.key_hash == digest, ApiKey.revoked.is_(False)))
    if row is None:
        return None
    if len(_KEY_CACHE) > 10_000:
        _KEY_CACHE.clear()
    _KEY_CACHE[digest] = (time.monotonic() + KEY_CACHE_S, row.tenant_id)
    return s.get(Tenant, row.tenant_id)


# -- events ---------------------------------------------------------------------------------------------------
def add_event(s: Session, job_id: str, kind: str, **data: Any) -> None:
    s.add(Event(job_id=job_id, kind=kind, data=data))
    if kind == "state" and data.get("state") in TERMINAL:  # every terminal transition passes here: its webhook
        from services import webhooks

        webhooks.enqueue(s, job_id, str(data["state"]))


def events_after(s: Session, job_id: str, after: int, limit: int = 500) -> list[Event]:
    q = select(Event).where(Event.job_id == job_id, Event.id > after).order_by(Event.id).limit(limit)
    return list(s.scalars(q))


# -- jobs -----------------------------------------------------------------------------------------------------
def request_hash(payload: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def job_of_tenant(s: Session, tenant_id: str, job_id: str) -> Job | None:
    job = s.get(Job, job_id)
    return job if job is not None and job.tenant_id == tenant_id else None


def find_idempotent(s: Session, tenant_id: str, key: str) -> Job | None:
    return s.scalar(select(Job).where(Job.tenant_id == tenant_id, Job.idempotency_key == key))


def list_jobs(s: Session, tenant_id: str, state: str | None, capture_id: str | None, stage: str | None,
              limit: int, offset: int) -> tuple[list[Job], int]:
    q = select(Job).where(Job.tenant_id == tenant_id)
    if state:
        q = q.where(Job.state == state)
    if capture_id:
        q = q.where(Job.capture_id == capture_id)
    if stage:
        q = q.where(Job.stage == stage)
    total = s.scalar(select(func.count()).select_from(q.subquery())) or 0
    rows = list(s.scalars(q.order_by(Job.created_at.desc(), Job.id).limit(limit).offset(offset)))
    return rows, int(total)


def stage_runs(s: Session, job_id: str) -> list[StageRun]:
    return list(s.scalars(select(StageRun).where(StageRun.job_id == job_id).order_by(StageRun.id)))


def next_stage(job: Job) -> str | None:
    for stage in STAGE_NAMES:
        if stage not in (job.stages_done or []):
            return stage
    return None


def mark_dispatched(s: Session, job_id: str, attempt: int) -> None:
    s.execute(update(Job).where(Job.id == job_id, Job.attempt == attempt).values(dispatched_at=now()))


def cancel(s: Session, job: Job) -> bool:
    """Queued or running -> canceled (a running worker sees it within cancel_poll_s and stops)."""
    r = s.execute(update(Job).where(Job.id == job.id, Job.state.in_(ACTIVE))
                  .values(state="canceled", finished_at=now(), message="canceled by the client"))  # fmt: skip
    if r.rowcount:  # type: ignore[attr-defined]
        add_event(s, job.id, "state", state="canceled", stage=job.stage, progress=job.progress,
                  message="canceled by the client")
        return True
    return False


def requeue(s: Session, job: Job, reason: str, from_stage: str | None = None) -> tuple[int, str] | None:
    """Back to queued with a new attempt (stale messages of older attempts are dropped); returns (attempt, first
    stage to run), or None when someone else changed the job first."""
    done = list(job.stages_done or [])
    if from_stage is not None:
        done = done[:STAGE_NAMES.index(from_stage)]
    attempt = job.attempt + 1
    stage = next((st for st in STAGE_NAMES if st not in done), STAGE_NAMES[-1])
    r = s.execute(update(Job).where(Job.id == job.id, Job.attempt == job.attempt).values(
        attempt=attempt, state="queued", worker=None, heartbeat_at=None, dispatched_at=None, error="",
        stages_done=done, stage=stage, stage_fraction=0.0, finished_at=None, message=reason,
        progress=overall_progress(stage, 0.0) if stage != STAGE_NAMES[0] else 0.0))
    if not r.rowcount:  # type: ignore[attr-defined]
        return None
    add_event(s, job.id, "requeued", attempt=attempt, stage=stage, message=reason)
    return attempt, stage


# -- worker side ----------------------------------------------------------------------------------------------
def claim(s: Session, job_id: str, attempt: int, stage: str, worker: str, stale_before: datetime) -> bool:
    """Take the job for `stage` unless another live worker holds it or the attempt is stale."""
    r = s.execute(update(Job).where(
        Job.id == job_id, Job.attempt == attempt, Job.state.in_(ACTIVE),
        (Job.worker.is_(None)) | (Job.worker == worker) | (Job.heartbeat_at < stale_before),
    ).values(state="running", stage=stage, stage_fraction=0.0, worker=worker, heartbeat_at=now(),
             started_at=func.coalesce(Job.started_at, now()), message=f"{stage} started"))  # fmt: skip
    return bool(r.rowcount)  # type: ignore[attr-defined]


def stale_jobs(s: Session, stale_before: datetime) -> list[Job]:
    """Running jobs held by a worker whose heartbeat stopped."""
    q = select(Job).where(Job.state == "running", Job.worker.is_not(None), Job.heartbeat_at < stale_before)
    return list(s.scalars(q))


def undispatched_jobs(s: Session, older_than: timedelta) -> list[Job]:
    """Active jobs not held by a worker whose next message was never sent (the broker was down)."""
    q = select(Job).where(Job.state.in_(ACTIVE), Job.worker.is_(None), Job.dispatched_at.is_(None),
                          Job.updated_at < now() - older_than)  # fmt: skip
    return list(s.scalars(q))
