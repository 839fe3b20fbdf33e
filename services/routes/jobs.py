"""Jobs: create (config + idempotency key; the config, device and queue checked here, the tenant's limits too),
list (filters, paging), get, cancel, retry/restart, and the progress stream (server-sent events; each event's id is
its row id, so a client reconnects with Last-Event-ID; streams end with an `event: shutdown` when the API stops).
State changes go through services/lifecycle.py. The stream reads new events from the database when the job's Redis
channel wakes it (lifecycle.Wakeup), and every SAFETY_POLL_S in any case (Redis down: only then). Records and events
are shown without server paths (services/redact.py)."""

from __future__ import annotations

import json
import re
import time
from collections.abc import AsyncIterator
from typing import Annotated

import anyio
from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.responses import StreamingResponse
from sqlalchemy.exc import IntegrityError

from neumatex_core.pipeline import STAGES
from services import cleanup, crud, fleet, lifecycle, quota, shutdown, webhooks
from services.core.db import session_scope
from services.errors import ApiError, not_found
from services.jobconfig import build_config, given
from services.models import TERMINAL, Capture, Job, now
from services.redact import redact_data, redact_text
from services.routes.deps import Offset, SessionDep, TenantDep
from services.schemas import JobCreate, JobOut, JobPage, JobRetry, StageRunOut, WebhookDeliveryOut

router = APIRouter(tags=["jobs"])
SAFETY_POLL_S = 5.0  # a stream reads the database at least this often (a missed wake-up, Redis down)
SLICE_S = 0.2  # a stream checks for shutdown and a closed connection this often (no database read)
KEEP_ALIVE_S = 15.0
EVENTS_PAGE = 500  # events per database read


def job_out(s: SessionDep, job: Job, runs: bool = True) -> JobOut:
    out = JobOut.model_validate(job)
    out.message, out.error = redact_text(out.message), redact_text(out.error)
    out.metrics = redact_data(out.metrics)
    if job.state == "queued":
        out.waiting = fleet.queue_waiting(s, job.queue) or None
    if runs:
        out.stage_runs = [StageRunOut.model_validate(r) for r in crud.stage_runs(s, job.id)]
        if job.webhook_url:
            out.webhooks = [WebhookDeliveryOut.model_validate(d) for d in webhooks.deliveries_of(s, job.id)]
            for d in out.webhooks:
                d.next_at = d.next_at if d.status == "pending" else None
    if job.state == "running" and job.started_at is not None and job.progress > 0.02:
        elapsed = (now() - job.started_at).total_seconds()
        out.eta_s = max(0.0, elapsed * (1 - job.progress) / job.progress)
    return out


def _get(s: SessionDep, tenant_id: str, job_id: str) -> Job:
    job = crud.job_of_tenant(s, tenant_id, job_id)
    if job is None:
        raise not_found("job", job_id)
    return job


@router.post("/jobs", status_code=201, response_model=JobOut, responses={200: {"description": "idempotent replay"}})
def create_job(body: JobCreate, response: Response, s: SessionDep, tenant: TenantDep,
               idempotency_key: Annotated[str | None, Header(max_length=200)] = None) -> JobOut:
    key = body.idempotency_key or idempotency_key
    overrides = given(body.config)
    payload = {**body.model_dump(exclude={"idempotency_key", "config"}), "config": overrides}
    digest = crud.request_hash(payload)
    if key:
        found = crud.find_idempotent(s, tenant.id, key)
        if found is not None:
            if found.request_hash != digest:
                raise ApiError(409, f"idempotency key {key!r} was used for a different request")
            response.status_code = 200
            return job_out(s, found)
    cap = s.get(Capture, body.capture_id)
    if cap is None or cap.tenant_id != tenant.id:
        raise not_found("capture", body.capture_id)
    try:
        config = build_config(body.preset, body.config)
    except (ValueError, TypeError) as exc:
        raise ApiError(422, f"bad job config: {exc}") from None
    queue = lifecycle.job_queue(body.preset, body.queue)
    problem = fleet.device_problem(s, config.device, queue)
    if problem:
        raise ApiError(422, f"bad job config: {problem}")
    if body.webhook_url is not None:
        bad_url = webhooks.url_problem(body.webhook_url)
        if bad_url:
            raise ApiError(422, bad_url)
    quota.check_new_job(s, tenant.id)
    job = Job(tenant_id=tenant.id, capture_id=cap.id, preset=body.preset, config=overrides, queue=queue,
              idempotency_key=key, request_hash=digest, message=fleet.queue_waiting(s, queue),
              webhook_url=body.webhook_url)  # fmt: skip
    s.add(job)
    try:
        s.flush()
    except IntegrityError:  # the same key raced in from another request
        s.rollback()
        found = crud.find_idempotent(s, tenant.id, key or "")
        if found is None or found.request_hash != digest:
            raise ApiError(409, f"idempotency key {key!r} was used for a different request") from None
        response.status_code = 200
        return job_out(s, found)
    lifecycle.created(s, job)
    s.commit()
    lifecycle.dispatch(job.id, STAGES[0], job.attempt, job.queue)
    s.refresh(job)
    return job_out(s, job)


@router.get("/jobs", response_model=JobPage)
def list_jobs(s: SessionDep, tenant: TenantDep, state: str | None = None, capture_id: str | None = None,
              stage: str | None = None, limit: Annotated[int, Query(ge=1, le=500)] = 50,
              offset: Offset = 0) -> JobPage:
    rows, total = crud.list_jobs(s, tenant.id, state, capture_id, stage, limit, offset)
    nxt = offset + len(rows) if offset + len(rows) < total else None
    return JobPage(items=[job_out(s, j, runs=False) for j in rows], total=total, limit=limit, offset=offset,
                   next_offset=nxt)  # fmt: skip


@router.get("/jobs/{job_id}", response_model=JobOut)
def get_job(job_id: str, s: SessionDep, tenant: TenantDep) -> JobOut:
    return job_out(s, _get(s, tenant.id, job_id))


@router.post("/jobs/{job_id}/cancel", response_model=JobOut)
def cancel_job(job_id: str, s: SessionDep, tenant: TenantDep) -> JobOut:
    job = _get(s, tenant.id, job_id)
    if not lifecycle.cancel(s, job):
        raise ApiError(409, f"job {job_id} is {job.state}; only queued or running jobs can be canceled")
    s.commit()
    s.refresh(job)
    return job_out(s, job)


@router.post("/jobs/{job_id}/retry", response_model=JobOut,
             summary="Run a failed or canceled job again from its first unfinished stage (or from_stage)")
def retry_job(job_id: str, s: SessionDep, tenant: TenantDep, body: JobRetry | None = None) -> JobOut:
    job = _get(s, tenant.id, job_id)
    from_stage: str | None = body.from_stage if body else None
    if job.state not in ("failed", "canceled") and not (job.state == "completed" and from_stage):
        raise ApiError(409, f"job {job_id} is {job.state}; retry needs a failed or canceled job (or a completed "
                       "one with from_stage)")
    kept = cleanup.kept_stages(job)  # its work folder may have been deleted or reaped (retention)
    if len(kept) < len(job.stages_done or []) and (from_stage is None or STAGES.index(from_stage) > len(kept)):
        from_stage = STAGES[len(kept)]
    quota.check_new_job(s, tenant.id)
    if from_stage is not None:
        from services.storage import get_storage

        storage = get_storage()
        for st in STAGES[STAGES.index(from_stage):]:
            storage.delete(f"work/{job.id}/{st}")
    got = lifecycle.requeue(s, job, f"retry requested from {from_stage or 'the first unfinished stage'}", from_stage)
    if got is None:
        raise ApiError(409, f"job {job_id} changed meanwhile; try again")
    s.commit()
    lifecycle.dispatch(job.id, got[1], got[0], job.queue)
    s.refresh(job)
    return job_out(s, job)


def event_id(header: str | None) -> int:
    """The Last-Event-ID header as the id to resume after (0 without it); 400 when it is not an event id."""
    if header is None or not header.strip():
        return 0
    if not re.fullmatch(r"[0-9]{1,18}", header.strip()):
        raise ApiError(400, f"the Last-Event-ID header must be the id of an event (a whole number), not "
                       f"{header[:40]!r}")
    return int(header)


@router.get("/jobs/{job_id}/events", summary="Progress stream (text/event-stream)",
            response_class=StreamingResponse, responses={200: {"content": {"text/event-stream": {}}}})
async def job_events(job_id: str, request: Request, tenant: TenantDep,
                     last_event_id: Annotated[str | None, Header()] = None) -> StreamingResponse:
    with session_scope() as s:
        _get(s, tenant.id, job_id)
    start = event_id(last_event_id)

    def poll(after: int) -> tuple[list[tuple[int, str, str]], str]:
        with session_scope() as s:
            rows = crud.events_after(s, job_id, after, EVENTS_PAGE)
            job = s.get(Job, job_id)
            return ([(e.id, e.kind, json.dumps({**redact_data(e.data), "kind": e.kind, "at": e.created_at.isoformat()}))
                     for e in rows], job.state if job else "canceled")  # fmt: skip

    async def stream() -> AsyncIterator[str]:
        after = start
        wake = await lifecycle.Wakeup.open(job_id)  # subscribed before the first read: no event is missed
        try:
            yield "retry: 1000\n\n"
            due, next_poll, sent_at = True, 0.0, time.monotonic()
            while not await request.is_disconnected():
                if shutdown.STOPPING.is_set():
                    yield f"event: shutdown\ndata: {json.dumps({'message': shutdown.MESSAGE})}\n\n"
                    return
                if due or time.monotonic() >= next_poll:
                    rows, state = await anyio.to_thread.run_sync(poll, after)
                    next_poll = time.monotonic() + SAFETY_POLL_S
                    for ident, kind, data in rows:
                        after = ident
                        yield f"id: {ident}\nevent: {kind}\ndata: {data}\n\n"
                    if not rows and state in TERMINAL:
                        yield f"event: end\ndata: {json.dumps({'state': state})}\n\n"
                        return
                    if rows:
                        sent_at = time.monotonic()
                    # read again at once when the page was full, or the job ended (its last events may have been
                    # committed between the two reads of `poll`)
                    due = len(rows) >= EVENTS_PAGE or (bool(rows) and state in TERMINAL)
                    if due:
                        continue
                if time.monotonic() - sent_at >= KEEP_ALIVE_S:
                    sent_at = time.monotonic()
                    yield ": keep-alive\n\n"
                if wake is not None and not wake.broken:
                    due = await wake.wait(SLICE_S)
                    continue
                await anyio.sleep(SLICE_S)  # no wake-ups (Redis down): the safety poll only
                if time.monotonic() >= next_poll:  # subscribe again before that poll
                    with anyio.CancelScope(shield=True):
                        if wake is not None:
                            await wake.close()
                        wake = await lifecycle.Wakeup.open(job_id, timeout=0.5)
        finally:
            if wake is not None:
                with anyio.CancelScope(shield=True):  # also when the client went away (the stream is cancelled)
                    await wake.close()

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
