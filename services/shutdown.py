"""Graceful stop of the API: on SIGTERM or SIGINT, STOPPING is set and every progress stream ends at its next poll
(within 0.2 s) with `event: shutdown`, so the server (uvicorn) finds no open response to wait for and stops at once;
clients reconnect with Last-Event-ID and miss nothing.

uvicorn installs its own handlers before the app starts; `watch_signals` (called at start-up) chains ours in front
of them, so uvicorn's shutdown still runs. Outside the main thread (a test client) it does nothing.
"""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType
from typing import Any

STOPPING = threading.Event()
MESSAGE = "the server is stopping; reconnect with the Last-Event-ID header to resume"
log = logging.getLogger("neumatex.api")


def watch_signals() -> None:
    if threading.current_thread() is not threading.main_thread():
        return
    STOPPING.clear()
    for sig in (signal.SIGTERM, signal.SIGINT):
        previous = signal.getsignal(sig)

        def handler(signum: int, frame: FrameType | None, previous: Any = previous) -> None:
            if not STOPPING.is_set():
                log.warning("signal %d: closing progress streams and stopping", signum)
            STOPPING.set()
            if callable(previous):
                previous(signum, frame)
            elif previous is not None:  # SIG_DFL or SIG_IGN: put it back and deliver the signal again
                signal.signal(signum, previous)
                signal.raise_signal(signum)

        signal.signal(sig, handler)
