"""Request and response bodies (pydantic)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


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
    capture_id: str
    preset: Literal["tiny", "cpu", "gpu"] = "cpu"
    config: dict[str, Any] = Field(default_factory=dict, description="ExtractConfig field overrides; TTO under 'tto'")
    queue: Literal["cpu", "gpu"] | None = None
    idempotency_key: str | None = Field(None, max_length=200, description="or the Idempotency-Key header")


class JobRetry(BaseModel):
    from_stage: Literal["validate", "prepare_views", "lmrm", "tto", "export"] | None = None


class StageRunOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    stage: str
    attempt: int
    worker: str
    status: str
    started_at: datetime
    finished_at: datetime | None
    seconds: float | None


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
    stage_runs: list[StageRunOut] = []


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
