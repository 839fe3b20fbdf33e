"""The live workers: each Celery worker writes its presence row (queues, CUDA) every heartbeat_s
(workers/presence.py); a worker is live while its row was written within `live_within_s`. Job creation asks
`device_problem` (422 when no live worker on the job's queue can run CUDA) and `queue_waiting` (the job is
accepted but flagged: it waits for a worker of its queue)."""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from services.core.config import get_settings
from services.models import WorkerNode, now


def beat(s: Session, name: str, queues: list[str], cuda: bool, started_at: datetime) -> None:
    """Insert or refresh the worker's row (`started_at`: when this worker process started)."""
    row = s.get(WorkerNode, name)
    if row is None:
        s.add(WorkerNode(name=name, queues=sorted(queues), cuda=cuda, started_at=started_at, seen_at=now()))
    else:
        row.queues, row.cuda, row.started_at, row.seen_at = sorted(queues), cuda, started_at, now()


def gone(s: Session, name: str) -> None:
    """The worker stopped cleanly."""
    s.execute(delete(WorkerNode).where(WorkerNode.name == name))


def live(s: Session) -> list[WorkerNode]:
    cutoff = now() - timedelta(seconds=get_settings().live_within_s)
    return list(s.scalars(select(WorkerNode).where(WorkerNode.seen_at >= cutoff).order_by(WorkerNode.name)))


def describe(workers: list[WorkerNode]) -> str:
    if not workers:
        return "no worker is live"
    return "live workers: " + "; ".join(f"{w.name} (queues {', '.join(w.queues)}, "
                                        f"{'CUDA' if w.cuda else 'no CUDA'})" for w in workers)  # fmt: skip


def device_problem(s: Session, device: str, queue: str) -> str:
    """Why a job with this device on this queue cannot run now ("" when it can). Only `cuda` is checked: "auto"
    and "cpu" run on any worker."""
    if device != "cuda":
        return ""
    workers = live(s)
    if any(w.cuda and queue in w.queues for w in workers):
        return ""
    return (f"device 'cuda' needs a live worker with CUDA on the {queue!r} queue and there is none "
            f"({describe(workers)}); use device 'auto' or 'cpu', or start a GPU worker "
            "(python -m services worker --queue gpu)")


def queue_waiting(s: Session, queue: str) -> str:
    """A note for a queued job when no live worker takes its queue ("" when one does)."""
    workers = live(s)
    if any(queue in w.queues for w in workers):
        return ""
    return (f"waiting: no live worker takes the {queue!r} queue ({describe(workers)}); the job starts when one "
            "does")


def summary(s: Session) -> dict[str, int]:
    """Live workers per queue (and 'cuda': how many can run CUDA), for /readyz."""
    out: dict[str, int] = {"cuda": 0}
    for w in live(s):
        for q in w.queues:
            out[q] = out.get(q, 0) + 1
        out["cuda"] += int(w.cuda)
    return out
