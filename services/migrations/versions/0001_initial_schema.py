"""Initial schema: the tables of services/models.py as Base.metadata.create_all made them before migrations.

Written by autogenerate against an empty database, then reviewed. A database made by that create_all is stamped at
this revision (services.core.db.upgrade sets the config attribute `skip_existing_tables`): its tables are kept and
only those it lacks are created, as create_all would have done.

Revision ID: 0001
Revises:
Create Date: 2026-11-25
"""

from __future__ import annotations

from typing import Any

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    config = op.get_context().config
    existing: set[str] = set()
    if config is not None and config.attributes.get("skip_existing_tables"):
        existing = set(sa.inspect(op.get_bind()).get_table_names())

    def table(name: str, *items: Any, indexes: tuple[str, ...] = ()) -> None:
        """Create table `name` with an index (ix_<table>_<column>) on each of `indexes`, unless it exists."""
        if name in existing:
            return
        op.create_table(name, *items)
        for column in indexes:
            op.create_index(op.f(f"ix_{name}_{column}"), name, [column], unique=False)

    table("tenants",
          sa.Column("id", sa.String(length=32), nullable=False),
          sa.Column("name", sa.String(length=200), nullable=False),
          sa.Column("created_at", sa.DateTime(), nullable=False),
          sa.PrimaryKeyConstraint("id"),
          sa.UniqueConstraint("name"))  # fmt: skip
    table("webhook_deliveries",
          sa.Column("id", sa.String(length=32), nullable=False),
          sa.Column("job_id", sa.String(length=32), nullable=False),
          sa.Column("tenant_id", sa.String(length=32), nullable=False),
          sa.Column("url", sa.String(length=2000), nullable=False),
          sa.Column("state", sa.String(length=16), nullable=False),
          sa.Column("job_attempt", sa.Integer(), nullable=False),
          sa.Column("status", sa.String(length=16), nullable=False),
          sa.Column("attempts", sa.Integer(), nullable=False),
          sa.Column("next_at", sa.DateTime(), nullable=False),
          sa.Column("log", sa.JSON(), nullable=False),
          sa.Column("created_at", sa.DateTime(), nullable=False),
          sa.Column("delivered_at", sa.DateTime(), nullable=True),
          sa.PrimaryKeyConstraint("id"),
          indexes=("job_id", "next_at", "status"))  # fmt: skip
    table("worker_nodes",
          sa.Column("name", sa.String(length=200), nullable=False),
          sa.Column("queues", sa.JSON(), nullable=False),
          sa.Column("cuda", sa.Boolean(), nullable=False),
          sa.Column("started_at", sa.DateTime(), nullable=False),
          sa.Column("seen_at", sa.DateTime(), nullable=False),
          sa.PrimaryKeyConstraint("name"),
          indexes=("seen_at",))  # fmt: skip
    table("api_keys",
          sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
          sa.Column("tenant_id", sa.String(length=32), nullable=False),
          sa.Column("key_hash", sa.String(length=64), nullable=False),
          sa.Column("prefix", sa.String(length=16), nullable=False),
          sa.Column("revoked", sa.Boolean(), nullable=False),
          sa.Column("created_at", sa.DateTime(), nullable=False),
          sa.ForeignKeyConstraint(["tenant_id"], ["tenants.id"]),
          sa.PrimaryKeyConstraint("id"),
          sa.UniqueConstraint("key_hash"),
          indexes=("tenant_id",))  # fmt: skip
    table("captures",
          sa.Column("id", sa.String(length=32), nullable=False),
          sa.Column("tenant_id", sa.String(length=32), nullable=False),
          sa.Column("name", sa.String(length=200), nullable=False),
          sa.Column("storage_key", sa.String(length=300), nullable=False),
          sa.Column("files", sa.Integer(), nullable=False),
          sa.Column("bytes", sa.BigInteger(), nullable=False),
          sa.Column("frames", sa.Integer(), nullable=False),
          sa.Column("created_at", sa.DateTime(), nullable=False),
          sa.ForeignKeyConstraint(["tenant_id"], ["tenants.id"]),
          sa.PrimaryKeyConstraint("id"),
          indexes=("tenant_id",))  # fmt: skip
    table("tenant_limits",
          sa.Column("tenant_id", sa.String(length=32), nullable=False),
          sa.Column("storage_bytes", sa.BigInteger(), nullable=True),
          sa.Column("active_jobs", sa.Integer(), nullable=True),
          sa.ForeignKeyConstraint(["tenant_id"], ["tenants.id"]),
          sa.PrimaryKeyConstraint("tenant_id"))  # fmt: skip
    table("uploads",
          sa.Column("id", sa.String(length=32), nullable=False),
          sa.Column("tenant_id", sa.String(length=32), nullable=False),
          sa.Column("name", sa.String(length=200), nullable=False),
          sa.Column("files", sa.Integer(), nullable=False),
          sa.Column("bytes", sa.BigInteger(), nullable=False),
          sa.Column("created_at", sa.DateTime(), nullable=False),
          sa.ForeignKeyConstraint(["tenant_id"], ["tenants.id"]),
          sa.PrimaryKeyConstraint("id"),
          indexes=("tenant_id",))  # fmt: skip
    table("jobs",
          sa.Column("id", sa.String(length=32), nullable=False),
          sa.Column("tenant_id", sa.String(length=32), nullable=False),
          sa.Column("capture_id", sa.String(length=32), nullable=False),
          sa.Column("state", sa.String(length=16), nullable=False),
          sa.Column("stage", sa.String(length=32), nullable=False),
          sa.Column("stage_fraction", sa.Float(), nullable=False),
          sa.Column("progress", sa.Float(), nullable=False),
          sa.Column("message", sa.Text(), nullable=False),
          sa.Column("preset", sa.String(length=16), nullable=False),
          sa.Column("config", sa.JSON(), nullable=False),
          sa.Column("queue", sa.String(length=16), nullable=False),
          sa.Column("metrics", sa.JSON(), nullable=False),
          sa.Column("timings", sa.JSON(), nullable=False),
          sa.Column("stages_done", sa.JSON(), nullable=False),
          sa.Column("error", sa.Text(), nullable=False),
          sa.Column("idempotency_key", sa.String(length=200), nullable=True),
          sa.Column("request_hash", sa.String(length=64), nullable=False),
          sa.Column("attempt", sa.Integer(), nullable=False),
          sa.Column("worker", sa.String(length=200), nullable=True),
          sa.Column("heartbeat_at", sa.DateTime(), nullable=True),
          sa.Column("dispatched_at", sa.DateTime(), nullable=True),
          sa.Column("asset_key", sa.String(length=300), nullable=True),
          sa.Column("webhook_url", sa.String(length=2000), nullable=True),
          sa.Column("created_at", sa.DateTime(), nullable=False),
          sa.Column("updated_at", sa.DateTime(), nullable=False),
          sa.Column("started_at", sa.DateTime(), nullable=True),
          sa.Column("finished_at", sa.DateTime(), nullable=True),
          sa.ForeignKeyConstraint(["capture_id"], ["captures.id"]),
          sa.ForeignKeyConstraint(["tenant_id"], ["tenants.id"]),
          sa.PrimaryKeyConstraint("id"),
          sa.UniqueConstraint("tenant_id", "idempotency_key", name="uq_job_idempotency"),
          indexes=("capture_id", "created_at", "state", "tenant_id"))  # fmt: skip
    table("events",
          sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
          sa.Column("job_id", sa.String(length=32), nullable=False),
          sa.Column("kind", sa.String(length=32), nullable=False),
          sa.Column("data", sa.JSON(), nullable=False),
          sa.Column("created_at", sa.DateTime(), nullable=False),
          sa.ForeignKeyConstraint(["job_id"], ["jobs.id"]),
          sa.PrimaryKeyConstraint("id"),
          indexes=("job_id",))  # fmt: skip
    table("stage_runs",
          sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
          sa.Column("job_id", sa.String(length=32), nullable=False),
          sa.Column("stage", sa.String(length=32), nullable=False),
          sa.Column("attempt", sa.Integer(), nullable=False),
          sa.Column("worker", sa.String(length=200), nullable=False),
          sa.Column("status", sa.String(length=16), nullable=False),
          sa.Column("started_at", sa.DateTime(), nullable=False),
          sa.Column("finished_at", sa.DateTime(), nullable=True),
          sa.Column("seconds", sa.Float(), nullable=True),
          sa.ForeignKeyConstraint(["job_id"], ["jobs.id"]),
          sa.PrimaryKeyConstraint("id"),
          indexes=("job_id",))  # fmt: skip


def downgrade() -> None:
    for name in ("stage_runs", "events", "jobs", "uploads", "tenant_limits", "captures", "api_keys", "worker_nodes",
                 "webhook_deliveries", "tenants"):  # fmt: skip
        op.drop_table(name)  # its indexes go with it
