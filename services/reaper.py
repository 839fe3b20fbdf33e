"""The reaper: re-queues running jobs whose worker stopped sending heartbeats (killed, machine gone), resuming
from the first unfinished stage with a new attempt, and sends again the jobs whose next message never reached the
broker or was taken by a worker that never claimed the job (services/lifecycle.py does all three). With `clean`
it also removes upload sessions and staging folders older than upload_ttl_s, and finished jobs' work folders older
than work_retention_s (services/cleanup.py).

It runs on Celery beat: `python -m services beat` (also started by `python -m services serve`) sends the
`neumatex.reap` task (workers/tasks.py) to the maintenance queue, which only the beat process takes, every
reaper_every_s, and with clean=True every
CLEAN_EVERY_S; `python -m services reap` runs one pass by hand. Several beats or reapers at once are harmless:
each change is a conditional UPDATE, so one wins.
"""

from __future__ import annotations

import logging
import time
from datetime import timedelta

from sqlalchemy import delete, select

from services import lifecycle
from services.core.config import get_settings
from services.core.db import session_scope
from services.models import Upload, now

log = logging.getLogger("neumatex.reaper")
CLEAN_EVERY_S = 60.0  # the cleanup passes (staging, retention) run this often


def reap_once() -> list[str]:
    """One pass; returns the ids of the jobs sent again (re-queued, or whose message had not reached the broker)."""
    return lifecycle.requeue_stale() + lifecycle.redispatch_lost() + lifecycle.redispatch_unclaimed()


def clean_staging() -> int:
    """Remove upload sessions older than upload_ttl_s and staging folders no session owns (a request that died
    mid-upload) once they are that old; returns how many folders were removed."""
    from services.storage import get_storage

    st = get_settings()
    cutoff = now() - timedelta(seconds=st.upload_ttl_s)
    with session_scope() as s:
        s.execute(delete(Upload).where(Upload.created_at < cutoff))
        live = set(s.scalars(select(Upload.id)))
    storage = get_storage()
    removed = 0
    for name, mtime in storage.ages("staging").items():  # local: the folders' mtimes; S3: each one's newest object
        if name not in live and time.time() - mtime > st.upload_ttl_s:
            storage.delete(f"staging/{name}")
            removed += 1
    return removed


def reap_pass(clean: bool = False) -> dict[str, object]:
    """What the `neumatex.reap` task runs: `reap_once`, and with `clean` the cleanup passes."""
    out: dict[str, object] = {"sent": reap_once()}
    if clean:
        from services.cleanup import clean_work

        out["staging_removed"] = clean_staging()
        out["work_removed"] = clean_work()
    return out
