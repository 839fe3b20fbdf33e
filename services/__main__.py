"""`python -m services serve|api|worker|beat|create-tenant|set-limits|reap` (also `make serve`).

serve: starts redis-server (from apt) when nothing answers at NEUMATEX_REDIS_URL, nginx in front of the API when
it is installed (services/proxy.py; --no-proxy: the API alone), the API (uvicorn), one Celery worker and Celery
beat (which sends the reaper's task, services/reaper.py) on this machine with the embedded defaults (SQLite, local
storage under data/service), creates a tenant with a printed API key unless NEUMATEX_BOOTSTRAP_API_KEY is set, and
prints the dashboard URL. It supervises them (services/supervisor.py): a child that dies is restarted, and one that
keeps dying stops everything with the reason printed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

from services.supervisor import Child, Supervisor

if TYPE_CHECKING:
    from services.proxy import ProxyConfig


def redis_up(url: str) -> bool:
    import redis

    try:
        client = redis.Redis.from_url(url, socket_connect_timeout=1, socket_timeout=1)
        client.ping()
        client.close()
        return True
    except Exception:
        return False


def redis_child(url: str, folder: Path) -> Child | None:
    """redis-server to start (append-only file on, so queued messages survive a restart) when none answers."""
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
    return Child("redis-server", [exe, "--port", str(u.port or 6379), "--bind", "127.0.0.1", "--dir", str(folder),
                                  "--appendonly", "yes", "--save", "", "--protected-mode", "yes", "--loglevel",
                                  "warning"], dict(os.environ), ready=lambda: redis_up(url))  # fmt: skip


def worker_command(queue: str, concurrency: int, name: str) -> list[str]:
    return [sys.executable, "-m", "celery", "-A", "workers.celery_app:celery_app", "worker", "-Q", queue,
            "--concurrency", str(concurrency), "--prefetch-multiplier", "1", "-n", name, "--loglevel", "INFO",
            "--without-gossip", "--without-mingle"]  # fmt: skip


def beat_command(data_dir: Path) -> list[str]:
    """Celery beat sending the reaper's task (workers/celery_app.py), embedded in a one-process worker that takes
    only the maintenance queue, so it also runs the reaps; its schedule file goes in `data_dir` (the service's data
    folder, created here). Run exactly one per deployment."""
    from services.queue import MAINTENANCE

    data_dir.mkdir(parents=True, exist_ok=True)
    return [sys.executable, "-m", "celery", "-A", "workers.celery_app:celery_app", "worker", "--beat", "-Q",
            MAINTENANCE, "--concurrency", "1", "--pool", "solo", "-n", "beat@%h", "--loglevel", "WARNING",
            "--without-gossip", "--without-mingle", "--schedule-filename",
            str((data_dir / "celerybeat-schedule").resolve())]  # fmt: skip


def api_command(host: str, port: int) -> list[str]:
    """uvicorn serving the API: uvloop (uvicorn[standard]) for the event loop, but h11 as the HTTP parser, because
    httptools answers a header with non-ASCII bytes (e.g. a mistyped API key) with a bare 400 before the app can
    say what is wrong (a 401 naming the key). h11 is told how long a request's head may grow (`max_header_bytes`)."""
    from services.core.config import get_settings

    settings = get_settings()
    return [sys.executable, "-m", "uvicorn", "services.main:app", "--host", host, "--port", str(port), "--http", "h11",
            "--h11-max-incomplete-event-size", str(settings.max_header_bytes), "--log-level", "warning",
            "--timeout-graceful-shutdown", f"{settings.shutdown_grace_s:g}"]


def proxy_config(host: str, port: int, data_dir: Path, max_upload_bytes: int) -> ProxyConfig | None:
    """nginx in front of the API on `host:port` (services/proxy.py), or None when nginx is not installed."""
    from services.proxy import ProxyConfig, free_port, nginx_path

    if nginx_path() is None:
        return None
    return ProxyConfig(data_dir / "proxy", port, free_port(), max_upload_bytes, host=host)


def serve(args: argparse.Namespace) -> int:
    from services.core.config import get_settings
    from services.core.db import get_engine, session_scope
    from services.core.security import new_api_key
    from services.crud import ensure_tenant

    st = get_settings()
    st.data_dir.mkdir(parents=True, exist_ok=True)
    sup = Supervisor(max_restarts=args.max_restarts)
    redis = redis_child(st.redis_url, st.data_dir / "redis")
    if redis is not None:
        sup.add(redis)
        if not redis_up(st.redis_url):
            sup.stop_all()
            sys.exit(f"redis-server did not start on {st.redis_url}")
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
    api_host, api_port = args.host, args.port
    proxy = None if args.no_proxy else proxy_config(args.host, args.port, st.data_dir, st.max_upload_bytes)
    if proxy is not None:  # nginx takes the port and receives uploads; the API listens on this machine only
        api_host, api_port = "127.0.0.1", proxy.api_port
        env.update(proxy.api_env())
        proxy.write()
        sup.add(Child("nginx", proxy.command(), env))
    sup.add(Child("api", api_command(api_host, api_port), env))
    sup.add(Child("worker", worker_command("cpu,gpu" if args.gpu else "cpu", 1, "cpu@%h"), env))
    sup.add(Child("beat", beat_command(st.data_dir), env))
    print(f"NeuMatEx service: dashboard http://{args.host}:{args.port}/  (API docs /docs)")
    print(f"API key (tenant '{st.bootstrap_tenant or 'local'}'): {key}   [saved in {key_file}]")
    print("uploads are received by nginx (deploy/nginx/)" if proxy is not None else
          "nginx not found (make sysdeps installs it) or --no-proxy: uploads go through the API, several times slower")
    print("Ctrl-C stops the API, the worker, beat" + (", nginx" if proxy else "") + (" and redis-server" if redis
          else "") + "; a child that dies is restarted", flush=True)
    return sup.run()


def set_limits(name: str, storage_bytes: int | None, active_jobs: int | None) -> int:
    from sqlalchemy import select

    from services.core.db import session_scope
    from services.models import Tenant, TenantLimits
    from services.quota import limits

    with session_scope() as s:
        tenant = s.scalar(select(Tenant).where(Tenant.name == name))
        if tenant is None:
            print(f"error: no tenant named {name!r}", file=sys.stderr)
            return 2
        row = s.get(TenantLimits, tenant.id) or TenantLimits(tenant_id=tenant.id)
        if storage_bytes is not None:
            row.storage_bytes = None if storage_bytes < 0 else storage_bytes
        if active_jobs is not None:
            row.active_jobs = None if active_jobs < 0 else active_jobs
        s.add(row)
        s.flush()
        lim = limits(s, tenant.id)
        print(f"tenant {name}: storage {lim.storage_bytes or 'no limit'} bytes, active jobs "
              f"{lim.active_jobs or 'no limit'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m services", description="NeuMatEx job service")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("serve", help="Redis (if needed), the API, one worker and beat; prints the dashboard URL")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--gpu", action="store_true", help="the worker also takes the gpu queue")
    p.add_argument("--no-proxy", action="store_true",
                   help="no nginx in front: the API takes the port and receives uploads itself")
    p.add_argument("--max-restarts", type=int, default=5,
                   help="a child that dies more often than this within 60 s stops everything")
    p = sub.add_parser("api", help="only the API")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p = sub.add_parser("worker", help="only a worker")
    p.add_argument("--queue", default="cpu", help="cpu, gpu or cpu,gpu")
    p.add_argument("--name", default="worker@%h")
    sub.add_parser("beat", help="only Celery beat: sends the reaper's task every reaper_every_s (run one per "
                   "deployment; a second one is harmless)")
    p = sub.add_parser("create-tenant", help="create a tenant and print its API key")
    p.add_argument("name")
    p = sub.add_parser("set-limits", help="set a tenant's storage quota and active-job limit (overrides the "
                       "settings; -1: back to the setting, 0: no limit)")
    p.add_argument("name", help="the tenant's name")
    p.add_argument("--storage-bytes", type=int, default=None)
    p.add_argument("--active-jobs", type=int, default=None)
    sub.add_parser("migrate", help="bring the database (NEUMATEX_DATABASE_URL) to the newest schema migration; "
                   "every process also does this at start")
    sub.add_parser("reap", help="one reaper pass (re-queue jobs of vanished workers, apply the retention)")
    args = ap.parse_args(argv)
    if args.cmd == "serve":
        return serve(args)
    if args.cmd == "api":
        os.execv(sys.executable, api_command(args.host, args.port))
    if args.cmd == "worker":
        os.execv(sys.executable, worker_command(args.queue, 1, args.name))
    if args.cmd == "beat":
        from services.core.config import get_settings

        os.execv(sys.executable, beat_command(get_settings().data_dir))
    if args.cmd == "create-tenant":
        from services.core.db import session_scope
        from services.crud import create_tenant

        with session_scope() as s:
            tenant, key = create_tenant(s, args.name)
            print(f"tenant {tenant.id} ({args.name}); API key (shown once): {key}")
        return 0
    if args.cmd == "set-limits":
        return set_limits(args.name, args.storage_bytes, args.active_jobs)
    if args.cmd == "migrate":
        import logging

        from services.core.db import migrate

        logging.basicConfig(level=logging.INFO, format="%(message)s")  # alembic's "Running upgrade ..." lines
        print("database at revision", migrate())
        return 0
    if args.cmd == "reap":
        from services.reaper import reap_pass

        out = reap_pass(clean=True)
        print("re-queued:", out["sent"])
        print("staging folders removed:", out["staging_removed"])
        print("work folders removed (retention):", out["work_removed"])
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
