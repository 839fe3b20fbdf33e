"""The children of `python -m services serve` (redis-server when it started one, the API, the worker, beat) under
supervision: a child that dies is started again (after the rest of its process group, e.g. a worker's pool
processes, is killed), with a pause that grows with each restart; a child that died more than `max_restarts`
times within `window_s` stops everything, and the reason is printed. SIGTERM or SIGINT to the supervisor stops
the children in reverse order (SIGTERM to each process group, SIGKILL after `grace_s`).

Each child runs in its own session, so a Ctrl-C in the terminal reaches only the supervisor, which stops the
children in order instead of them racing each other down.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

Say = Callable[[str], None]


def _say(text: str) -> None:
    print(f"serve: {text}", flush=True)


def exit_reason(code: int) -> str:
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with status {code}"


@dataclass
class Child:
    name: str
    command: list[str]
    env: dict[str, str]
    ready: Callable[[], bool] | None = None  # waited for after each start (e.g. redis answers)
    proc: subprocess.Popen[bytes] | None = None
    deaths: deque[float] = field(default_factory=deque)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None


class Supervisor:
    def __init__(self, max_restarts: int = 5, window_s: float = 60.0, grace_s: float = 20.0, say: Say = _say):
        self.children: list[Child] = []
        self.max_restarts, self.window_s, self.grace_s, self.say = max_restarts, window_s, grace_s, say
        self.stopping = False

    def start(self, child: Child) -> None:
        child.proc = subprocess.Popen(child.command, env=child.env, start_new_session=True)
        if child.ready is not None:
            end = time.monotonic() + 30
            while not child.ready():
                if child.proc.poll() is not None or time.monotonic() > end:
                    break
                time.sleep(0.1)
        self.say(f"{child.name} started (pid {child.proc.pid})")

    def add(self, child: Child) -> Child:
        self.children.append(child)
        self.start(child)
        return child

    def check(self) -> str:
        """Restart the children that died; the reason to stop everything, or ""."""
        for child in self.children:
            assert child.proc is not None
            code = child.proc.poll()
            if code is None or self.stopping:
                continue
            _kill_group(child.proc.pid, signal.SIGKILL)  # what it leaves behind (a worker's pool processes)
            t = time.monotonic()
            child.deaths.append(t)
            while child.deaths and t - child.deaths[0] > self.window_s:
                child.deaths.popleft()
            if len(child.deaths) > self.max_restarts:
                return (f"{child.name} (pid {child.proc.pid}) {exit_reason(code)}; it died {len(child.deaths)} times "
                        f"in {self.window_s:.0f} s, so everything stops (see its output above)")
            pause = min(0.5 * 2 ** (len(child.deaths) - 1), 8.0)
            self.say(f"{child.name} (pid {child.proc.pid}) {exit_reason(code)}; restarting it in {pause:.1f} s "
                     f"(restart {len(child.deaths)} of at most {self.max_restarts} in {self.window_s:.0f} s)")
            time.sleep(pause)
            self.start(child)
        return ""

    def run(self, every: float = 0.5) -> int:
        """Supervise until SIGTERM/SIGINT (0) or a child dies too often (1); the children are stopped either way."""
        def _stop(*_: object) -> None:
            self.stopping = True

        signal.signal(signal.SIGINT, _stop)
        signal.signal(signal.SIGTERM, _stop)
        reason = ""
        while not self.stopping and not reason:
            reason = self.check()
            time.sleep(every)
        if reason:
            self.say(reason)
        self.stop_all()
        return 1 if reason else 0

    def stop_all(self) -> None:
        self.stopping = True
        for child in reversed(self.children):
            proc = child.proc
            if proc is None:
                continue
            if proc.poll() is None:
                _kill_group(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(self.grace_s)
                except subprocess.TimeoutExpired:
                    self.say(f"{child.name} did not stop within {self.grace_s:.0f} s; killing it")
            _kill_group(proc.pid, signal.SIGKILL)
            proc.wait(10)
        self.say("stopped")


def _kill_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass
