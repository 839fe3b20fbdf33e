"""The 3-D viewer route (services/routes/viewer.py) on one completed tiny job: `POST /v1/jobs/{id}/viewer-token` needs
the key and returns the page's URL under a token; the page, its script and its bundle load with that token alone and
the viewer's Content-Security-Policy; another tenant, a forged, garbled, other-job or expired token, and files that
are not the viewer's are all 404."""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np

from .helpers import KEY_B, Service, mint_in_service


def test_viewer_token_opens_the_page_and_its_bundle(service: Service, done: dict[str, Any]) -> None:
    jid = done["id"]
    with httpx.Client(base_url=service.url, timeout=60) as anonymous:
        assert anonymous.post(f"/v1/jobs/{jid}/viewer-token").status_code == 401
    with service.client(KEY_B) as other:
        r = other.post(f"/v1/jobs/{jid}/viewer-token")
        assert r.status_code == 404 and "not found" in r.json()["error"]
        other_tenant = other.get("/v1/me").json()["tenant"]["id"]
    with service.client() as c:
        t = c.post(f"/v1/jobs/{jid}/viewer-token")
        assert t.status_code == 200, t.text
        token, url = t.json()["token"], t.json()["url"]
        assert url == f"/v1/jobs/{jid}/viewer-token/{token}/index.html"
        tenant_id = c.get("/v1/me").json()["tenant"]["id"]
        assert c.post(f"/v1/jobs/{jid}/viewer-token").status_code == 200  # built once, minted again
    with httpx.Client(base_url=service.url, timeout=60) as browser:
        page = browser.get(url)
        assert page.status_code == 200 and page.headers["content-type"] == "text/html; charset=utf-8"
        csp = page.headers["content-security-policy"]
        assert "script-src 'self'" in csp and "connect-src 'self'" in csp and "default-src 'none'" in csp
        assert "unsafe-eval" not in csp and "<script src=\"viewer.js\"></script>" in page.text
        base = url.rsplit("/", 1)[0]
        js = browser.get(f"{base}/viewer.js")
        assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript")
        info = browser.get(f"{base}/bundle.json").json()
        mesh = browser.get(f"{base}/{info['mesh']['file']}")
        corners = np.frombuffer(mesh.content, "<f4").reshape(-1, 11)
        assert len(corners) == info["mesh"]["corners"] and len(corners) % 3 == 0
        assert np.abs(np.linalg.norm(corners[:, 3:6], axis=1) - 1).max() < 1e-3  # unit shading normals
        res = info["material"]["resolution"]
        material = browser.get(f"{base}/{info['material']['file']}")
        channels = info["material"]["channels"]  # rho_d, the basis's latents, PBR, mask, zeros: whole RGBA texels
        assert channels == 4 * -(-(3 + info["basis"]["latent_dim"] + 6) // 4)
        assert len(material.content) == res * res * channels * 4
        assert info["basis"]["basis_id"] == c_manifest_basis(service, jid)
        env = info["envmaps"][0]
        assert browser.get(f"{base}/{env['file']}").status_code == 200
        # the token opens nothing else, and nothing when altered, expired or minted for another tenant
        for bad in ("%2e%2e/%2e%2e/asset/manifest.json", "..%2fasset%2fmanifest.json", "nope.bin", "report/index.html"):
            assert browser.get(f"{base}/{bad}").status_code == 404, bad
        assert browser.get(f"/v1/jobs/{jid}/asset/files/manifest.json").status_code == 401
        forged = token[:-2] + ("AA" if not token.endswith("AA") else "BB")
        grants = (tenant_id, -5), (tenant_id, 60), (other_tenant, 60)  # expired, fresh, another tenant
        expired, fresh, stranger = mint_in_service(service, "viewer-token", jid, *grants)
        for t_bad in (forged, "garbage", "a.b", expired, stranger):
            r = browser.get(f"/v1/jobs/{jid}/viewer-token/{t_bad}/index.html")
            assert r.status_code == 404, (t_bad, r.status_code)
        assert browser.get(f"/v1/jobs/job_other/viewer-token/{token}/index.html").status_code == 404
        assert browser.get(f"/v1/jobs/{jid}/viewer-token/{fresh}/bundle.json").status_code == 200
    # the page runs under its policy in Debian's Chromium (software WebGL2) and draws the asset
    from viewer_fixtures import read_display, viewer_page

    with viewer_page(service.url + url + "?auto=0&size=48", viewport=400) as tab:
        violations: list[str] = []
        tab.on("console", lambda m: violations.append(m.text) if "Content Security Policy" in m.text else None)
        tab.evaluate("() => window.neumatexViewer.renderFrames(2)")
        image = read_display(tab)
        assert tab.evaluate("() => window.neumatexViewer.error") is None and not violations, violations
        assert image.std() > 0.02  # an object in front of a map, not a blank canvas


def c_manifest_basis(service: Service, job_id: str) -> str:
    with service.client() as c:
        return str(c.get(f"/v1/jobs/{job_id}/asset").json()["manifest"]["basis"]["basis_id"])
