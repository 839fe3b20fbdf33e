"""The dashboard (services/routes/dashboard*.py) and the report behind its job page (services/routes/reports.py).

On one completed tiny job: the report route serves the pipeline's own index.html and every image it references
(PNG, not uniform) with its Content-Security-Policy; another tenant gets 404, `..` is refused; the token links open
that job's report only and expire. The login: an API key for a signed HttpOnly SameSite=Strict cookie that the
API accepts in place of the key, with CSRF checks on requests that change something, ending at logout, expiry or
the key's revocation. Then the real dashboard in Debian's Chromium driven by Playwright: log in through the form,
upload the example capture as a zip with the tiny preset and watch its row's progress bar, fed by the job's event
stream, reach 100 %; filters and pages; the job page with the report's images all loaded, the loss and PSNR curves,
metrics, the asset downloaded (a real download: a zip with manifest.json) and the 3-D viewer button; a folder
upload whose running job is canceled, retried and canceled again with the page's buttons; a failed job's error in
plain words; logout. Screenshots: NEUMATEX_UPDATE_SCREENSHOTS=1 writes docs/dashboard.png and
docs/dashboard-job.png."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from services.cluster import REPO, wait_for

from .helpers import (
    EXAMPLE,
    KEY_A,
    KEY_B,
    TINY,
    Service,
    blank_masks,
    capture_zip,
    job,
    mint_in_service,
    submit,
    upload,
    wait_state,
)

CHROMIUM = "/usr/bin/chromium"  # Debian's (make sysdeps); Playwright downloads nothing
KEY_A2 = "nmx_test_tenant_a_second_key_0123456789"  # a second key of tenant A, revoked by a test
SCREENSHOTS = os.environ.get("NEUMATEX_UPDATE_SCREENSHOTS") == "1"


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
        grants = (tenant_id, -5), (tenant_id, 60), (other_tenant, 60)  # expired, fresh, another tenant
        expired, fresh, stranger = mint_in_service(service, "report-token", jid, *grants)
        r = browser.get(f"/v1/jobs/{jid}/report-token/{expired}/index.html")
        assert r.status_code == 403 and "expired" in r.json()["error"]
        assert browser.get(f"/v1/jobs/{jid}/report-token/{fresh}/index.html").status_code == 200
        # a token minted for tenant B (which does not own the job) is a 404, like every other-tenant id
        assert browser.get(f"/v1/jobs/{jid}/report-token/{stranger}/index.html").status_code == 404



# -- the login: a signed session cookie ---------------------------------------------------------------------------
CSRF = {"X-NeuMatEx-CSRF": "1"}


def login(service: Service, key: str = KEY_A, **headers: str) -> httpx.Response:
    return httpx.post(f"{service.url}/v1/session", json={"api_key": key}, headers={**CSRF, **headers}, timeout=30)


def cookie_client(service: Service, value: str) -> httpx.Client:
    return httpx.Client(base_url=service.url, cookies={"nmx_session": value}, timeout=60)


def in_service(service: Service, code: str, *args: str) -> str:
    out = subprocess.run([sys.executable, "-c", code, *args], env=service.env, cwd=REPO, check=True,
                         capture_output=True, text=True)  # fmt: skip
    return out.stdout.strip()


def test_session_cookie_login_csrf_and_logout(service: Service, done: dict[str, Any]) -> None:
    jid = done["id"]
    bad = login(service, "nmx_not_a_key_0123456789")
    assert bad.status_code == 401 and "set-cookie" not in bad.headers
    no_csrf = httpx.post(f"{service.url}/v1/session", json={"api_key": KEY_A}, timeout=30)
    assert no_csrf.status_code == 403 and "X-NeuMatEx-CSRF" in no_csrf.json()["error"]
    assert login(service, Origin="https://evil.example").status_code == 403
    r = login(service)
    assert r.status_code == 200, r.text
    assert r.json()["tenant"]["name"] == "a"
    set_cookie = r.headers["set-cookie"]
    attrs = {a.strip().split("=")[0].lower() for a in set_cookie.split(";")}
    assert {"httponly", "path", "max-age"} <= attrs and "samesite=strict" in set_cookie.lower(), set_cookie
    assert "secure" not in attrs  # plain http here (public_url http): a Secure cookie would never be sent back
    value = r.cookies["nmx_session"]
    assert KEY_A not in value and KEY_A not in set_cookie  # a signed session value, not the key
    with cookie_client(service, value) as c:
        # reading needs nothing else
        assert jid in {j["id"] for j in c.get("/v1/jobs").json()["items"]}
        assert c.get(f"/v1/jobs/{jid}").json()["state"] == "completed"
        assert c.get(f"/v1/jobs/{jid}/asset").status_code == 200
        # changing something needs the CSRF header, and a same-origin Origin / Sec-Fetch-Site when sent
        r = c.post(f"/v1/jobs/{jid}/cancel")
        assert r.status_code == 403 and "X-NeuMatEx-CSRF" in r.json()["error"], r.text
        r = c.post(f"/v1/jobs/{jid}/cancel", headers={**CSRF, "Origin": "https://evil.example"})
        assert r.status_code == 403 and "another origin" in r.json()["error"]
        r = c.post(f"/v1/jobs/{jid}/cancel", headers={**CSRF, "Sec-Fetch-Site": "cross-site"})
        assert r.status_code == 403 and "cross-site" in r.json()["error"]
        r = c.post(f"/v1/jobs/{jid}/cancel", headers={**CSRF, "Origin": service.url, "Sec-Fetch-Site": "same-origin"})
        assert r.status_code == 409 and "only queued or running" in r.json()["error"]  # authenticated, then refused
        # an API key header wins over the cookie (programs), so tenant B sees none of A's jobs
        assert c.get(f"/v1/jobs/{jid}", headers={"Authorization": f"Bearer {KEY_B}"}).status_code == 404
        assert c.get("/v1/jobs", headers={"X-API-Key": "nmx_wrong"}).status_code == 401
    # tenant B's session does not reach tenant A's job
    with cookie_client(service, login(service, KEY_B).cookies["nmx_session"]) as b:
        assert b.get(f"/v1/jobs/{jid}").status_code == 404
    # forged, expired, other-secret values are 401
    forged = value[:-2] + ("AA" if not value.endswith("AA") else "BB")
    for v in (forged, "garbage", value.split(".")[0]):
        with cookie_client(service, v) as c:
            assert c.get("/v1/jobs").status_code == 401, v
    code = ("import sys; from services.core.db import session_scope; from services.crud import tenant_for_key\n"
            "from services.routes.dashboard_session import key_row, mint\n"
            "with session_scope() as s: row = key_row(s, sys.argv[1]); print(mint(row.tenant_id, row.id, ttl_s=-5)[0])")
    expired = in_service(service, code, KEY_A)
    with cookie_client(service, expired) as c:
        r = c.get("/v1/jobs")
        assert r.status_code == 401 and "expired" in r.json()["error"]
    # revoking the key ends its sessions
    service.add_tenant("a", KEY_A2)
    second = login(service, KEY_A2).cookies["nmx_session"]
    with cookie_client(service, second) as c:
        assert c.get("/v1/jobs").status_code == 200
        in_service(service, "import sys; from sqlalchemy import update; from services.core.db import session_scope\n"
                   "from services.models import ApiKey; from services.core.security import hash_api_key\n"
                   "with session_scope() as s: s.execute(update(ApiKey).where(ApiKey.key_hash == "
                   "hash_api_key(sys.argv[1])).values(revoked=True))", KEY_A2)
        r = c.get("/v1/jobs")
        assert r.status_code == 401 and "revoked" in r.json()["error"]
    assert login(service, KEY_A2).status_code == 401
    # logout removes the cookie
    out = httpx.delete(f"{service.url}/v1/session", cookies={"nmx_session": value}, headers=CSRF, timeout=30)
    assert out.status_code == 204 and re.search(r"nmx_session=(\"\")?;", out.headers["set-cookie"])
    assert "max-age=0" in out.headers["set-cookie"].lower()


# -- the dashboard in Chromium (Playwright) -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    assert Path(CHROMIUM).is_file(), "chromium is needed (make sysdeps installs it)"
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--disable-dev-shm-usage", "--disable-gpu"])
        yield b
        b.close()


class Page:
    """A logged-in dashboard tab (the login through the form), with the page's script errors collected."""

    def __init__(self, browser: Any, service: Service):
        self.service = service
        self.context = browser.new_context(viewport={"width": 1280, "height": 900}, accept_downloads=True)
        self.page = self.context.new_page()
        self.page.set_default_timeout(30_000)
        self.errors: list[str] = []
        self.page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))
        self.page.on("console", self._console)

    def _console(self, message: Any) -> None:
        if message.type == "error" and "401" not in message.text:  # 401: the login page's own check, a bad key
            self.errors.append(message.text)

    def close(self) -> None:
        self.context.close()


@pytest.fixture(scope="module")
def tab(browser: Any, service: Service, done: dict[str, Any]) -> Iterator[Page]:
    t = Page(browser, service)
    page = t.page
    page.goto(service.url + "/")
    page.wait_for_selector("#login-form", state="visible")
    assert page.is_hidden("#app")
    page.fill("#login-key", "nmx_not_a_key_0123456789")
    page.click("#login-submit")
    page.wait_for_function("() => document.getElementById('login-error').textContent.includes('unknown or revoked')")
    page.fill("#login-key", KEY_A)
    page.click("#login-submit")
    page.wait_for_selector("#app", state="visible")
    assert "tenant a" in page.inner_text("#who")
    (cookie,) = [c for c in t.context.cookies() if c["name"] == "nmx_session"]
    assert cookie["httpOnly"] and cookie["sameSite"] == "Strict" and cookie["path"] == "/"
    assert KEY_A not in cookie["value"] and KEY_A not in page.url
    assert page.evaluate("document.cookie") == ""  # HttpOnly: no script reads it
    assert page.evaluate("localStorage.length + sessionStorage.length") == 0  # the key is kept nowhere
    assert page.input_value("#login-key") == ""
    yield t
    assert not t.errors, t.errors  # no script error and no Content-Security-Policy violation on the way
    t.close()


def row_of(page: Any, job_id: str) -> dict[str, str] | None:
    return dict(page.evaluate("""id => {const r = document.querySelector(`tr[data-job="${id}"]`); if (!r) return null;
        return {state: r.dataset.state, progress: r.dataset.progress, events: r.dataset.events,
                pct: r.querySelector('.pct').textContent, stage: r.querySelector('.stage').textContent,
                eta: r.querySelector('.eta').textContent,
                width: r.querySelector('.fill').style.width}}""", job_id) or {}) or None


def shoot(page: Any, name: str, tmp: Path, height: int = 0) -> None:
    """A screenshot (the whole page, or its top `height` pixels) into docs/ with NEUMATEX_UPDATE_SCREENSHOTS=1."""
    target = (REPO / "docs" / name) if SCREENSHOTS else tmp / name
    clip = {"x": 0, "y": 0, "width": 1280, "height": height} if height else None
    # generous timeout: a full-page capture of the framed report takes tens of seconds on 2 busy cores
    page.screenshot(path=str(target), full_page=True, clip=clip, timeout=180_000)
    assert target.stat().st_size > 10_000


def test_browser_upload_zip_and_watch_live_progress(tab: Page, service: Service, tmp_path: Path) -> None:
    page = tab.page
    zip_path = tmp_path / "teapot.zip"
    zip_path.write_bytes(capture_zip())
    page.select_option("#up-preset", "tiny")
    page.fill("#up-config", "{not json")
    page.set_input_files("#up-zip", str(zip_path))
    page.click("#up-submit")
    page.wait_for_selector("#up-status[data-state=error]")
    assert "not valid JSON" in page.inner_text("#up-status")
    page.fill("#up-config", json.dumps(TINY))
    page.select_option("#up-variation", "uniform")  # goes into the config: with TINY's random init it is refused
    page.click("#up-submit")
    page.wait_for_selector("#up-status[data-state=error]")
    assert "variation='uniform'" in page.inner_text("#up-status")
    assert [e for e in tab.errors if "422" in e] and all("422" in e for e in tab.errors)  # the browser logs it
    tab.errors.clear()
    page.select_option("#up-variation", "")  # the default (choose; textured without a PBR start)
    page.click("#up-submit")
    page.wait_for_selector("#up-status[data-state=created]", timeout=60_000)
    jid = page.get_attribute("#up-status", "data-job")
    assert jid and jid.startswith("job_")
    # The row follows the job's event stream: record what it shows until the job completes.
    seen: list[dict[str, str]] = []
    end = time.monotonic() + 240
    while time.monotonic() < end:
        r = row_of(page, jid)
        if r:
            seen.append(r)
            if r["state"] in ("completed", "failed", "canceled"):
                break
        time.sleep(0.1)
    final = seen[-1]
    assert final["state"] == "completed", (final, job(service.client(), jid).get("error"))
    page.wait_for_function("id => document.querySelector(`tr[data-job='${id}'] .pct`).textContent === '100%'", arg=jid)
    assert row_of(page, jid)["width"] == "100%"  # type: ignore[index]
    shown = [float(r["progress"]) for r in seen]
    assert shown == sorted(shown) and len(set(shown)) >= 3, shown  # the bar moved forward, in steps
    assert max(int(r["events"]) for r in seen) > 0, seen[-3:]  # updated by the stream's events, not only by polls
    stages = {r["stage"] for r in seen}
    assert "tto" in stages or "export" in stages, stages  # the stage column followed the job
    assert any(r["eta"].endswith(" s") for r in seen if r["state"] == "running"), seen  # an ETA while it ran
    page.wait_for_selector(f'tr[data-job="{jid}"] a[href$="/asset.zip"]')  # the list reloaded once it ended
    # the state filter and paging
    page.select_option("#f-state", "failed")
    page.wait_for_function("id => !document.querySelector(`tr[data-job='${id}']`)", arg=jid)
    page.select_option("#f-state", "completed")
    page.wait_for_selector(f'tr[data-job="{jid}"]')
    page.select_option("#f-state", "")
    page.wait_for_selector(f'tr[data-job="{jid}"]')
    shoot(page, "dashboard.png", tmp_path)
    other = tab.context.new_page()
    other.goto(service.url + "/?per_page=1")
    other.wait_for_selector(f'tr[data-job="{jid}"]')  # the newest first
    assert other.locator("#rows tr[data-job]").count() == 1 and other.is_disabled("#prev")
    other.click("#next")
    other.wait_for_function("id => !document.querySelector(`tr[data-job='${id}']`)", arg=jid)
    assert other.locator("#rows tr[data-job]").count() == 1 and "2-2 of" in other.inner_text("#page-info")
    other.click("#prev")
    other.wait_for_selector(f'tr[data-job="{jid}"]')
    other.close()


def test_browser_job_page(tab: Page, service: Service, done: dict[str, Any], tmp_path: Path) -> None:
    page, jid = tab.page, done["id"]
    with service.client() as c:
        expected = len(images_of(c.get(f"/v1/jobs/{jid}/report/index.html").text))
        steps = len(c.get(f"/v1/jobs/{jid}/report/history.json").json())
        has_viewer = "/v1/jobs/{job_id}/viewer-token" in c.get("/openapi.json").json()["paths"]
    page.goto(f"{service.url}/#job/{jid}")
    page.wait_for_selector("#j-state[data-state=completed]")
    page.wait_for_function("() => Number(document.getElementById('report-status').dataset.total) > 0",
                           timeout=60_000)
    status = page.locator("#report-status")
    got = [int(status.get_attribute(f"data-{k}") or -1) for k in ("loaded", "total", "failed")]
    assert got == [expected, expected, 0], got
    assert f"report: {expected} of {expected} images loaded" in status.inner_text()
    # The frame's images, counted by the test too: all loaded, none broken, the report's renders among them.
    frame = page.frame_locator("#report")
    imgs = page.evaluate("""() => Array.from(document.getElementById('report').contentDocument.images).map(
        i => ({src: i.getAttribute('src'), ok: i.complete && i.naturalWidth > 0}))""")
    assert len(imgs) == expected >= 5 and all(i["ok"] for i in imgs), imgs
    assert "curves.png" in {i["src"] for i in imgs}
    assert frame.locator("body").inner_text()  # the report's own words are there
    # The loss and PSNR curves: every TTO step from history.json.
    page.wait_for_selector("#curve-loss")
    for curve in ("curve-loss", "curve-psnr"):
        assert page.get_attribute(f"#{curve}", "data-points") == str(steps)
        points = page.get_attribute(f"#{curve} polyline", "points") or ""
        assert len(points.split()) == steps and len(set(points.split())) > 1, points
    assert "steps (the report's history.json)" in page.inner_text("#j-curve")
    # metrics and timings per stage
    timings = dict(page.evaluate("""() => Array.from(document.querySelectorAll('#j-metrics-table tr')).slice(1)
        .map(r => [r.cells[0].textContent, r.cells[1].textContent])"""))
    assert list(timings) == ["validate", "prepare_views", "lmrm", "tto", "export"], timings
    assert all(float(v) >= 0 for v in timings.values()) and float(timings["tto"]) > 0, timings
    assert "psnr_batch" in page.inner_text("#j-metrics-table")
    assert page.is_hidden("#j-failed")
    assert page.is_disabled("#j-cancel") and page.is_disabled("#j-retry")
    # the asset: a real download of the zip
    with page.expect_download() as info:
        page.click("#j-zip")
    download = info.value
    assert download.suggested_filename == f"{jid}.zip"
    with zipfile.ZipFile(download.path()) as z:
        assert z.testzip() is None and "manifest.json" in z.namelist()
    # the 3-D viewer: a new tab on the URL POST .../viewer-token returns, or the button disabled with a note
    if has_viewer:
        assert page.is_enabled("#j-viewer")
        with page.expect_popup() as popup:
            page.click("#j-viewer")
        viewer = popup.value
        viewer.wait_for_url(re.compile(r"^https?://"), timeout=30_000)  # from about:blank to the returned URL
        assert viewer.url.startswith(service.url), viewer.url
        assert viewer.evaluate("window.opener") is None  # the viewer tab cannot reach back into the dashboard
        viewer.close()
    else:
        page.wait_for_function("() => document.getElementById('j-viewer-note').textContent.includes('not available')")
        assert page.is_disabled("#j-viewer")
    shoot(page, "dashboard-job.png", tmp_path, height=1700)


def test_browser_folder_upload_cancel_and_retry(tab: Page, service: Service, tmp_path: Path) -> None:
    """A folder upload (webkitdirectory) whose job runs long enough to cancel from its page, then retry, then
    cancel again (the worker is freed for the next test)."""
    import shutil

    page = tab.page
    folder = tmp_path / "pot-folder"
    shutil.copytree(EXAMPLE, folder, ignore=shutil.ignore_patterns("photos", "gbuffers"))
    page.goto(service.url + "/#")
    page.wait_for_selector("#upload-form")
    page.select_option("#up-preset", "tiny")
    page.fill("#up-name", "")
    page.fill("#up-config", json.dumps({**TINY, "tto": {"steps": 20000}}))
    page.set_input_files("#up-dir", str(folder))
    page.click("#up-submit")
    page.wait_for_selector("#up-status[data-state=created]", timeout=60_000)
    jid = page.get_attribute("#up-status", "data-job")
    assert jid
    with service.client() as c:
        cap = c.get(f"/v1/captures/{job(c, jid)['capture_id']}").json()
        assert cap["name"] == "pot-folder" and cap["frames"] == 23, cap
    page.click(f'tr[data-job="{jid}"] a[href^="#job/"]')
    page.wait_for_selector("#j-state[data-state=running]", timeout=120_000)
    with service.client() as c:
        wait_for(lambda: job(c, jid)["stage"] == "tto", 120, "the TTO to start")
    page.wait_for_selector("#curve-loss", timeout=60_000)  # live curve points from the progress events
    assert page.is_disabled("#j-retry")
    page.click("#j-cancel")
    page.wait_for_selector("#j-state[data-state=canceled]", timeout=30_000)
    assert page.is_enabled("#j-retry") and page.is_disabled("#j-cancel")
    page.click("#j-retry")
    page.wait_for_function("() => ['queued', 'running'].includes(document.getElementById('j-state').dataset.state)")
    with service.client() as c:
        assert job(c, jid)["attempt"] >= 2
    page.click("#j-cancel")
    page.wait_for_selector("#j-state[data-state=canceled]", timeout=30_000)
    with service.client() as c:
        assert job(c, jid)["state"] == "canceled"


def test_browser_failed_job_in_plain_words(tab: Page, service: Service) -> None:
    masks = blank_masks()
    with service.client() as c:
        r = upload(c, capture_zip(drop=tuple(masks), extra=masks), name="no-cover")
        assert r.status_code == 201, r.text
        jid = submit(c, r.json()["id"])["id"]
        failed = wait_state(c, jid, ("completed", "failed", "canceled"), 120, service)
    assert failed["state"] == "failed"
    page = tab.page
    page.goto(f"{service.url}/#job/{jid}")
    page.wait_for_selector("#j-state[data-state=failed]")
    page.wait_for_selector("#j-failed", state="visible")
    text = page.inner_text("#j-failed")
    assert "This job failed in its tto stage" in text and "covers no pixel of any photo" in text, text
    assert page.is_enabled("#j-retry") and page.is_disabled("#j-cancel")
    assert "/tmp" not in text and str(service.root) not in text  # no server paths
    page.goto(f"{service.url}/#")
    page.wait_for_selector(f'tr[data-job="{jid}"][data-state=failed]')
    assert "covers no pixel" in page.inner_text(f'tr[data-job="{jid}"] + tr.errrow')


def test_report_scripts_do_not_run(tab: Page, service: Service, done: dict[str, Any]) -> None:
    """A script and an onerror handler put into the report folder, opened through a token, run neither."""
    jid = done["id"]
    folder = service.storage / "assets" / jid / "asset" / "report"
    assert (folder / "index.html").is_file()
    (folder / "evil.html").write_text("<!doctype html><html><body><p id='p'>static</p><script>document.getElementById"
                                      "('p').textContent='script ran'</script>"
                                      "<img src='nope.png' onerror=\"document.title='handler ran'\"></body></html>")
    try:
        with service.client() as c:
            url = c.post(f"/v1/jobs/{jid}/report-token").json()["url"].replace("index.html", "evil.html")
        page = tab.context.new_page()
        page.goto(service.url + url)
        page.wait_for_load_state("load")
        time.sleep(0.5)
        assert page.inner_text("#p") == "static" and page.title() != "handler ran"
        page.close()
    finally:
        (folder / "evil.html").unlink()


def test_browser_logout(tab: Page, service: Service) -> None:
    page = tab.page
    page.goto(service.url + "/#")
    page.wait_for_selector("#logout", state="visible")
    page.click("#logout")
    page.wait_for_selector("#login-form", state="visible")
    assert "logged out" in page.inner_text("#login-error") and page.is_hidden("#app")
    assert not [c for c in tab.context.cookies() if c["name"] == "nmx_session"]
    assert page.evaluate("fetch('/v1/jobs').then(r => r.status)") == 401
    page.reload()
    page.wait_for_selector("#login-form", state="visible")
