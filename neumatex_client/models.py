"""Response bodies of the job service, as the client sees them. They mirror `services/schemas.py` field for field
(tests/service/test_client.py compares them with the app's OpenAPI schema), but this package imports nothing of
the service, so a pipeline machine needs only httpx, pydantic and tqdm. Unknown fields a newer server sends are
ignored."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict

TERMINAL = ("completed", "failed", "canceled")


class _Model(BaseModel):
    model_config = ConfigDict(extra="ignore")


class Capture(_Model):
    id: str
    name: str
    files: int
    bytes: int
    frames: int
    created_at: datetime


class Upload(_Model):
    id: str
    name: str
    files: int
    bytes: int
    created_at: datetime


class StageRun(_Model):
    stage: str
    attempt: int
    worker: str
    status: str
    started_at: datetime
    finished_at: datetime | None
    seconds: float | None


class WebhookAttempt(_Model):
    at: str
    status_code: int | None
    error: str
    seconds: float


class WebhookDelivery(_Model):
    id: str
    url: str
    state: str
    job_attempt: int
    status: str
    attempts: int
    next_at: datetime | None = None
    created_at: datetime
    delivered_at: datetime | None
    log: list[WebhookAttempt]


class Job(_Model):
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
    waiting: str | None = None
    stage_runs: list[StageRun] = []
    webhook_url: str | None = None
    webhooks: list[WebhookDelivery] = []

    @property
    def done(self) -> bool:
        """completed, failed or canceled"""
        return self.state in TERMINAL


class JobPage(_Model):
    items: list[Job]
    total: int
    limit: int
    offset: int
    next_offset: int | None


class AssetManifest(_Model):
    job_id: str
    files: list[str]
    bytes: int
    manifest: dict[str, Any]


class StorageUsage(_Model):
    used_bytes: int
    limit_bytes: int | None
    captures_bytes: int
    uploads_bytes: int
    jobs_bytes: int


class JobsUsage(_Model):
    active: int
    limit: int | None


class Quota(_Model):
    tenant: str
    storage: StorageUsage
    jobs: JobsUsage
    work_retention_s: float | None


class WebhookSecret(_Model):
    secret: str
    header: str


class Deleted(_Model):
    deleted: str
    jobs: list[str] = []
    bytes_freed: int


# client model -> the service's schema component of the same shape (checked by the tests)
SCHEMA_NAMES: dict[type[BaseModel], str] = {
    Capture: "CaptureOut", Upload: "UploadOut", StageRun: "StageRunOut", WebhookAttempt: "WebhookAttemptOut",
    WebhookDelivery: "WebhookDeliveryOut", Job: "JobOut", JobPage: "JobPage", AssetManifest: "AssetManifest",
    StorageUsage: "StorageUsage", JobsUsage: "JobsUsage", Quota: "QuotaOut", WebhookSecret: "WebhookSecret",
    Deleted: "Deleted",
}
