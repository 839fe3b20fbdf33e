"""Plain queries of the API: tenants and API keys, events after an id, jobs by tenant, idempotency, listing and
stage runs. Every change of a job's state lives in services/lifecycle.py."""

from __future__ import annotations

import hashlib
import json
import time
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.core.security import hash_api_key, new_api_key
from services.models import ApiKey, Event, Job, StageRun, Tenant


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
KEY_CACHE_S = 1.0  # a revoked key stops working within this many seconds, in every API process (fast path too)


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
