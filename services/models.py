"""Tables: tenants, API keys (hashed), uploads (init/upload/commit sessions), captures, jobs, stage runs, events,
per-tenant limits, webhook deliveries, and the workers' presence (which queues live workers take, and whether they
can run CUDA).

The job row is the source of truth: state (queued, running, completed, failed, canceled), the current stage,
overall progress in [0, 1], metrics and timings per stage, the error in plain words, the idempotency key, the
dispatch generation (`attempt`: bumped on every re-queue so stale broker messages are dropped), the worker that
holds it and that worker's heartbeat.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import JSON, BigInteger, Boolean, DateTime, Float, ForeignKey, Integer, String, Text, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from services.core.base import Base

JOB_STATES = ("queued", "running", "completed", "failed", "canceled")
ACTIVE = ("queued", "running")
TERMINAL = ("completed", "failed", "canceled")


def now() -> datetime:
    return datetime.now(UTC).replace(tzinfo=None)  # naive UTC everywhere (SQLite keeps no zone)


def new_id(prefix: str) -> str:
    return f"{prefix}_{uuid.uuid4().hex[:20]}"


class Tenant(Base):
    __tablename__ = "tenants"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=lambda: new_id("ten"))
    name: Mapped[str] = mapped_column(String(200), unique=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=now)


class ApiKey(Base):
    __tablename__ = "api_keys"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id"), index=True)
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))  # the first characters, to tell keys apart in listings
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=now)


class Upload(Base):
    """A NodeODM-style upload session: init, then files in one or more requests, then commit."""

    __tablename__ = "uploads"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=lambda: new_id("upl"))
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id"), index=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    files: Mapped[int] = mapped_column(Integer, default=0)
    bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=now)


class Capture(Base):
    __tablename__ = "captures"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=lambda: new_id("cap"))
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id"), index=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    storage_key: Mapped[str] = mapped_column(String(300))  # folder holding transforms.json
    files: Mapped[int] = mapped_column(Integer, default=0)
    bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    frames: Mapped[int] = mapped_column(Integer, default=0)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=now)


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (UniqueConstraint("tenant_id", "idempotency_key", name="uq_job_idempotency"),)
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=lambda: new_id("job"))
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id"), index=True)
    capture_id: Mapped[str] = mapped_column(ForeignKey("captures.id"), index=True)
    state: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    stage: Mapped[str] = mapped_column(String(32), default="validate")  # current (or last) stage
    stage_fraction: Mapped[float] = mapped_column(Float, default=0.0)
    progress: Mapped[float] = mapped_column(Float, default=0.0)  # overall, never decreases within an attempt
    message: Mapped[str] = mapped_column(Text, default="")
    preset: Mapped[str] = mapped_column(String(16), default="cpu")
    config: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # the overrides given at creation
    queue: Mapped[str] = mapped_column(String(16), default="cpu")
    metrics: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # per stage
    timings: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # seconds per stage
    stages_done: Mapped[list[str]] = mapped_column(JSON, default=list)
    error: Mapped[str] = mapped_column(Text, default="")
    idempotency_key: Mapped[str | None] = mapped_column(String(200), nullable=True)
    request_hash: Mapped[str] = mapped_column(String(64), default="")
    attempt: Mapped[int] = mapped_column(Integer, default=1)  # dispatch generation
    worker: Mapped[str | None] = mapped_column(String(200), nullable=True)  # holder while a stage runs
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    dispatched_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)  # None: not sent yet
    asset_key: Mapped[str | None] = mapped_column(String(300), nullable=True)
    webhook_url: Mapped[str | None] = mapped_column(String(2000), nullable=True)  # POSTed when the job ends
    created_at: Mapped[datetime] = mapped_column(DateTime, default=now, index=True)
    updated_at: Mapped[datetime] = mapped_column(DateTime, default=now, onupdate=now)
    started_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)


class StageRun(Base):
    """One execution of one stage by one worker: finished, failed, canceled, lost (the worker vanished) or
    running."""

    __tablename__ = "stage_runs"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), index=True)
    stage: Mapped[str] = mapped_column(String(32))
    attempt: Mapped[int] = mapped_column(Integer)
    worker: Mapped[str] = mapped_column(String(200))
    status: Mapped[str] = mapped_column(String(16), default="running")
    started_at: Mapped[datetime] = mapped_column(DateTime, default=now)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    seconds: Mapped[float | None] = mapped_column(Float, nullable=True)


class Event(Base):
    """The job's history, streamed to clients over SSE (the id is the SSE event id)."""

    __tablename__ = "events"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"), index=True)
    kind: Mapped[str] = mapped_column(String(32))  # state, stage, progress, requeued, worker
    data: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=now)


class WebhookDelivery(Base):
    """One webhook notification of a job reaching a terminal state (services/webhooks.py): pending until its URL
    answers 2xx (delivered) or max attempts are spent (failed); `log` holds every attempt. No foreign key, so
    deleting a job's records leaves it to be dropped by the sender."""

    __tablename__ = "webhook_deliveries"
    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=lambda: new_id("whd"))
    job_id: Mapped[str] = mapped_column(String(32), index=True)
    tenant_id: Mapped[str] = mapped_column(String(32))
    url: Mapped[str] = mapped_column(String(2000))
    state: Mapped[str] = mapped_column(String(16))  # the job's terminal state it announces
    job_attempt: Mapped[int] = mapped_column(Integer, default=1)
    status: Mapped[str] = mapped_column(String(16), default="pending", index=True)  # pending, delivered, failed
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_at: Mapped[datetime] = mapped_column(DateTime, default=now, index=True)
    log: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=now)
    delivered_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)


class TenantLimits(Base):
    """Per-tenant overrides of the settings tenant_storage_bytes and tenant_active_jobs (None: the setting's)."""

    __tablename__ = "tenant_limits"
    tenant_id: Mapped[str] = mapped_column(ForeignKey("tenants.id"), primary_key=True)
    storage_bytes: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    active_jobs: Mapped[int | None] = mapped_column(Integer, nullable=True)


class WorkerNode(Base):
    """A Celery worker's presence: its queues and whether it can run CUDA, written every heartbeat_s by the worker
    (workers/presence.py); live while seen within live_within_s. Job creation checks `device` and `queue` here."""

    __tablename__ = "worker_nodes"
    name: Mapped[str] = mapped_column(String(200), primary_key=True)
    queues: Mapped[list[str]] = mapped_column(JSON, default=list)
    cuda: Mapped[bool] = mapped_column(Boolean, default=False)
    started_at: Mapped[datetime] = mapped_column(DateTime, default=now)
    seen_at: Mapped[datetime] = mapped_column(DateTime, default=now, index=True)
