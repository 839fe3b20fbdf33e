"""The workers' Celery app: the service's producer app (services/queue.py: broker, queues, delivery settings) extended
with the task modules and the beat schedule of the reaper (services/reaper.py): `neumatex.reap` to the maintenance
queue every reaper_every_s, and with clean=True every CLEAN_EVERY_S. The beat process (`python -m services beat`) is
a worker with embedded beat that takes only that queue, so a reap never waits behind a long stage; a reap message
not started within twice its interval expires (the next one supersedes it). Beat keeps its schedule file in the
data folder.
"""

from __future__ import annotations

from celery import Celery

from services import queue
from services.core.config import get_settings
from services.reaper import CLEAN_EVERY_S


def _reap_entry(every: float, clean: bool) -> dict[str, object]:
    return {"task": queue.REAP_TASK, "schedule": every, "args": [clean],
            "options": {"queue": queue.MAINTENANCE, "expires": max(2 * every, 10.0)}}  # fmt: skip


def make_celery() -> Celery:
    """The producer app with the worker's tasks and the beat schedule."""
    st = get_settings()
    app = queue.producer()
    app.conf.update(
        include=["workers.tasks", "workers.presence"],
        beat_schedule={"reap": _reap_entry(st.reaper_every_s, False),
                       "reap-and-clean": _reap_entry(CLEAN_EVERY_S, True)},
        beat_schedule_filename=str((st.data_dir / "celerybeat-schedule").resolve()),
        beat_max_loop_interval=min(st.reaper_every_s, 5.0),
    )
    return app


celery_app = make_celery()
