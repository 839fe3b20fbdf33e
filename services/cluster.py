"""A whole service on this machine as subprocesses: redis-server on a free port (append-only file on, so it can be
stopped and started again without losing messages), the API under uvicorn, Celery workers and Celery beat (the
reaper's schedule: `start_beat`, needed wherever a job must be re-queued after its worker died), sharing one data
folder (SQLite + local storage), optionally behind the reverse proxy (nginx, services/proxy.py: `proxy=True`, then
`url` is the proxy's and `api_url` the API's own). Used by tests/service and bench/service.py; each process runs in
its own session, so `kill9()` reaches a worker's pool children too.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from services.proxy import ProxyConfig, free_port

REPO = Path(__file__).resolve().parents[1]

FAST = {"NEUMATEX_HEARTBEAT_S": "0.5", "NEUMATEX_STALE_AFTER_S": "4", "NEUMATEX_REAPER_EVERY_S": "1",
        "NEUMATEX_REDISPATCH_AFTER_S": "3", "NEUMATEX_PROGRESS_EVERY_S": "0.1",
        "NEUMATEX_PARTIAL_STORE_EVERY_S": "1"}  # fmt: skip


def wait_for(check: Callable[[], Any], timeout: float, what: str, every: float = 0.1) -> Any:
    """Poll `check` until it returns something true; AssertionError naming `what` after `timeout` seconds."""
    end = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < end:
        try:
            last = check()
            if last:
                return last
        except OSError:
            pass
        except Exception as exc:  # httpx errors while a process starts
            last = exc
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what} (last: {last!r})")


class Redis:
    def __init__(self, folder: Path):
        self.folder, self.port = folder, free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen[bytes] | None = None
        folder.mkdir(parents=True, exist_ok=True)

    def ping(self) -> bool:
        import redis

        try:
            return bool(redis.Redis(port=self.port, socket_timeout=0.5, socket_connect_timeout=0.5).ping())
        except redis.RedisError:
            return False

    def start(self) -> None:
        exe = shutil.which("redis-server")
        if exe is None:
            raise RuntimeError("redis-server not found: `make test` installs it (apt-get install redis-server)")
        self.proc = subprocess.Popen([exe, "--port", str(self.port), "--bind", "127.0.0.1", "--dir",
                                      str(self.folder), "--appendonly", "yes", "--appendfsync", "always",
                                      "--save", ""], stdout=subprocess.DEVNULL)  # fmt: skip
        wait_for(self.ping, 20, "redis-server")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(20)
            self.proc = None


class Proc:
    """A subprocess in its own session with its output appended to a log file."""

    def __init__(self, cmd: list[str], env: dict[str, str], log: Path):
        self.cmd, self.env, self.log = cmd, env, log
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> Proc:
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(self.cmd, env=self.env, cwd=REPO, stdout=out, stderr=subprocess.STDOUT,
                                         start_new_session=True)  # fmt: skip
        return self

    def kill9(self) -> None:
        """SIGKILL to the process and every process of its session (a Celery worker and its pool children)."""
        assert self.proc is not None
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(10)

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """SIGSTOP to the process's session for the block, SIGCONT after: what the block does happens between two of
        the process's steps, however fast it runs them (keep the block short: its heartbeat stops too)."""
        assert self.proc is not None
        os.killpg(self.proc.pid, signal.SIGSTOP)
        try:
            yield
        finally:
            os.killpg(self.proc.pid, signal.SIGCONT)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)

    def tail(self, n: int = 4000) -> str:
        return self.log.read_text(errors="replace")[-n:] if self.log.exists() else ""


class Cluster:
    """Redis, the API and workers sharing one environment (data folder, database, broker)."""

    def __init__(self, root: Path, env: dict[str, str] | None = None, proxy: bool = False):
        self.root = root
        self.redis = Redis(root / "redis")
        self.port = free_port()
        self.api_url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "NEUMATEX_DATA_DIR": str(root / "data"), "NEUMATEX_REDIS_URL": self.redis.url,
                    "NEUMATEX_TORCH_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1",
                    **(env or {})}  # fmt: skip
        self.proxy_config: ProxyConfig | None = None
        if proxy:
            limit = int(self.env.get("NEUMATEX_MAX_UPLOAD_BYTES", 2 * 1024**3))
            self.proxy_config = ProxyConfig(root / "proxy", free_port(), self.port, limit, workers=1)
            self.env.update(self.proxy_config.api_env())
        self.url = f"http://127.0.0.1:{self.proxy_config.port}" if self.proxy_config else self.api_url
        self.proxy: Proc | None = None
        self.api: Proc | None = None
        self.beat: Proc | None = None
        self.workers: list[Proc] = []
        self._n = 0

    @property
    def storage(self) -> Path:
        return self.root / "data" / "storage"

    def add_tenant(self, name: str, key: str) -> None:
        code = ("from services.core.db import session_scope\nfrom services.crud import ensure_tenant\n"
                f"with session_scope() as s: ensure_tenant(s, {name!r}, {key!r})")  # fmt: skip
        subprocess.run([sys.executable, "-c", code], env=self.env, cwd=REPO, check=True)

    def start_api(self, timeout: float = 120) -> None:
        import httpx

        from services.__main__ import api_command

        self.api = Proc(api_command("127.0.0.1", self.port), self.env, self.root / "api.log").start()
        wait_for(lambda: httpx.get(self.api_url + "/healthz", timeout=2).status_code == 200, timeout, "the API")
        if self.proxy_config is not None and (self.proxy is None or self.proxy.proc is None
                                              or self.proxy.proc.poll() is not None):  # fmt: skip
            self.proxy_config.write()
            self.proxy = Proc(self.proxy_config.command(), self.env, self.root / "proxy.log").start()
            wait_for(lambda: httpx.get(self.url + "/healthz", timeout=2).status_code == 200, timeout, "the proxy")

    def restart_api(self) -> None:
        assert self.api is not None
        self.api.stop()
        self.start_api()

    def start_worker(self, queue: str = "cpu", env: dict[str, str] | None = None) -> Proc:
        """A Celery worker (one pool process) on `queue`; `env` adds to or overrides the cluster's environment for
        this worker alone (e.g. its own data and scratch folders)."""
        self._n += 1
        cmd = [sys.executable, "-m", "celery", "-A", "workers.celery_app:celery_app", "worker", "-Q", queue,
               "--concurrency", "1", "--prefetch-multiplier", "1", "-n", f"w{self._n}@%h", "--loglevel", "INFO",
               "--without-gossip", "--without-mingle", "--without-heartbeat"]  # fmt: skip
        w = Proc(cmd, {**self.env, **(env or {})}, self.root / f"worker{self._n}.log").start()
        self.workers.append(w)
        return w

    def start_beat(self) -> Proc:
        """Celery beat (once; later calls return the running one): sends the reaper's task to the maintenance queue
        every reaper_every_s and runs it (a worker with embedded beat taking only that queue)."""
        if self.beat is None or self.beat.proc is None or self.beat.proc.poll() is not None:
            from services.__main__ import beat_command

            cmd = beat_command(Path(self.env["NEUMATEX_DATA_DIR"]))
            self.beat = Proc(cmd, self.env, self.root / "beat.log").start()
        return self.beat

    def stop(self) -> None:
        if self.beat is not None:
            self.beat.stop()
        for w in self.workers:
            w.stop()
        if self.proxy is not None:
            self.proxy.stop()
        if self.api is not None:
            self.api.stop()
        self.redis.stop()
