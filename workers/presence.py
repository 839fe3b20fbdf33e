"""The worker's presence row (services/fleet.py): written when the worker is ready, then every heartbeat_s by a
thread of the worker's main process, removed when it stops cleanly (a killed worker's row just goes stale).

Whether the worker can run CUDA is asked through NVML (PYTORCH_NVML_BASED_CUDA_CHECK), which does not initialise
CUDA in this process, so the prefork pool's children can still use it."""

from __future__ import annotations

import logging
import os
import threading
from typing import Any

from celery.signals import worker_ready, worker_shutdown

from services import fleet
from services.core.config import get_settings
from services.core.db import session_scope
from services.models import now

log = logging.getLogger("neumatex.workers")
_state: dict[str, Any] = {}


def cuda_available() -> bool:
    os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
    try:
        import torch

        return bool(torch.cuda.is_available())
    except Exception:  # no driver, a broken install: not a CUDA worker
        return False


class Presence(threading.Thread):
    def __init__(self, name: str, queues: list[str], cuda: bool):
        super().__init__(daemon=True, name="neumatex-presence")
        self.worker, self.queues, self.cuda = name, queues, cuda
        self.stopped = threading.Event()
        self.started_at = now()

    def beat(self) -> None:
        try:
            with session_scope() as s:
                fleet.beat(s, self.worker, self.queues, self.cuda, self.started_at)
        except Exception as exc:  # a busy database: the next beat retries
            log.warning("presence of %s not written: %s", self.worker, exc)

    def run(self) -> None:
        every = get_settings().heartbeat_s
        while not self.stopped.wait(every):
            self.beat()


@worker_ready.connect
def _ready(sender: Any = None, **_: Any) -> None:
    queues = sorted(sender.app.amqp.queues.consume_from) if sender is not None else []
    thread = Presence(str(getattr(sender, "hostname", "") or f"worker@{os.getpid()}"), queues, cuda_available())
    thread.beat()
    thread.start()
    _state["thread"] = thread
    log.info("presence: %s takes %s (%s)", thread.worker, queues, "CUDA" if thread.cuda else "no CUDA")


@worker_shutdown.connect
def _shutdown(**_: Any) -> None:
    thread = _state.pop("thread", None)
    if thread is None:
        return
    thread.stopped.set()
    try:
        with session_scope() as s:
            fleet.gone(s, thread.worker)
    except Exception as exc:
        log.warning("presence of %s not removed: %s", thread.worker, exc)
