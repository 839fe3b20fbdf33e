"""The job lifecycle, owned here and only here: every change of a job's state, its events, and the stage messages.

States (services/models.py): queued -> running -> completed | failed | canceled; running -> queued again when the
job is re-queued (its worker vanished, or a retry) with a new `attempt`, so stale messages of older attempts are
dropped. The transitions:

- `created`      the API added a job: its `queued` event (then `dispatch` of the first stage)
- `claim`        a worker takes (job, stage, attempt): stale messages dropped, one conditional UPDATE (a live
                 holder wins), a StageRun row, `stage started` (and `state running`) events
- `record_progress` / `heartbeat` / `holder_problem`   while the stage runs
- `advance`      the stage finished: the next stage is dispatched, or the job is completed
- `fail`         the stage raised (bad input, crash, time limit)
- `stopped`      the worker stopped the stage because the job was canceled or given to another worker
- `cancel`       the client canceled a queued or running job (the worker notices within cancel_poll_s)
- `requeue`      back to queued with a new attempt (a retry, or `requeue_stale` for a worker that vanished)
- `redispatch_lost`   jobs whose next message never reached the broker are sent again
- `redispatch_unclaimed`   jobs whose message reached the broker but no worker claimed it, while their queue is
                 empty (a worker took it and lost its broker connection before claiming), are sent again

Every state change that can race is one conditional UPDATE on (id, attempt, worker, state) so exactly one side
wins; the API, the workers and the reaper (services/reaper.py, on Celery beat) all go through here.

Queues: the stages validate, prepare_views and export always run on the `cpu` queue; lmrm and tto on the job's
queue (`gpu` for the gpu preset or when the job asks for it): `stage_queue`.

Progress streams: every event written by `add_event` publishes a small wake-up on the Redis channel
`neumatex:job:<id>` after its transaction commits; the SSE route (services/routes/jobs.py) subscribes with
`Wakeup` and reads the new event rows only when woken (plus a slow safety poll). Redis down: nothing is published
and the streams fall back to the slow poll.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import redis
import redis.asyncio
from sqlalchemy import event, func, select, update
from sqlalchemy.orm import Session

from neumatex_core.pipeline import STAGES, StageProgress
from services import queue as broker
from services import webhooks
from services.core.config import get_settings
from services.core.db import session_scope
from services.models import ACTIVE, Capture, Event, Job, StageRun, now

log = logging.getLogger("neumatex.lifecycle")

# Share of the overall progress per stage (TTO dominates); sums to 1.
STAGE_WEIGHTS = {"validate": 0.05, "prepare_views": 0.15, "lmrm": 0.05, "tto": 0.6, "export": 0.15}
CPU_STAGES = ("validate", "prepare_views", "export")  # no GPU work in them: always on the cpu queue
assert set(STAGE_WEIGHTS) == set(STAGES) and set(CPU_STAGES) <= set(STAGES)


# -- where a job runs -----------------------------------------------------------------------------------------
def job_queue(preset: str, requested: str | None = None) -> str:
    """The job's queue: the one asked for, else `gpu` for the gpu preset and `cpu` for the others."""
    return requested or (broker.GPU if preset == "gpu" else broker.CPU)


def stage_queue(stage: str, queue: str) -> str:
    """The queue of one stage of a job on `queue`: validate, prepare_views and export on `cpu`, lmrm and tto on
    the job's queue."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r} (expected one of {', '.join(STAGES)})")
    return broker.CPU if stage in CPU_STAGES else queue


def overall_progress(stage: str, fraction: float) -> float:
    """The job's progress in [0, 1] when `stage` is `fraction` done."""
    i = STAGES.index(stage)
    before = sum(STAGE_WEIGHTS[s] for s in STAGES[:i])
    return min(1.0, before + STAGE_WEIGHTS[stage] * min(max(fraction, 0.0), 1.0))


def next_stage(job: Job) -> str | None:
    """The first stage the job has not finished (None: all done)."""
    return next((stage for stage in STAGES if stage not in (job.stages_done or [])), None)


# -- events and their wake-ups --------------------------------------------------------------------------------
_WAKE = "neumatex_wake"  # Session.info key: the job ids whose events this transaction wrote
CHANNEL_PREFIX = "neumatex:job:"  # Redis pub/sub channel per job: neumatex:job:<id> (SSE and services/fastpath.py)


def channel(job_id: str) -> str:
    """The Redis pub/sub channel woken after each committed event of the job."""
    return CHANNEL_PREFIX + job_id


def add_event(s: Session, job_id: str, kind: str, **data: Any) -> None:
    """One event of the job's history (streamed over SSE); terminal `state` events also queue the job's webhook. A
    wake-up is published on the job's channel once the transaction commits."""
    s.add(Event(job_id=job_id, kind=kind, data=data))
    s.info.setdefault(_WAKE, set()).add(job_id)
    if kind == "state" and data.get("state") in ("completed", "failed", "canceled"):
        webhooks.enqueue(s, job_id, str(data["state"]))  # in the same transaction as the transition


class _Publisher:
    """A Redis client for the wake-ups; after a failure it stays quiet for `pause_s` so a broker outage does not
    slow every commit down (the streams' safety poll covers the gap)."""

    pause_s = 2.0

    def __init__(self) -> None:
        self.client: redis.Redis | None = None
        self.quiet_until = 0.0
        self.lock = threading.Lock()

    def publish(self, job_ids: set[str]) -> None:
        if time.monotonic() < self.quiet_until:
            return
        try:
            with self.lock:
                if self.client is None:
                    self.client = redis.Redis.from_url(get_settings().redis_url, socket_timeout=0.5,
                                                       socket_connect_timeout=0.5)  # fmt: skip
                client = self.client
            pipe = client.pipeline(transaction=False)
            for job_id in job_ids:
                pipe.publish(channel(job_id), "1")
            pipe.execute()
        except (redis.RedisError, OSError) as exc:
            self.quiet_until = time.monotonic() + self.pause_s
            log.info("progress wake-ups not published (Redis unavailable: %s); streams poll instead", exc)


_PUBLISHER = _Publisher()


@event.listens_for(Session, "after_commit")
def _after_commit(s: Session) -> None:
    ids = s.info.pop(_WAKE, None)
    if ids:
        _PUBLISHER.publish(ids)


@event.listens_for(Session, "after_rollback")
def _after_rollback(s: Session) -> None:
    s.info.pop(_WAKE, None)


class Wakeup:
    """A progress stream's subscription to its job's channel (redis.asyncio). `open` returns None when Redis cannot
    be reached; `wait` returns True when woken (every pending wake-up is consumed), False on timeout; after a lost
    connection `broken` is set and the stream polls."""

    def __init__(self, client: redis.asyncio.Redis, pubsub: Any):
        self.client, self.pubsub, self.broken = client, pubsub, False

    @classmethod
    async def open(cls, job_id: str, timeout: float = 1.0) -> Wakeup | None:
        client = redis.asyncio.Redis.from_url(get_settings().redis_url, socket_connect_timeout=timeout)
        pubsub = client.pubsub()
        try:
            await pubsub.subscribe(channel(job_id))
            end = time.monotonic() + timeout
            while time.monotonic() < end:  # subscribed once Redis confirms: no wake-up after this is missed
                msg = await pubsub.get_message(timeout=max(0.01, end - time.monotonic()))
                if msg is not None and msg["type"] == "subscribe":
                    return cls(client, pubsub)
            raise TimeoutError("no subscribe confirmation")
        except (redis.RedisError, OSError, TimeoutError) as exc:
            log.info("progress stream of %s polls (Redis unavailable: %s)", job_id, exc)
            await _close(client, pubsub)
            return None

    async def wait(self, timeout: float) -> bool:
        if self.broken:
            return False
        try:
            msg = await self.pubsub.get_message(ignore_subscribe_messages=True, timeout=timeout)
            if msg is None:
                return False
            while await self.pubsub.get_message(ignore_subscribe_messages=True, timeout=0.0) is not None:
                pass
            return True
        except (redis.RedisError, OSError) as exc:
            log.info("progress wake-ups lost (%s); the stream polls", exc)
            self.broken = True
            return False

    async def close(self) -> None:
        await _close(self.client, self.pubsub)


async def _close(client: redis.asyncio.Redis, pubsub: Any) -> None:
    try:
        await pubsub.aclose()
        await client.aclose()
    except (redis.RedisError, OSError):
        pass


# -- dispatch -------------------------------------------------------------------------------------------------
def dispatch(job_id: str, stage: str, attempt: int, queue: str) -> bool:
    """Send (job, stage, attempt) to the stage's queue (`stage_queue` of the job's `queue`) and mark the job
    dispatched; False when the broker is down (the reaper's `redispatch_lost` sends it later)."""
    if not broker.send_stage(job_id, stage, attempt, stage_queue(stage, queue)):
        return False
    with session_scope() as s:
        s.execute(update(Job).where(Job.id == job_id, Job.attempt == attempt).values(dispatched_at=now()))
    return True


# -- API side -------------------------------------------------------------------------------------------------
def created(s: Session, job: Job) -> None:
    """A job the API just added (and flushed): its first event. Commit, then `dispatch(job.id, STAGES[0], ...)`."""
    add_event(s, job.id, "state", state="queued", stage=job.stage, progress=0.0, message=job.message)


def cancel(s: Session, job: Job) -> bool:
    """Queued or running -> canceled (a running worker sees it within cancel_poll_s and stops)."""
    r = s.execute(update(Job).where(Job.id == job.id, Job.state.in_(ACTIVE))
                  .values(state="canceled", finished_at=now(), message="canceled by the client"))  # fmt: skip
    if r.rowcount:  # type: ignore[attr-defined]
        add_event(s, job.id, "state", state="canceled", stage=job.stage, progress=job.progress,
                  message="canceled by the client")
        return True
    return False


def requeue(s: Session, job: Job, reason: str, from_stage: str | None = None) -> tuple[int, str] | None:
    """Back to queued with a new attempt (stale messages of older attempts are dropped), keeping the finished
    stages before `from_stage`; returns (attempt, first stage to run), or None when someone else changed the job
    first. Commit, then `dispatch`."""
    done = list(job.stages_done or [])
    if from_stage is not None:
        done = done[:STAGES.index(from_stage)]
    attempt = job.attempt + 1
    stage = next((st for st in STAGES if st not in done), STAGES[-1])
    r = s.execute(update(Job).where(Job.id == job.id, Job.attempt == job.attempt).values(
        attempt=attempt, state="queued", worker=None, heartbeat_at=None, dispatched_at=None, error="",
        stages_done=done, stage=stage, stage_fraction=0.0, finished_at=None, message=reason,
        progress=overall_progress(stage, 0.0) if stage != STAGES[0] else 0.0))
    if not r.rowcount:  # type: ignore[attr-defined]
        return None
    add_event(s, job.id, "requeued", attempt=attempt, stage=stage, message=reason)
    return attempt, stage


# -- reaper side ----------------------------------------------------------------------------------------------
def requeue_stale() -> list[str]:
    """Re-queue the running jobs whose worker stopped sending heartbeats (stale_after_s) from their first
    unfinished stage, marking that worker's stage runs lost, and send them; returns their ids."""
    stale_before = now() - timedelta(seconds=get_settings().stale_after_s)
    to_send: list[tuple[str, str, int, str]] = []
    with session_scope() as s:
        q = select(Job).where(Job.state == "running", Job.worker.is_not(None), Job.heartbeat_at < stale_before)
        for job in list(s.scalars(q)):
            worker, stage = job.worker, job.stage
            got = requeue(s, job, f"worker {worker} stopped sending heartbeats during {stage}; re-queued")
            if got is None:
                continue
            s.execute(update(StageRun).where(StageRun.job_id == job.id, StageRun.worker == worker,
                                             StageRun.status == "running")
                      .values(status="lost", finished_at=now()))  # fmt: skip
            to_send.append((job.id, got[1], got[0], job.queue))
            log.warning("job %s: worker %s vanished during %s; re-queued as attempt %d", job.id, worker, stage, got[0])
    return [job_id for job_id, stage, attempt, q in to_send if dispatch(job_id, stage, attempt, q)]


def redispatch_lost() -> list[str]:
    """Send again the active jobs no worker holds whose next message never reached the broker (redispatch_after_s
    after their last change); returns their ids."""
    older = now() - timedelta(seconds=get_settings().redispatch_after_s)
    with session_scope() as s:
        q = select(Job).where(Job.state.in_(ACTIVE), Job.worker.is_(None), Job.dispatched_at.is_(None),
                              Job.updated_at < older)  # fmt: skip
        todo = [(job.id, nxt, job.attempt, job.queue) for job in s.scalars(q) if (nxt := next_stage(job))]
    return [job_id for job_id, stage, attempt, q in todo if dispatch(job_id, stage, attempt, q)]


def redispatch_unclaimed() -> list[str]:
    """Send again the active jobs that were dispatched more than redispatch_after_s ago, that no worker has claimed,
    and whose stage queue holds no waiting message; returns their ids.

    Their message is not waiting in the queue (a job behind others keeps it non-empty), so a worker took it and
    never claimed the job: it lost its broker connection first (Redis restarted, network cut) or died between the
    two. The broker keeps such a message unacknowledged until the visibility timeout (hours), and the job would
    wait as long. A duplicate message is harmless: `claim` drops it ("not next", "held by another worker")."""
    older = now() - timedelta(seconds=get_settings().redispatch_after_s)
    with session_scope() as s:
        q = select(Job).where(Job.state.in_(ACTIVE), Job.worker.is_(None), Job.dispatched_at.is_not(None),
                              Job.dispatched_at < older)  # fmt: skip
        todo = [(job.id, nxt, job.attempt, job.queue) for job in s.scalars(q) if (nxt := next_stage(job))]
    empty: dict[str, bool] = {}
    sent = []
    for job_id, stage, attempt, queue in todo:
        name = stage_queue(stage, queue)
        if name not in empty:
            empty[name] = broker.waiting(name) == 0
        if empty[name] and dispatch(job_id, stage, attempt, queue):
            log.warning("job %s: its %s message was taken but never claimed; sent again", job_id, stage)
            sent.append(job_id)
    return sent


# -- worker side ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Claimed:
    """What a worker needs to run the stage it claimed: its StageRun id, the capture's storage key, the preset and
    the stored config overrides."""

    run_id: int
    capture_key: str
    preset: str
    overrides: dict[str, Any]


def claim(job_id: str, stage: str, attempt: int, worker: str) -> Claimed | str:
    """Take the job for `stage` (one conditional UPDATE) unless the message is stale (older attempt, finished or
    not the next stage, ended job) or another live worker holds it; the reason (a string) when not taken."""
    if stage not in STAGES:
        return "unknown stage"
    stale_before = now() - timedelta(seconds=get_settings().stale_after_s)
    with session_scope() as s:
        job = s.get(Job, job_id)
        if job is None or job.attempt != attempt or job.state not in ACTIVE:
            return "stale"
        if next_stage(job) != stage:
            return "not next"
        was_queued = job.state == "queued"
        r = s.execute(update(Job).where(
            Job.id == job_id, Job.attempt == attempt, Job.state.in_(ACTIVE),
            (Job.worker.is_(None)) | (Job.worker == worker) | (Job.heartbeat_at < stale_before),
        ).values(state="running", stage=stage, stage_fraction=0.0, worker=worker, heartbeat_at=now(),
                 started_at=func.coalesce(Job.started_at, now()), message=f"{stage} started"))  # fmt: skip
        if not r.rowcount:  # type: ignore[attr-defined]
            return "held by another worker"
        run = StageRun(job_id=job_id, stage=stage, attempt=attempt, worker=worker)
        s.add(run)
        add_event(s, job_id, "stage", stage=stage, status="started", worker=worker, attempt=attempt)
        if stage == STAGES[0] or was_queued:
            add_event(s, job_id, "state", state="running", stage=stage, progress=job.progress)
        s.flush()
        capture = s.get(Capture, job.capture_id)
        assert capture is not None
        return Claimed(run.id, capture.storage_key, job.preset, dict(job.config or {}))


def _holds(job: Job, attempt: int, worker: str) -> bool:
    return job.state == "running" and job.attempt == attempt and job.worker == worker


def holder_problem(job_id: str, attempt: int, worker: str) -> str:
    """Why the worker should stop ("" while it still holds the job): canceled, superseded, or deleted."""
    with session_scope() as s:
        job = s.get(Job, job_id)
        if job is None:
            return "the job was deleted"
        if job.state == "canceled":
            return "canceled"
        return "" if _holds(job, attempt, worker) else "superseded"


def heartbeat(job_id: str, worker: str) -> None:
    """The holder is alive (the reaper re-queues jobs whose heartbeat is older than stale_after_s)."""
    with session_scope() as s:
        s.execute(update(Job).where(Job.id == job_id, Job.worker == worker).values(heartbeat_at=now()))


def record_progress(job_id: str, stage: str, attempt: int, worker: str, p: StageProgress) -> bool:
    """The stage's progress on the job (overall progress never decreases) and a `progress` event; False when the
    worker no longer holds the job."""
    overall = overall_progress(stage, p.fraction)
    with session_scope() as s:
        job = s.get(Job, job_id)
        if job is None or not _holds(job, attempt, worker):
            return False
        job.progress = max(job.progress, overall)
        job.stage_fraction = p.fraction
        job.message = p.message
        job.heartbeat_at = now()
        add_event(s, job_id, "progress", stage=stage, fraction=p.fraction, progress=job.progress, message=p.message,
                  metrics=p.metrics, attempt=attempt)  # fmt: skip
        return True


def _end_run(s: Session, run_id: int, status: str) -> None:
    run = s.get(StageRun, run_id)
    if run is not None:
        run.status, run.finished_at = status, now()
        run.seconds = (run.finished_at - run.started_at).total_seconds()


def stopped(job_id: str, stage: str, worker: str, run_id: int, reason: str, message: str) -> None:
    """The worker stopped the stage (`reason`: canceled, superseded, the job was deleted) and let the job go."""
    with session_scope() as s:
        _end_run(s, run_id, "canceled" if reason == "canceled" else "superseded")
        s.execute(update(Job).where(Job.id == job_id, Job.worker == worker).values(worker=None))
        add_event(s, job_id, "worker", worker=worker, stage=stage, status="stopped", reason=reason, message=message)


def fail(job_id: str, stage: str, attempt: int, worker: str, run_id: int, error: str) -> bool:
    """running -> failed with `error` in plain words (if the worker still holds the job)."""
    with session_scope() as s:
        _end_run(s, run_id, "failed")
    with session_scope() as s:
        r = s.execute(update(Job).where(Job.id == job_id, Job.attempt == attempt, Job.worker == worker,
                                        Job.state == "running")
                      .values(state="failed", error=error, worker=None, finished_at=now(),
                              message=f"{stage} failed"))  # fmt: skip
        if not r.rowcount:  # type: ignore[attr-defined]
            return False
        add_event(s, job_id, "state", state="failed", stage=stage, error=error)
        return True


def _numbers(metrics: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in metrics.items() if isinstance(v, int | float | str | bool)}


def advance(job_id: str, stage: str, attempt: int, worker: str, run_id: int, metrics: dict[str, Any],
            asset_key: str | None = None) -> str:
    """The stage finished with `metrics` (seconds under "seconds"): record it, then dispatch the next stage, or
    complete the job (the last stage's published `asset_key`). Returns what happened, for the worker's log."""
    seconds = float(metrics.get("seconds", 0.0))
    with session_scope() as s:
        _end_run(s, run_id, "finished")
    last = stage == STAGES[-1]
    nxt = None if last else STAGES[STAGES.index(stage) + 1]
    with session_scope() as s:
        job = s.get(Job, job_id)
        if job is None or not _holds(job, attempt, worker):
            return "finished, job no longer ours"
        queue = job.queue
        values: dict[str, Any] = {
            "stages_done": [*job.stages_done, stage], "metrics": {**job.metrics, stage: _numbers(metrics)},
            "timings": {**job.timings, stage: seconds}, "worker": None, "stage_fraction": 1.0,
            "progress": max(job.progress, overall_progress(stage, 1.0)), "message": f"{stage} done"}  # fmt: skip
        if nxt is None:
            values.update(state="completed", asset_key=asset_key, finished_at=now(), progress=1.0)
        else:
            values.update(stage=nxt, stage_fraction=0.0, dispatched_at=None)
        r = s.execute(update(Job).where(Job.id == job_id, Job.attempt == attempt, Job.worker == worker,
                                        Job.state == "running").values(**values))  # fmt: skip
        if not r.rowcount:  # type: ignore[attr-defined]
            return "finished, job no longer ours"
        add_event(s, job_id, "stage", stage=stage, status="finished", worker=worker, attempt=attempt, seconds=seconds,
                  progress=values["progress"])  # fmt: skip
        if nxt is None:
            add_event(s, job_id, "state", state="completed", stage=stage, progress=1.0)
    if nxt is not None:
        dispatch(job_id, nxt, attempt, queue)
    return "finished"
