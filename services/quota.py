"""Per-tenant limits: stored bytes (captures, staged uploads, the jobs' work folders and assets) and active jobs
(queued + running). The settings tenant_storage_bytes and tenant_active_jobs apply to every tenant unless its
tenant_limits row overrides them (`python -m services set-limits`); 0 or a negative value means no limit.

Over the storage quota: 507 (Insufficient Storage, with the usage and what to delete); at the job limit: 429 with
Retry-After. Capture and upload bytes come from the database; job bytes are measured on the storage (file sizes
in the folder, object sizes in the bucket).
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.core.config import get_settings
from services.errors import ApiError
from services.models import ACTIVE, Capture, Job, TenantLimits, Upload
from services.storage import get_storage

MiB = 1024**2


@dataclass
class Limits:
    storage_bytes: int | None  # None: no limit
    active_jobs: int | None


@dataclass
class Usage:
    captures_bytes: int
    uploads_bytes: int
    jobs_bytes: int
    active_jobs: int

    @property
    def stored(self) -> int:
        return self.captures_bytes + self.uploads_bytes + self.jobs_bytes


def _positive(value: int | None) -> int | None:
    return value if value is not None and value > 0 else None


def limits(s: Session, tenant_id: str) -> Limits:
    st = get_settings()
    row = s.get(TenantLimits, tenant_id)
    storage = row.storage_bytes if row is not None and row.storage_bytes is not None else st.tenant_storage_bytes
    jobs = row.active_jobs if row is not None and row.active_jobs is not None else st.tenant_active_jobs
    return Limits(_positive(storage), _positive(jobs))


def job_bytes(job_id: str) -> int:
    """Bytes stored for the job: its work folder and its asset (object sizes on S3)."""
    storage = get_storage()  # S3: one listing per folder (sizes come with the listing)
    return sum(storage.sizes(f"work/{job_id}").values()) + sum(storage.sizes(f"assets/{job_id}").values())


def usage(s: Session, tenant_id: str) -> Usage:
    captures = s.scalar(select(func.coalesce(func.sum(Capture.bytes), 0)).where(Capture.tenant_id == tenant_id))
    uploads = s.scalar(select(func.coalesce(func.sum(Upload.bytes), 0)).where(Upload.tenant_id == tenant_id))
    jobs = sum(job_bytes(j) for j in s.scalars(select(Job.id).where(Job.tenant_id == tenant_id)))
    active = s.scalar(select(func.count()).where(Job.tenant_id == tenant_id, Job.state.in_(ACTIVE)))
    return Usage(int(captures or 0), int(uploads or 0), jobs, int(active or 0))


def over_quota(used: int, adding: int, limit: int) -> ApiError:
    return ApiError(507, f"storage quota exceeded: {used / MiB:.1f} MiB stored of {limit / MiB:.1f} MiB allowed, "
                    f"{adding / MiB:.1f} MiB more would not fit; delete captures (DELETE /v1/captures/{{id}}) or "
                    "assets (DELETE /v1/jobs/{id}/asset) first")  # fmt: skip


def check_storage(s: Session, tenant_id: str, adding: int) -> None:
    """507 when `adding` more bytes would take the tenant over its storage quota (adding 0: when it is over)."""
    limit = limits(s, tenant_id).storage_bytes
    if limit is None:
        return
    used = usage(s, tenant_id).stored
    if used + adding > limit or used >= limit:
        raise over_quota(used, adding, limit)


def check_new_job(s: Session, tenant_id: str) -> None:
    """429 at the active-job limit; 507 when the tenant's storage is already over its quota (a job writes more)."""
    lim = limits(s, tenant_id)
    if lim.active_jobs is not None:
        active = s.scalar(select(func.count()).where(Job.tenant_id == tenant_id, Job.state.in_(ACTIVE))) or 0
        if active >= lim.active_jobs:
            raise ApiError(429, f"too many active jobs: {active} queued or running, at most {lim.active_jobs} at "
                           "once; wait for one to finish or cancel one (POST /v1/jobs/{id}/cancel)",
                           headers={"Retry-After": "30"})  # fmt: skip
    check_storage(s, tenant_id, 0)
