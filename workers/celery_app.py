"""The Celery app (Redis broker) and `dispatch`, which sends one stage of one job to its queue ("cpu" or "gpu").

Delivery: acks_late + reject_on_worker_lost (a message is removed only after its stage ran), prefetch 1 (a worker
holds one stage at a time), and a visibility timeout above the longest stage time limit (Redis re-delivers an
unacknowledged message only after it). Results are not stored in Celery: the job row is the record.
"""

from __future__ import annotations

import logging

from celery import Celery
from kombu import Queue

from services.core.config import get_settings

TASK = "neumatex.stage"
QUEUES = ("cpu", "gpu")
log = logging.getLogger("neumatex.workers")


def make_celery() -> Celery:
    st = get_settings()
    app = Celery("neumatex", broker=st.redis_url, include=["workers.tasks", "workers.presence"])
    app.conf.update(
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        task_queues=[Queue(q) for q in QUEUES],
        task_default_queue="cpu",
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,
        broker_transport_options={"visibility_timeout": st.visibility_timeout_s, "socket_timeout": 5,
                                  "socket_connect_timeout": 3},  # fmt: skip
        worker_cancel_long_running_tasks_on_connection_loss=False,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
    )
    return app


celery_app = make_celery()


def dispatch(job_id: str, stage: str, attempt: int, queue: str) -> bool:
    """Send the stage; False (logged) when the broker cannot be reached (the reaper sends it again later)."""
    st = get_settings()
    limit = st.time_limit(stage)
    try:
        celery_app.send_task(TASK, args=[job_id, stage, attempt], queue=queue, soft_time_limit=limit,
                             time_limit=limit + 30, retry=True,
                             retry_policy={"max_retries": 3, "interval_start": 0.2, "interval_step": 0.5,
                                           "interval_max": 1.0})  # fmt: skip
        return True
    except Exception as exc:  # broker down: the job row stays undispatched and the reaper retries
        log.warning("could not send %s/%s to the broker: %s", job_id, stage, exc)
        return False
