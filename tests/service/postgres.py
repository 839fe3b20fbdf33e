"""A real PostgreSQL server for the tests, started from Debian's server binaries (apt package `postgresql`, at
/usr/lib/postgresql/<version>/bin; `make sysdeps` installs it) in a temporary folder: initdb, then `postgres` on a
free port with its unix socket in that folder, fsync off (the data is thrown away), trust authentication.

initdb and postgres refuse to run as root, so under root (CI) the server runs as the unprivileged `postgres` system
user that the Debian package creates, and its folder belongs to that user; as a normal user it runs as that user.
"""

from __future__ import annotations

import ctypes
import os
import pwd
import re
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from services.cluster import free_port

SUPERUSER = "neumatex"  # the cluster's superuser, made by initdb (trust authentication: no password)


def server_bindir() -> Path:
    """The folder of initdb and postgres: $NEUMATEX_PG_BINDIR, else the newest /usr/lib/postgresql/*/bin."""
    given = os.environ.get("NEUMATEX_PG_BINDIR")
    candidates = [Path(given)] if given else sorted(Path("/usr/lib/postgresql").glob("*/bin"),
                                                    key=lambda p: int(re.sub(r"\D", "", p.parent.name) or 0))
    for folder in reversed(candidates):
        if (folder / "initdb").is_file() and (folder / "postgres").is_file():
            return folder
    raise RuntimeError("PostgreSQL server binaries (initdb, postgres) not found under /usr/lib/postgresql/*/bin: "
                       "`make sysdeps` installs postgresql (apt-get install postgresql), or set NEUMATEX_PG_BINDIR")


def _die_with_parent() -> None:
    """In the server's process before exec (after its user is set, which would clear it): SIGQUIT, an immediate
    shutdown, when the test process that started it dies without stopping it (killed, or a timeout)."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGQUIT)  # 1: PR_SET_PDEATHSIG


class Postgres:
    """One throwaway PostgreSQL server. `start()`, then `create_database(name)` for a URL, `stop()` at the end."""

    def __init__(self) -> None:
        self.bindir = server_bindir()
        self.port = free_port()
        self.proc: subprocess.Popen[bytes] | None = None
        # As root the server runs as `postgres`: it must own its folder, and reach it, so the folder is made in the
        # system's temporary folder (sticky, world-traversable), not under pytest's private (0700) one.
        self.as_user: dict[str, Any] = {}
        if os.geteuid() == 0:
            try:
                pw = pwd.getpwnam("postgres")
            except KeyError:
                raise RuntimeError("running as root, PostgreSQL needs an unprivileged user to run as and there is no "
                                   "`postgres` user: `make sysdeps` installs postgresql, which creates it") from None
            self.as_user = {"user": pw.pw_uid, "group": pw.pw_gid, "extra_groups": []}
        self.folder = Path(tempfile.mkdtemp(prefix="neumatex-pg-"))  # short: a unix socket path is <= 107 bytes
        if self.as_user:
            os.chown(self.folder, self.as_user["user"], self.as_user["group"])
        self.data = self.folder / "data"
        self.log = self.folder / "postgres.log"

    def _run(self, *cmd: str) -> None:
        r = subprocess.run(cmd, cwd=self.folder, capture_output=True, text=True, **self.as_user)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")

    def start(self, timeout: float = 60) -> Postgres:
        self._run(str(self.bindir / "initdb"), "-D", str(self.data), "-U", SUPERUSER, "--auth=trust", "-E", "UTF8",
                  "--locale=C", "--no-sync", "--no-instructions")  # fmt: skip
        settings = {"listen_addresses": "127.0.0.1", "port": str(self.port),
                    "unix_socket_directories": str(self.folder),
                    "fsync": "off", "synchronous_commit": "off", "full_page_writes": "off",
                    # every process of a test cluster has a pool of up to 64 connections (services/core/db.py)
                    "max_connections": "400", "shared_buffers": "64MB"}  # fmt: skip
        args = [f"--{k.replace('_', '-')}={v}" for k, v in settings.items()]
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen([str(self.bindir / "postgres"), "-D", str(self.data), *args], cwd=self.folder,
                                         stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                         preexec_fn=_die_with_parent, **self.as_user)  # fmt: skip
        end = time.monotonic() + timeout
        while not self.ready():
            if self.proc.poll() is not None or time.monotonic() > end:
                tail = self.log.read_text(errors="replace")[-3000:]
                self.stop()
                raise RuntimeError(f"PostgreSQL did not start on port {self.port}:\n{tail}")
            time.sleep(0.1)
        return self

    def ready(self) -> bool:
        import psycopg

        try:
            with psycopg.connect(**self.params("postgres"), connect_timeout=2) as conn:
                conn.execute("SELECT 1")
            return True
        except psycopg.OperationalError:
            return False

    def params(self, database: str) -> dict[str, Any]:
        return {"host": str(self.folder), "port": self.port, "user": SUPERUSER, "dbname": database}

    def url(self, database: str) -> str:
        """SQLAlchemy URL of `database` over the unix socket."""
        return f"postgresql+psycopg://{SUPERUSER}@/{database}?host={self.folder}&port={self.port}"

    def create_database(self, name: str) -> str:
        """A new empty database (dropped first if it exists); returns its URL."""
        import psycopg

        assert re.fullmatch(r"[a-z_][a-z0-9_]*", name), name
        with psycopg.connect(**self.params("postgres"), autocommit=True) as conn:
            conn.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def stop(self) -> None:
        """Fast shutdown (SIGINT: open sessions are ended), then the folder is removed."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self.proc = None
        shutil.rmtree(self.folder, ignore_errors=True)
