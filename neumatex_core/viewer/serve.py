"""`neumatex view ASSET`: write the asset's web bundle into a temporary folder and serve it on localhost with the
standard library's http.server (no web framework in the core), opening the browser unless told not to."""

from __future__ import annotations

import functools
import http.server
import tempfile
import threading
import webbrowser
from dataclasses import dataclass
from pathlib import Path

from neumatex_core.viewer.web_bundle import EnvSource, shared_envmaps, sky_envmap, write_bundle

TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".json": "application/json",
         ".bin": "application/octet-stream"}  # fmt: skip
# The page runs its own script, compiles WebGL shaders and fetches its bundle from the same origin; nothing else.
CSP = ("default-src 'none'; script-src 'self'; connect-src 'self'; style-src 'unsafe-inline'; img-src 'self' data:; "
       "base-uri 'none'; form-action 'none'; frame-ancestors 'self'")  # fmt: skip


class _Handler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, **TYPES}

    def end_headers(self) -> None:
        self.send_header("Content-Security-Policy", CSP)
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the base class's name
        pass


@dataclass
class ViewerServer:
    """A running server of a bundle folder; `url` is the page, `close()` stops it."""

    server: http.server.ThreadingHTTPServer
    thread: threading.Thread
    folder: Path

    @property
    def url(self) -> str:
        host = self.server.server_address[0]
        name = host.decode() if isinstance(host, bytes) else str(host)
        return f"http://{name}:{self.server.server_port}/index.html"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(timeout=5)


def serve_folder(folder: str | Path, port: int = 0, host: str = "127.0.0.1") -> ViewerServer:
    """Serve `folder` (a written bundle) on host:port (0: any free port) from a background thread."""
    handler = functools.partial(_Handler, directory=str(folder))
    server = http.server.ThreadingHTTPServer((host, port), handler)
    thread = threading.Thread(target=server.serve_forever, name="neumatex-view", daemon=True)
    thread.start()
    return ViewerServer(server, thread, Path(folder))


def envmap_choices(envmap: str, shared: str) -> tuple[list[EnvSource], str]:
    """The maps the page offers: `envmap` (a file) first if given, then every map of the `shared` folder; the
    built-in sky when there is none. Returns (maps, default name)."""
    maps: list[EnvSource] = []
    if envmap:
        maps.append(EnvSource.from_file(envmap))
    if shared and Path(shared).is_dir():
        taken = {m.name for m in maps}
        maps += [m for m in shared_envmaps(shared) if m.name not in taken]
    if not maps:
        maps.append(sky_envmap())
    return maps, maps[0].name


def run_view(asset_path: str, envmap: str = "", shared: str = "", port: int = 8765, open_browser: bool = True,
             env_height: int = 256) -> int:
    """Build the bundle, serve it until Ctrl-C; returns the exit code."""
    from neumatex_core.assets import read_asset

    asset = read_asset(asset_path)
    maps, default = envmap_choices(envmap, shared)
    with tempfile.TemporaryDirectory(prefix="neumatex-view-") as tmp:
        write_bundle(asset, tmp, maps, default, env_height)
        viewer = serve_folder(tmp, port)
        names = ", ".join(m.name for m in maps)
        print(f"viewing {asset.name} at {viewer.url} (maps: {names}); Ctrl-C stops", flush=True)
        if open_browser:
            webbrowser.open(viewer.url)
        try:
            viewer.thread.join()
        except KeyboardInterrupt:
            pass
        finally:
            viewer.close()
    return 0
