"""The caller's tenant: GET /v1/quota (stored bytes and active jobs against the tenant's limits, and the work
folders' retention), GET /v1/me (the tenant and its quota) and GET /v1/webhook-secret (the key its webhooks are
signed with)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from services import quota, webhooks
from services.core.config import get_settings
from services.routes.deps import SessionDep, TenantDep
from services.schemas import JobsUsage, QuotaOut, StorageUsage, WebhookSecret

router = APIRouter(tags=["tenant"])


@router.get("/quota", response_model=QuotaOut, summary="Storage and active jobs against this tenant's limits")
def get_quota(s: SessionDep, tenant: TenantDep) -> QuotaOut:
    use, lim = quota.usage(s, tenant.id), quota.limits(s, tenant.id)
    keep = get_settings().work_retention_s
    return QuotaOut(tenant=tenant.name,
                    storage=StorageUsage(used_bytes=use.stored, limit_bytes=lim.storage_bytes,
                                         captures_bytes=use.captures_bytes, uploads_bytes=use.uploads_bytes,
                                         jobs_bytes=use.jobs_bytes),
                    jobs=JobsUsage(active=use.active_jobs, limit=lim.active_jobs),
                    work_retention_s=keep if keep > 0 else None)  # fmt: skip


@router.get("/me", summary="The tenant of this API key, with its quota")
def me(s: SessionDep, tenant: TenantDep) -> dict[str, Any]:
    return {"tenant": {"id": tenant.id, "name": tenant.name, "created_at": tenant.created_at.isoformat()},
            "quota": get_quota(s, tenant).model_dump()}  # fmt: skip


@router.get("/webhook-secret", response_model=WebhookSecret, summary="The secret of this tenant's webhook signatures")
def webhook_secret(tenant: TenantDep) -> WebhookSecret:
    return WebhookSecret(secret=webhooks.tenant_secret(tenant.id), header=webhooks.SIGNATURE_HEADER)
