"""The reverse proxy in front of the API (deploy/nginx/neumatex.conf.template, services/proxy.py), with a real
nginx: uploads arrive as the proxy's body files (a zip unpacked from it, a PUT file hard-linked into place), the
proxy's name for a body file is honoured only with its secret, what nginx refuses itself is answered in the API's
error format, and no body file outlives its request. Also the raw PUT of one file into an upload session, directly
to the API."""

from __future__ import annotations

import hashlib
import io
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from neumatex_client.client import Client
from services.cluster import wait_for
from services.proxy import render

from .helpers import EXAMPLE, KEY_A, Service, capture_zip, upload


@pytest.fixture(scope="module")
def proxied(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    svc = Service(tmp_path_factory.mktemp("proxied"), proxy=True)
    svc.redis.start()
    svc.add_tenant("a", KEY_A)
    svc.start_api()
    yield svc
    svc.stop()


def _digests(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}  # fmt: skip


def _stored(service: Service, capture_id: str) -> Path:
    return service.storage / "captures" / capture_id


def _no_bodies_left(service: Service) -> None:
    """nginx removes a body file when it frees the request, which may be just after the client has the answer."""
    assert service.proxy_config is not None
    body_dir = service.proxy_config.body_dir
    wait_for(lambda: not any(body_dir.iterdir()), 5, f"nginx to remove its body files ({list(body_dir.iterdir())})")


def test_a_zip_through_the_proxy_is_unpacked_from_its_body_file(proxied: Service) -> None:
    with proxied.client() as c:
        r = upload(c, capture_zip())
    assert r.status_code == 201, r.text
    cap = r.json()
    skip = ("photos", "gbuffers")
    want = {k: v for k, v in _digests(EXAMPLE).items() if k.split("/")[0] not in skip}
    assert _digests(_stored(proxied, cap["id"])) == want
    _no_bodies_left(proxied)


def test_the_client_puts_large_files_and_they_arrive_whole(proxied: Service, tmp_path: Path) -> None:
    folder = tmp_path / "teapot"
    with zipfile.ZipFile(io.BytesIO(capture_zip(prefix=""))) as z:
        z.extractall(folder)
    (folder / "notes.txt").write_bytes(bytes(range(256)) * 20_000)  # 5 MB: larger than the chunk, so a PUT
    client = Client(proxied.url, KEY_A)
    cap = client.upload_capture(folder, chunk_bytes=1 << 20)
    stored = _stored(proxied, cap.id)
    assert _digests(stored) == _digests(folder)
    assert (stored / "notes.txt").stat().st_mode & 0o777 == 0o644
    _no_bodies_left(proxied)
    assert (stored / "notes.txt").stat().st_nlink == 1  # the proxy's own name for the body file is gone


def test_a_body_file_header_is_refused_without_the_proxys_secret(proxied: Service) -> None:
    forged = {"X-Neumatex-Body-File": "/etc/passwd", "Content-Type": "application/zip"}
    with httpx.Client(base_url=proxied.api_url, headers={"Authorization": f"Bearer {KEY_A}"}) as direct:
        r = direct.post("/v1/captures", content=capture_zip(), headers=forged)
        assert r.status_code == 400
        assert "only accepted from this service's proxy" in r.json()["error"]
        r = direct.post("/v1/captures", content=capture_zip(),
                        headers={**forged, "X-Neumatex-Body-Token": "guessed-guessed-guessed"})  # fmt: skip
        assert r.status_code == 400
    with proxied.client() as c:  # through the proxy the client's headers are replaced: its real body is used
        r = c.post("/v1/captures", content=capture_zip(), headers={**forged, "X-Neumatex-Body-Token": "x" * 20})
        assert r.status_code == 201, r.text
    _no_bodies_left(proxied)


def test_what_the_proxy_refuses_is_answered_in_the_apis_format(proxied: Service) -> None:
    with proxied.client() as c:
        r = c.post("/v1/captures", content=b"\0" * (9 * 1024**2), headers={"Content-Type": "application/zip"})
        assert r.status_code == 413
        assert r.json()["error"] == f"upload larger than the limit of {8 * 1024**2} bytes"
        bad = capture_zip(extra={"../../escape.txt": b"x"})
        r = upload(c, bad)
        assert r.status_code == 422 and "zip-slip" in r.text
    _no_bodies_left(proxied)


def test_put_of_one_file_into_a_session_directly(proxied: Service) -> None:
    with httpx.Client(base_url=proxied.api_url, headers={"Authorization": f"Bearer {KEY_A}"}) as c:
        up = c.post("/v1/uploads", json={"name": "put"}).json()
        url = f"/v1/uploads/{up['id']}/files"
        assert c.put(f"{url}/notes.txt", content=b"hello").status_code == 200
        r = c.put(f"{url}/notes.txt", content=b"hello")
        assert r.status_code == 409 and r.json()["problems"] == [{"file": "notes.txt", "message": "already uploaded"}]
        r = c.put(f"{url}/notes.txt/inner.txt", content=b"x")
        assert r.status_code == 422 and "both a file and a folder" in r.json()["error"]
        r = c.put(f"{url}/run.sh", content=b"x")
        assert r.status_code == 415
        r = c.put(f"{url}/..%2F..%2Fescape.txt", content=b"x")
        assert r.status_code in (404, 422)  # a name escaping the capture never reaches the disk
        assert c.delete(f"/v1/uploads/{up['id']}").status_code == 204


def test_the_template_fills_only_its_own_names() -> None:
    out = render("listen ${NEUMATEX_PROXY_LISTEN}; set $x $request_body_file;", {"NEUMATEX_PROXY_LISTEN": "80"})
    assert out == "listen 80; set $x $request_body_file;"
    with pytest.raises(KeyError, match="NEUMATEX_API_UPSTREAM"):
        render("server ${NEUMATEX_API_UPSTREAM};", {})


def test_a_proxy_body_dir_needs_the_secret(tmp_path: Path) -> None:
    from services.core.config import Settings

    with pytest.raises(ValueError, match="NEUMATEX_PROXY_BODY_TOKEN"):
        Settings(proxy_body_dir=tmp_path)


def _raw_request(url: str, head: str, timeout: float = 10) -> bytes:
    """Send only the request's head (no body) and return what the server answers within `timeout`."""
    import socket
    from urllib.parse import urlparse

    u = urlparse(url)
    with socket.create_connection((u.hostname, u.port), timeout=timeout) as sock:
        sock.sendall(head.encode())
        answer = b""
        while b"\r\n\r\n" not in answer:
            chunk = sock.recv(65536)
            if not chunk:
                break
            answer += chunk
        return answer


def test_the_proxy_refuses_before_reading_a_body(proxied: Service) -> None:
    # a declared 6 MiB body that is never sent: the refusal must come anyway (nginx asked the API first)
    head = ("POST /v1/captures HTTP/1.1\r\nHost: x\r\nContent-Type: application/zip\r\n"
            f"Content-Length: {6 * 1024**2}\r\n\r\n")  # fmt: skip
    answer = _raw_request(proxied.url, head)
    assert answer.startswith(b"HTTP/1.1 401"), answer[:200]
    assert b"WWW-Authenticate: Bearer" in answer
    answer = _raw_request(proxied.url, head.replace("Host: x", "Host: x\r\nX-API-Key: nmx_unknown_key_0123456789"))
    assert answer.startswith(b"HTTP/1.1 401"), answer[:200]
    with proxied.client() as c:
        r = c.post("/v1/captures", content=b"x" * 1000, headers={"Authorization": "Bearer nope"})
        assert r.status_code == 401 and r.json() == {"error": "unknown or revoked API key"}
        r = c.put("/v1/uploads/upl_nope/files/notes.txt", content=b"x")
        assert r.status_code == 404 and r.json() == {"error": "upload 'upl_nope' not found"}
        up = c.post("/v1/uploads", json={"name": "budget"}).json()
        assert c.put(f"/v1/uploads/{up['id']}/files/a.txt", content=b"a" * (5 * 1024**2)).status_code == 200
        r = c.put(f"/v1/uploads/{up['id']}/files/b.txt", content=b"b" * (4 * 1024**2))  # over what is left
        assert r.status_code == 413
        assert r.json()["error"] == f"upload larger than the limit of {3 * 1024**2} bytes (3.0 MiB)"
        assert c.delete(f"/v1/uploads/{up['id']}").status_code == 204
    _no_bodies_left(proxied)


def test_the_dashboards_cookie_uploads_through_the_proxy(proxied: Service) -> None:
    csrf = {"X-NeuMatEx-CSRF": "1"}
    with httpx.Client(base_url=proxied.url, timeout=60) as browser:
        assert browser.post("/v1/session", json={"api_key": KEY_A}, headers=csrf).status_code == 200
        r = browser.post("/v1/captures", content=capture_zip(), headers={"Content-Type": "application/zip", **csrf})
        assert r.status_code == 201, r.text
        r = browser.post("/v1/captures", content=capture_zip(), headers={"Content-Type": "application/zip"})
        assert r.status_code == 403 and "X-NeuMatEx-CSRF" in r.json()["error"]  # the API still checks the request
    _no_bodies_left(proxied)
