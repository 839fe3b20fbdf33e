"""The dashboard's job page and the report behind it (services/routes/reports.py, services/routes/dashboard.py), on
one completed tiny job: the report route serves the pipeline's own index.html and every image it references (PNG,
not uniform) with its Content-Security-Policy; another tenant gets 404, `..` is refused; the token links open
that job's report only and expire; and headless Chromium, loading the real dashboard with the key in the URL
fragment, shows the job's state and the report with all its images loaded."""

from __future__ import annotations

import io
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from services.cluster import REPO

from .helpers import KEY_A, KEY_B, Service, capture_zip, submit, upload, wait_state

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def done(service: Service) -> Iterator[dict[str, Any]]:
    """One completed tiny job of tenant A (the worker is stopped afterwards)."""
    worker = service.start_worker()
    try:
        with service.client() as c:
            r = upload(c, capture_zip())
            assert r.status_code == 201, r.text
            first = submit(c, r.json()["id"])
            job = wait_state(c, first["id"], ("completed", "failed", "canceled"), 240, service)
            assert job["state"] == "completed", job["error"]
        yield job
    finally:
        worker.stop()


def images_of(page: str) -> list[str]:
    return re.findall(r"<img src='([^']+)'", page)


def test_report_route_serves_the_pipelines_report(service: Service, done: dict[str, Any]) -> None:
    jid = done["id"]
    with service.client() as c:
        r = c.get(f"/v1/jobs/{jid}/report/index.html")
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == "text/html; charset=utf-8"
        csp = r.headers["content-security-policy"]
        assert "default-src 'none'" in csp and "sandbox" in csp
        assert "allow-scripts" not in csp and "script-src" not in csp and "connect-src" not in csp
        assert r.headers["x-content-type-options"] == "nosniff"
        # the very file the pipeline wrote into the asset, not another rendering of it
        assert r.content == c.get(f"/v1/jobs/{jid}/asset/files/report/index.html").content
        assert c.get(f"/v1/jobs/{jid}/report/").content == r.content
        srcs = images_of(r.text)
        assert len(srcs) >= 5 and "curves.png" in srcs, srcs
        for src in srcs:
            img = c.get(f"/v1/jobs/{jid}/report/{src}")
            assert img.status_code == 200 and img.headers["content-type"] == "image/png", (src, img.status_code)
            assert "sandbox" in img.headers["content-security-policy"]
            pixels = np.asarray(Image.open(io.BytesIO(img.content)).convert("RGB"), dtype=np.float32)
            assert pixels.max() - pixels.min() > 10, f"{src} is uniform"
        assert c.get(f"/v1/jobs/{jid}/report/history.json").headers["content-type"] == "application/json"
        # only files under report/: `..` (also percent-encoded), absolute paths, NUL, folders and missing files
        for bad in ("%2e%2e/manifest.json", "..%2fmanifest.json", "%2e%2e%2f%2e%2e%2f%2e%2e%2fjobs.db",
                    "%2fetc%2fpasswd", "index.html%00.png", "nope.png"):  # fmt: skip
            r = c.get(f"/v1/jobs/{jid}/report/{bad}")
            assert r.status_code == 404, (bad, r.status_code)
        assert c.get(f"/v1/jobs/{jid}/asset/files/manifest.json").status_code == 200  # it exists, above report/
        assert c.get("/v1/jobs/job_nope/report/index.html").status_code == 404
    with service.client(KEY_B) as other:
        for r in (other.get(f"/v1/jobs/{jid}/report/index.html"), other.get(f"/v1/jobs/{jid}/report/curves.png"),
                  other.post(f"/v1/jobs/{jid}/report-token")):  # fmt: skip
            assert r.status_code == 404 and "not found" in r.json()["error"], r.status_code
    with httpx.Client(base_url=service.url, timeout=60) as anonymous:
        assert anonymous.get(f"/v1/jobs/{jid}/report/index.html").status_code == 401


def mint_in_service(service: Service, job_id: str, *grants: tuple[str, float]) -> list[str]:
    """Tokens minted with the service's own secret (its data folder) for (tenant id, seconds to live) each, e.g. one
    that has already expired."""
    code = ("import sys; from services.routes.reports import mint; "
            "[print(mint(sys.argv[1], t, ttl_s=float(s))[0]) for t, s in zip(sys.argv[2::2], sys.argv[3::2])]")
    args = [str(x) for grant in grants for x in grant]
    out = subprocess.run([sys.executable, "-c", code, job_id, *args], env=service.env, cwd=REPO, check=True,
                         capture_output=True, text=True)  # fmt: skip
    return out.stdout.split()


def test_report_token_links(service: Service, done: dict[str, Any]) -> None:
    jid = done["id"]
    with service.client() as c:
        t = c.post(f"/v1/jobs/{jid}/report-token")
        assert t.status_code == 200, t.text
        token, url = t.json()["token"], t.json()["url"]
        assert url == f"/v1/jobs/{jid}/report-token/{token}/index.html"
        tenant_id = c.get("/v1/me").json()["tenant"]["id"]
    # no key: the token alone opens the report and its images
    with httpx.Client(base_url=service.url, timeout=60) as browser:
        page = browser.get(url)
        assert page.status_code == 200 and page.headers["content-type"] == "text/html; charset=utf-8"
        assert "sandbox" in page.headers["content-security-policy"]
        base = url.rsplit("/", 1)[0]
        for src in images_of(page.text):
            assert browser.get(f"{base}/{src}").headers["content-type"] == "image/png"
        assert browser.get(f"{base}/%2e%2e/manifest.json").status_code == 404
        # the token opens nothing else: not the API, not another job, not when altered or expired
        assert browser.get(f"/v1/jobs/{jid}", params={"token": token}).status_code == 401
        assert browser.get(f"/v1/jobs/{jid}/asset/files/manifest.json").status_code == 401
        other = browser.get(f"/v1/jobs/job_other/report-token/{token}/index.html")
        assert other.status_code == 403 and "another job" in other.json()["error"]
        forged = token[:-2] + ("AA" if not token.endswith("AA") else "BB")
        assert browser.get(f"/v1/jobs/{jid}/report-token/{forged}/index.html").status_code == 403
        assert browser.get(f"/v1/jobs/{jid}/report-token/garbage/index.html").status_code == 403
        with service.client(KEY_B) as b:
            other_tenant = b.get("/v1/me").json()["tenant"]["id"]
        expired, fresh, stranger = mint_in_service(service, jid, (tenant_id, -5), (tenant_id, 60), (other_tenant, 60))
        r = browser.get(f"/v1/jobs/{jid}/report-token/{expired}/index.html")
        assert r.status_code == 403 and "expired" in r.json()["error"]
        assert browser.get(f"/v1/jobs/{jid}/report-token/{fresh}/index.html").status_code == 200
        # a token minted for tenant B (which does not own the job) is a 404, like every other-tenant id
        assert browser.get(f"/v1/jobs/{jid}/report-token/{stranger}/index.html").status_code == 404


def headless(url: str, out: Path, *extra: str, budget_ms: int = 20000) -> str:
    """What headless Chromium made of the page (its DOM after `budget_ms` of virtual time), or a screenshot."""
    assert CHROMIUM, "chromium is needed (make sysdeps installs it)"
    cmd = [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
           "--no-first-run", f"--user-data-dir={out}", f"--virtual-time-budget={budget_ms}", *extra, url]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def test_dashboard_job_page_in_a_browser(service: Service, done: dict[str, Any], tmp_path: Path) -> None:
    jid = done["id"]
    with service.client() as c:
        expected = len(images_of(c.get(f"/v1/jobs/{jid}/report/index.html").text))
    dom = headless(f"{service.url}/#job/{jid}&key={KEY_A}", tmp_path / "profile", "--dump-dom")
    state = re.search(r'id="j-state"[^>]*data-state="([a-z]+)"', dom)
    assert state and state.group(1) == "completed", dom[-3000:]
    status = re.search(r'<p id="report-status" data-loaded="(\d+)" data-total="(\d+)" data-failed="(\d+)"', dom)
    assert status, dom[-3000:]
    loaded, total, failed = map(int, status.groups())
    assert (loaded, total, failed) == (expected, expected, 0), status.group(0)
    assert f"report: {expected} of {expected} images loaded" in dom
    assert 'id="curve-values"' in dom and "TTO loss" in dom  # the loss/PSNR values from the progress events
    assert "steps (the report's history.json)" in dom
    assert "/report-token/" in dom and 'sandbox="allow-same-origin"' in dom
    # a completed job: no cancel or retry, the asset to download
    for button in ("j-cancel", "j-retry"):
        assert re.search(rf'<button id="{button}"[^>]*disabled', dom), button
    assert re.search(r'<a id="j-zip" href="#">', dom), "the asset link is hidden"
    # A script in a report file does not run (the policy and the sandbox), so it cannot reach the API or the key.
    folder = service.storage / "assets" / jid / "asset" / "report"
    assert (folder / "index.html").is_file()
    (folder / "evil.html").write_text("<!doctype html><html><body><p id='p'>static</p><script>document.getElementById"
                                      "('p').textContent='script ran: '+localStorage.length</script>"
                                      "<img src='nope.png' onerror=\"document.title='handler ran'\"></body></html>")
    try:
        with service.client() as c:
            url = c.post(f"/v1/jobs/{jid}/report-token").json()["url"].replace("index.html", "evil.html")
        evil = headless(f"{service.url}{url}", tmp_path / "profile", "--dump-dom", budget_ms=3000)
        assert '<p id="p">static</p>' in evil and "<title>handler ran</title>" not in evil, evil
    finally:
        (folder / "evil.html").unlink()
    # The list links each job to its page.
    listing = headless(f"{service.url}/#key={KEY_A}", tmp_path / "profile", "--dump-dom", budget_ms=5000)
    assert f'href="#job/{jid}"' in listing
