"""The reverse proxy (nginx) in front of the API on one machine: its configuration rendered from the one template
that docker-compose.yml also uses (deploy/nginx/neumatex.conf.template), and the command that runs it. Used by
`python -m services serve` when nginx is installed and by services/cluster.py (tests, bench/service.py).

Why a proxy (docs/service.md "Uploads through the proxy"): nginx writes an upload's body to disk at C speed and
hands the API the file's name, so a capture never passes through the API's event loop byte by byte.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import socket
from dataclasses import dataclass, field
from pathlib import Path

TEMPLATE = Path(__file__).resolve().parents[1] / "deploy" / "nginx" / "neumatex.conf.template"
_NAME = re.compile(r"\$\{(NEUMATEX_[A-Z0-9_]+)\}")


def render(template: str, values: dict[str, str]) -> str:
    """`template` with each ${NEUMATEX_...} replaced from `values` (nginx's own $variables stay); KeyError names a
    missing one."""
    missing = sorted({m for m in _NAME.findall(template) if m not in values})
    if missing:
        raise KeyError(f"the proxy template needs {', '.join(missing)}")
    return _NAME.sub(lambda m: values[m.group(1)], template)


@dataclass
class ProxyConfig:
    """One nginx in `folder` (its config, pid, logs, temp files) on `host:port`, passing requests to the API on
    127.0.0.1:`api_port`; upload bodies go to `body_dir` (the API's NEUMATEX_PROXY_BODY_DIR)."""

    folder: Path
    port: int
    api_port: int
    max_upload_bytes: int
    workers: int | str = "auto"
    host: str = "127.0.0.1"
    token: str = field(default_factory=lambda: secrets.token_urlsafe(24))

    @property
    def body_dir(self) -> Path:
        return self.folder / "bodies"

    def api_env(self) -> dict[str, str]:
        """The settings the API needs to take bodies from this proxy."""
        return {"NEUMATEX_PROXY_BODY_DIR": str(self.body_dir), "NEUMATEX_PROXY_BODY_TOKEN": self.token}

    def write(self) -> Path:
        """Write nginx.conf (and the rendered server block) under `folder`; returns nginx.conf's path."""
        for sub in ("bodies", "proxy_temp", "client_temp", "fastcgi_temp", "uwsgi_temp", "scgi_temp"):
            (self.folder / sub).mkdir(parents=True, exist_ok=True, mode=0o700)
        server = render(TEMPLATE.read_text(), {
            "NEUMATEX_API_UPSTREAM": f"127.0.0.1:{self.api_port}", "NEUMATEX_PROXY_LISTEN": f"{self.host}:{self.port}",
            "NEUMATEX_PROXY_BODY_DIR": str(self.body_dir), "NEUMATEX_PROXY_BODY_TOKEN": self.token,
            "NEUMATEX_MAX_UPLOAD_BYTES": str(self.max_upload_bytes)})  # fmt: skip
        (self.folder / "neumatex.conf").write_text(server)
        f = self.folder
        user = "user root root;\n" if os.geteuid() == 0 else ""  # else nginx's workers would be nobody's
        main = (f"daemon off;\nworker_processes {self.workers};\npid {f}/nginx.pid;\nerror_log {f}/error.log warn;\n"
                f"{user}events {{ worker_connections 4096; }}\n"
                f"http {{\n  access_log off;\n  client_body_temp_path {f}/client_temp;\n"
                f"  proxy_temp_path {f}/proxy_temp;\n  fastcgi_temp_path {f}/fastcgi_temp;\n"
                f"  uwsgi_temp_path {f}/uwsgi_temp;\n  scgi_temp_path {f}/scgi_temp;\n"
                f"  include {f}/neumatex.conf;\n}}\n")  # fmt: skip
        conf = self.folder / "nginx.conf"
        conf.write_text(main)
        return conf

    def command(self) -> list[str]:
        """nginx in the foreground on the written config (write() first)."""
        exe = nginx_path()
        if exe is None:
            raise RuntimeError("nginx not found: `make sysdeps` installs it (apt-get install nginx-light)")
        f = self.folder
        return [exe, "-p", str(f), "-e", str(f / "error.log"), "-c", str(f / "nginx.conf")]


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def nginx_path() -> str | None:
    return shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx",) if os.access(p, os.X_OK)), None)
