"""The Celery app as a producer: broker (Redis), queues, task names and delivery settings, written once here so the
API, the reaper and the workers send the same messages. The workers (workers/celery_app.py) take this same app
and extend it with their task modules and the beat schedule; nothing here imports `workers` (the allowed
direction is workers -> services, checked by tests/test_service_layering.py).

Delivery: acks_late + reject_on_worker_lost (a message is removed only after its stage ran), prefetch 1 (a worker
holds one stage at a time), and a visibility timeout above the longest stage time limit (Redis re-delivers an
unacknowledged message only after it). Results are not stored in Celery: the job row is the record.
"""

from __future__ import annotations

import logging
from functools import lru_cache
from typing import Any

from celery import Celery
from kombu import Queue

from services.core.config import get_settings

STAGE_TASK = "neumatex.stage"  # args: [job_id, stage, attempt]
REAP_TASK = "neumatex.reap"  # args: [clean: bool] (services/reaper.py reap_pass)
CPU, GPU = "cpu", "gpu"
QUEUES = (CPU, GPU)  # the queues jobs run on
# The reaper's queue, taken only by the beat process (`python -m services beat`: a worker with embedded beat), so
# reaping never waits behind a long stage on a busy cpu worker.
MAINTENANCE = "maintenance"
log = logging.getLogger("neumatex.queue")

_RETRY = {"max_retries": 3, "interval_start": 0.2, "interval_step": 0.5, "interval_max": 1.0}  # ~2 s at most


def configure(app: Celery) -> Celery:
    """Apply the service's broker and delivery settings to `app` (returned)."""
    st = get_settings()
    app.conf.update(
        broker_url=st.redis_url,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        task_queues=[Queue(q) for q in (*QUEUES, MAINTENANCE)],
        task_default_queue=CPU,
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,
        broker_transport_options={"visibility_timeout": st.visibility_timeout_s, "socket_timeout": 5,
                                  "socket_connect_timeout": 3},  # fmt: skip
        worker_cancel_long_running_tasks_on_connection_loss=False,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
    )
    return app


@lru_cache
def producer() -> Celery:
    """This process's Celery app (one per process; the workers extend this same object)."""
    return configure(Celery("neumatex"))


def send_stage(job_id: str, stage: str, attempt: int, queue: str) -> bool:
    """Send one stage message to `queue`, with the stage's soft time limit (the hard one 30 s later); False (logged)
    when the broker cannot be reached (the job stays undispatched and the reaper sends it again later)."""
    limit = get_settings().time_limit(stage)
    options: dict[str, Any] = {"queue": queue, "soft_time_limit": limit, "time_limit": limit + 30}
    try:
        producer().send_task(STAGE_TASK, args=[job_id, stage, attempt], retry=True, retry_policy=_RETRY, **options)
        return True
    except Exception as exc:  # broker down: the job row stays undispatched and the reaper retries
        log.warning("could not send %s/%s to the broker: %s", job_id, stage, exc)
        return False


def waiting(queue: str) -> int | None:
    """How many messages wait in `queue` on the broker, not yet taken by a worker (a message a worker has taken
    but not acknowledged is not counted); None (logged) when the broker cannot be reached."""
    try:
        with producer().connection_for_write() as conn:
            conn.ensure_connection(max_retries=1)  # the app retries forever by default; the reaper must not hang
            return int(conn.default_channel.queue_declare(queue=queue).message_count)
    except Exception as exc:
        log.warning("could not count the messages of queue %s: %s", queue, exc)
        return None
