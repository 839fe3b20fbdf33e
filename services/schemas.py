"""Request and response bodies (pydantic)."""

from __future__ import annotations

from datetime import datetime
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from neumatex_core.pipeline import STAGES
from services.jobconfig import JobConfig, PresetName
from services.queue import QUEUES

if TYPE_CHECKING:
    StageName = str
    QueueName = str
else:  # the pipeline's stage order and the service's queues, written once (a 422 names the choices)
    StageName = Literal[STAGES]
    QueueName = Literal[QUEUES]


class CaptureOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: str
    name: str
    files: int
    bytes: int
    frames: int
    created_at: datetime


class UploadOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: str
    name: str
    files: int
    bytes: int
    created_at: datetime


class UploadInit(BaseModel):
    name: str = ""


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    capture_id: str = Field(max_length=100)
    preset: PresetName = "cpu"
    config: JobConfig = Field(default_factory=JobConfig, description="ExtractConfig field overrides; TTO under 'tto'")
    queue: QueueName | None = None
    idempotency_key: str | None = Field(None, max_length=200, description="or the Idempotency-Key header")
    webhook_url: str | None = Field(None, max_length=2000, description="http(s) URL POSTed a signed JSON body when "
                                    "the job completes, fails or is canceled (docs/service.md, Webhooks)")


class JobRetry(BaseModel):
    from_stage: StageName | None = None


class StageRunOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    stage: str
    attempt: int
    worker: str
    status: str
    started_at: datetime
    finished_at: datetime | None
    seconds: float | None


class WebhookAttemptOut(BaseModel):
    at: str
    status_code: int | None = Field(description="the receiver's answer; null: no answer (connection error)")
    error: str = Field(description="empty when delivered")
    seconds: float


class WebhookDeliveryOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: str
    url: str
    state: str = Field(description="the job's terminal state announced")
    job_attempt: int
    status: str = Field(description="pending, delivered or failed (attempts spent)")
    attempts: int
    next_at: datetime | None = Field(None, description="when a pending delivery is tried next")
    created_at: datetime
    delivered_at: datetime | None
    log: list[WebhookAttemptOut]


class JobOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: str
    capture_id: str
    state: str
    stage: str
    stage_fraction: float
    progress: float
    message: str
    preset: str
    config: dict[str, Any]
    queue: str
    metrics: dict[str, Any]
    timings: dict[str, Any]
    stages_done: list[str]
    error: str
    idempotency_key: str | None
    attempt: int
    worker: str | None
    heartbeat_at: datetime | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    eta_s: float | None = None
    waiting: str | None = Field(None, description="why a queued job is not running yet (no live worker takes its "
                                "queue), else null")  # fmt: skip
    stage_runs: list[StageRunOut] = []
    webhook_url: str | None = None
    webhooks: list[WebhookDeliveryOut] = Field([], description="webhook deliveries with every attempt (job page)")


class JobPage(BaseModel):
    items: list[JobOut]
    total: int
    limit: int
    offset: int
    next_offset: int | None


class AssetManifest(BaseModel):
    job_id: str
    files: list[str]
    bytes: int
    manifest: dict[str, Any]


class StorageUsage(BaseModel):
    used_bytes: int
    limit_bytes: int | None = Field(description="null: no limit")
    captures_bytes: int
    uploads_bytes: int
    jobs_bytes: int = Field(description="the jobs' work folders and assets")


class JobsUsage(BaseModel):
    active: int = Field(description="queued and running jobs")
    limit: int | None = Field(description="null: no limit")


class QuotaOut(BaseModel):
    tenant: str
    storage: StorageUsage
    jobs: JobsUsage
    work_retention_s: float | None = Field(description="finished jobs' work folders are removed after this; null: kept")


class WebhookSecret(BaseModel):
    secret: str = Field(description="HMAC-SHA256 key of this tenant's webhook signatures")
    header: str = Field(description="the signature header: t=<unix seconds>,v1=<hex HMAC of '<t>.' + raw body>")


class Deleted(BaseModel):
    deleted: str = Field(description="what was removed, e.g. 'capture cap_...'")
    jobs: list[str] = Field(default_factory=list, description="jobs removed with a capture")
    bytes_freed: int
