"""Settings from the environment (prefix NEUMATEX_, e.g. NEUMATEX_DATABASE_URL) or a .env file.

Defaults run everything embedded on one machine: SQLite and local storage under `data_dir`, Redis on localhost.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from neumatex_core.pipeline import STAGES


class Settings(BaseSettings):
    """Every knob of the service. Sizes in bytes, times in seconds."""

    model_config = SettingsConfigDict(env_prefix="NEUMATEX_", env_file=".env", extra="ignore")

    data_dir: Path = Path("data/service")
    database_url: str = ""  # default: sqlite:///<data_dir>/jobs.db; PostgreSQL: postgresql+psycopg://...
    redis_url: str = "redis://127.0.0.1:6379/0"
    # storage (services/storage.py, docs/service.md "Storage"): "local", a folder shared by the API and the workers
    # (a network mount across hosts), or "s3", an S3-compatible bucket (workers then need no shared disk)
    storage: Literal["local", "s3"] = "local"
    storage_root: Path | None = None  # local storage folder (default <data_dir>/storage)
    s3_endpoint_url: str = ""  # e.g. http://minio:9000; empty: AWS S3 of s3_region
    s3_bucket: str = ""
    s3_region: str = ""  # empty: boto3's default (AWS_DEFAULT_REGION, the profile)
    s3_prefix: str = ""  # every key under this prefix in the bucket (one bucket, several services)
    # credentials: the standard AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY (or a profile, an instance role) unless set
    s3_access_key_id: str = ""
    s3_secret_access_key: str = ""
    scratch_dir: Path | None = None  # s3: local folder for uploads being unpacked and stage runs (default: TMPDIR)
    partial_store_every_s: float = 30.0  # s3: a running stage's outputs so far (the TTO checkpoint) stored this often

    # uploads
    max_upload_bytes: int = 2 * 1024**3  # request body (the zip, or all form files together)
    max_capture_bytes: int = 4 * 1024**3  # unpacked capture
    max_files: int = 10_000
    max_zip_ratio: float = 200.0
    allowed_suffixes: tuple[str, ...] = (".json", ".png", ".jpg", ".jpeg", ".exr", ".hdr", ".tif", ".tiff",
                                         ".obj", ".ply", ".glb", ".gltf", ".mtl", ".txt", ".md")  # fmt: skip
    upload_ttl_s: float = 24 * 3600  # unfinished init/upload sessions are removed after this
    min_free_bytes: int = 1024**3  # uploads stop with 507 (storage full) before the storage's free space drops below
    # uploads through the reverse proxy (deploy/nginx/, docs/service.md "Uploads through the proxy"): nginx writes
    # an upload's body to a file in proxy_body_dir and names it in a header with proxy_body_token, a secret it shares
    # with the API (a client reaching the API directly cannot name a file). Unset: bodies arrive through the API.
    proxy_body_dir: Path | None = None
    proxy_body_token: str = ""

    # workers
    heartbeat_s: float = 2.0
    stale_after_s: float = 30.0  # a running job whose heartbeat is older is re-queued by the reaper
    reaper_every_s: float = 5.0
    redispatch_after_s: float = 30.0  # a job left undispatched (broker was down) this long is sent again
    progress_every_s: float = 0.3  # progress events at most this often per job
    cancel_poll_s: float = 0.25  # should_stop() reads the database at most this often
    torch_threads: int = 0  # 0: torch's default
    stage_time_limits: dict[str, float] = Field(default_factory=lambda: {
        "validate": 600.0, "prepare_views": 3600.0, "lmrm": 1800.0, "tto": 6 * 3600.0, "export": 3600.0})
    visibility_timeout_s: float = 8 * 3600.0  # must exceed the longest stage time limit

    # tenants (per-tenant overrides: `python -m services set-limits`); 0: no limit
    tenant_storage_bytes: int = 50 * 1024**3  # captures, staged uploads, jobs' work folders and assets -> 507
    tenant_active_jobs: int = 8  # queued + running jobs at once -> 429
    work_retention_s: float = 7 * 24 * 3600.0  # finished jobs' work folders are removed after this (0: kept)
    worker_seen_s: float = 0.0  # a worker counts as live if seen this recently (0: stale_after_s)

    # API
    metrics_token: str = ""  # /metrics needs 'Authorization: Bearer <metrics_token>' ...
    metrics_public: bool = False  # ... unless this is true (a private network); neither: /metrics is 403
    shutdown_grace_s: float = 5.0  # on SIGTERM, progress streams end and the API stops within this (uvicorn)
    # a request's headers up to this many bytes reach the app, however TCP splits them (uvicorn's h11 buffers at
    # most 16 KiB of an incomplete head by default, so a longer one got a bare 400 or a reset by chance); longer:
    # a 400 from the server
    max_header_bytes: int = 128 * 1024
    bootstrap_tenant: str = ""  # with bootstrap_api_key: created at start-up if missing (python -m services serve)
    bootstrap_api_key: str = ""
    public_url: str = "http://127.0.0.1:8000"
    cors_origins: list[str] = []
    report_token_ttl_s: float = 900.0  # links to a job's report (POST /v1/jobs/{id}/report-token) expire after this
    session_ttl_s: float = 12 * 3600.0  # the dashboard's login (a signed HttpOnly cookie) lasts this long
    session_cookie_secure: bool | None = None  # the cookie's Secure flag; None: when public_url is https

    # webhooks (services/webhooks.py): POSTed by the API process when a job ends, signed with HMAC-SHA256
    webhook_secret: str = ""  # the tenants' signing secrets derive from it (empty: <data_dir>/webhook-secret.txt)
    webhook_allow_private: bool = False  # allow webhook URLs on loopback/private/link-local addresses (tests, LANs)
    webhook_timeout_s: float = 10.0  # per delivery attempt
    webhook_max_attempts: int = 8  # then the delivery is marked failed
    webhook_backoff_s: float = 5.0  # first retry after this, doubling per attempt (Retry-After is honoured)
    webhook_max_backoff_s: float = 3600.0
    webhook_poll_s: float = 1.0  # how often the sender looks for due deliveries

    @model_validator(mode="after")
    def _check(self) -> Settings:
        longest = max(self.stage_time_limits.values())
        if self.visibility_timeout_s <= longest + 60:
            raise ValueError(f"visibility_timeout_s ({self.visibility_timeout_s:.0f} s) must exceed the longest stage "
                             f"time limit ({longest:.0f} s) plus a minute, or a running stage is delivered twice")
        unknown = set(self.stage_time_limits) - set(STAGES)
        if unknown:
            raise ValueError(f"stage_time_limits names unknown stages {sorted(unknown)}; stages: {STAGES}")
        if self.storage == "s3" and not self.s3_bucket:
            raise ValueError("storage 's3' needs a bucket: set NEUMATEX_S3_BUCKET (and NEUMATEX_S3_ENDPOINT_URL for "
                             "an S3-compatible server such as MinIO)")
        if self.proxy_body_dir is not None and len(self.proxy_body_token) < 16:
            raise ValueError("proxy_body_dir is set but proxy_body_token is not (at least 16 characters): set "
                             "NEUMATEX_PROXY_BODY_TOKEN to the secret the proxy sends (deploy/nginx/)")
        return self

    @property
    def db_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'jobs.db').resolve()}"

    @property
    def local_root(self) -> Path:
        return (self.storage_root or self.data_dir / "storage").resolve()

    @property
    def live_within_s(self) -> float:
        return self.worker_seen_s or self.stale_after_s

    def time_limit(self, stage: str) -> float:
        return float(self.stage_time_limits.get(stage, 3600.0))


@lru_cache
def get_settings() -> Settings:
    return Settings()
