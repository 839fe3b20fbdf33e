"""`python -m services serve|api|worker|create-tenant|reap` (also `make serve`).

serve: starts redis-server (from apt) when nothing answers at NEUMATEX_REDIS_URL, the API (uvicorn) and one
Celery worker on this machine with the embedded defaults (SQLite, local storage under data/service), creates a
tenant with a printed API key unless NEUMATEX_BOOTSTRAP_API_KEY is set, and prints the dashboard URL.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlparse


def redis_up(url: str) -> bool:
    import redis

    try:
        client = redis.Redis.from_url(url, socket_connect_timeout=1, socket_timeout=1)
        client.ping()
        client.close()
        return True
    except Exception:
        return False


def start_redis(url: str, folder: Path) -> subprocess.Popen[bytes] | None:
    """Start redis-server (append-only file on, so queued messages survive a restart) when none answers."""
    if redis_up(url):
        return None
    exe = shutil.which("redis-server")
    if exe is None:
        sys.exit("redis-server not found: install it (apt-get install redis-server) or point NEUMATEX_REDIS_URL at "
                 "a running Redis")
    u = urlparse(url)
    if u.hostname not in ("127.0.0.1", "localhost"):
        sys.exit(f"no Redis answers at {url} and it is not on this machine, so it cannot be started here")
    folder.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen([exe, "--port", str(u.port or 6379), "--bind", "127.0.0.1", "--dir", str(folder),
                             "--appendonly", "yes", "--save", "", "--protected-mode", "yes"],
                            stdout=subprocess.DEVNULL)  # fmt: skip
    for _ in range(100):
        if redis_up(url):
            return proc
        time.sleep(0.1)
    proc.terminate()
    sys.exit(f"redis-server did not start on {url}")


def worker_command(queue: str, concurrency: int, name: str) -> list[str]:
    return [sys.executable, "-m", "celery", "-A", "workers.celery_app:celery_app", "worker", "-Q", queue,
            "--concurrency", str(concurrency), "--prefetch-multiplier", "1", "-n", name, "--loglevel", "INFO",
            "--without-gossip", "--without-mingle"]  # fmt: skip


def api_command(host: str, port: int) -> list[str]:
    return [sys.executable, "-m", "uvicorn", "services.main:app", "--host", host, "--port", str(port),
            "--log-level", "warning"]  # fmt: skip


def serve(args: argparse.Namespace) -> int:
    from services.core.config import get_settings
    from services.core.db import get_engine, session_scope
    from services.core.security import new_api_key
    from services.crud import ensure_tenant

    st = get_settings()
    st.data_dir.mkdir(parents=True, exist_ok=True)
    procs: list[subprocess.Popen[bytes]] = []
    redis_proc = start_redis(st.redis_url, st.data_dir / "redis")
    if redis_proc is not None:
        procs.append(redis_proc)
    get_engine()
    key = st.bootstrap_api_key or os.environ.get("NEUMATEX_API_KEY") or ""
    key_file = st.data_dir / "api-key.txt"
    if not key and key_file.is_file():
        key = key_file.read_text().strip()
    if not key:
        key = new_api_key()
        key_file.write_text(key + "\n")
        key_file.chmod(0o600)
    with session_scope() as s:
        ensure_tenant(s, st.bootstrap_tenant or "local", key)
    env = dict(os.environ)
    procs.append(subprocess.Popen(api_command(args.host, args.port), env=env))
    procs.append(subprocess.Popen(worker_command("cpu,gpu" if args.gpu else "cpu", 1, "cpu@%h"), env=env))
    print(f"NeuMatEx service: dashboard http://{args.host}:{args.port}/  (API docs /docs)")
    print(f"API key (tenant '{st.bootstrap_tenant or 'local'}'): {key}   [saved in {key_file}]")
    print("Ctrl-C stops the API, the worker" + (" and redis-server" if redis_proc else ""))
    stop = False

    def _stop(*_: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGINT, _stop)
    signal.signal(signal.SIGTERM, _stop)
    while not stop and all(p.poll() is None for p in procs):
        time.sleep(0.5)
    for p in reversed(procs):
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m services", description="NeuMatEx job service")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("serve", help="Redis (if needed), the API and one worker; prints the dashboard URL")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--gpu", action="store_true", help="the worker also takes the gpu queue")
    p = sub.add_parser("api", help="only the API")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p = sub.add_parser("worker", help="only a worker")
    p.add_argument("--queue", default="cpu", help="cpu, gpu or cpu,gpu")
    p.add_argument("--name", default="worker@%h")
    p = sub.add_parser("create-tenant", help="create a tenant and print its API key")
    p.add_argument("name")
    sub.add_parser("reap", help="one reaper pass (re-queue jobs of vanished workers)")
    args = ap.parse_args(argv)
    if args.cmd == "serve":
        return serve(args)
    if args.cmd == "api":
        os.execv(sys.executable, api_command(args.host, args.port))
    if args.cmd == "worker":
        os.execv(sys.executable, worker_command(args.queue, 1, args.name))
    if args.cmd == "create-tenant":
        from services.core.db import session_scope
        from services.crud import create_tenant

        with session_scope() as s:
            tenant, key = create_tenant(s, args.name)
            print(f"tenant {tenant.id} ({args.name}); API key (shown once): {key}")
        return 0
    if args.cmd == "reap":
        from services.reaper import reap_once

        print("re-queued:", reap_once())
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
