"""Bad input gets a clear error (status, plain words, the file concerned) and leaves nothing behind: no capture
row, nothing in captures/ or staging/. Also the other upload forms (multi-file form, init/upload/commit) and
bad or missing API keys. No worker is needed: captures are validated before anything is queued."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from .helpers import EXAMPLE, KEY_B, METRICS_TOKEN, Service, capture_zip, upload

FILES = sorted(p for p in EXAMPLE.rglob("*") if p.is_file() and p.relative_to(EXAMPLE).parts[0] not in
               ("photos", "gbuffers"))  # fmt: skip


def storage(service: Service) -> Path:
    return service.root / "data" / "storage"


def snapshot(service: Service, c: httpx.Client) -> tuple[list[str], list[str], list[str]]:
    st = storage(service)
    caps = sorted(p.name for p in (st / "captures").iterdir()) if (st / "captures").is_dir() else []
    staged = sorted(p.name for p in (st / "staging").iterdir()) if (st / "staging").is_dir() else []
    return caps, staged, sorted(x["id"] for x in c.get("/v1/captures").json())


@pytest.fixture
def client(service: Service) -> Iterator[httpx.Client]:
    with service.client() as c:
        before = snapshot(service, c)
        yield c
        assert snapshot(service, c) == before, "a rejected upload left something behind"


def transforms() -> dict:
    return dict(json.loads((EXAMPLE / "transforms.json").read_text()))


def problems(r: httpx.Response) -> str:
    return json.dumps(r.json().get("problems", []))


def test_corrupt_image(client: httpx.Client) -> None:
    r = upload(client, capture_zip(extra={"images/003.png": b"not a png"}, drop=("images/003.png",)))
    assert r.status_code == 422, r.text
    assert "problem" in r.json()["error"] and "images/003.png" in problems(r)


def test_inconsistent_cameras(client: httpx.Client) -> None:
    t = transforms()
    m = np.asarray(t["frames"][2]["transform_matrix"])
    m[:3, :3] *= 1.7  # not a rotation: scaled axes
    t["frames"][2]["transform_matrix"] = m.tolist()
    t["w"] = 80  # images are 64 px wide
    r = upload(client, capture_zip(extra={"transforms.json": json.dumps(t).encode()}, drop=("transforms.json",)))
    assert r.status_code == 422, r.text
    found = r.json()["problems"]
    assert any(p["file"] == "transforms.json" and "frames[2]" in p["message"] and "orthonormal" in p["message"]
               for p in found), found  # fmt: skip
    assert any(p["file"] == "images/000.png" and "64x64" in p["message"] and "80x64" in p["message"] for p in found)


def test_wrong_file_types(client: httpx.Client) -> None:
    r = upload(client, capture_zip(extra={"tools/run.sh": b"#!/bin/sh\nrm -rf /\n"}))
    assert r.status_code == 415 and "tools/run.sh" in problems(r), r.text
    r = client.post("/v1/captures", content=b"hello", headers={"Content-Type": "text/plain"})
    assert r.status_code == 415 and "content type" in r.json()["error"]
    r = upload(client, b"this is not a zip at all")
    assert r.status_code == 422 and "zip" in (r.json()["error"] + problems(r))
    files = [("files", ("transforms.json", b"{}", "application/json")), ("files", ("a.exe", b"MZ", "x"))]
    r = client.post("/v1/captures", files=files)
    assert r.status_code == 415 and "a.exe" in problems(r)


def test_oversized_upload_413(client: httpx.Client) -> None:
    big = np.random.default_rng(0).bytes(9 * 1024**2)  # over the tests' 8 MiB limit
    r = upload(client, big)
    assert r.status_code == 413 and "limit" in r.json()["error"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: the limit is enforced on the bytes that arrive
        for i in range(0, len(big), 1 << 20):
            yield big[i:i + (1 << 20)]

    r = client.post("/v1/captures", content=chunks(), headers={"Content-Type": "application/zip"})
    assert r.status_code == 413


def test_zip_slip(client: httpx.Client, service: Service) -> None:
    r = upload(client, capture_zip(extra={"../../escaped.txt": b"owned"}))
    assert r.status_code == 422 and "zip-slip" in problems(r), r.text
    assert not list(service.root.rglob("escaped.txt"))


def test_zip_bomb(client: httpx.Client) -> None:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("teapot/transforms.json", json.dumps(transforms()))
        z.writestr("teapot/images/000.png", b"\0" * (30 * 1024**2))
    assert len(buf.getvalue()) < 100_000
    r = upload(client, buf.getvalue())
    assert r.status_code == 422 and "zip bomb" in problems(r), r.text


def test_missing_or_bad_api_key(service: Service) -> None:
    for headers in ({}, {"Authorization": "Bearer nmx_wrong"}, {"X-API-Key": "nope"}, {"Authorization": "Basic x"}):
        r = httpx.get(service.url + "/v1/jobs", headers=headers)
        assert r.status_code == 401 and "API key" in r.json()["error"] and r.headers["www-authenticate"] == "Bearer"
        r = httpx.post(service.url + "/v1/captures", headers={**headers, "Content-Type": "application/zip"},
                       content=capture_zip())  # fmt: skip
        assert r.status_code == 401


def metrics(service: Service) -> dict[str, float]:
    """The service's Prometheus samples, name{labels} -> value."""
    text = httpx.get(service.url + "/metrics", headers={"Authorization": f"Bearer {METRICS_TOKEN}"}).text
    return {k: float(v) for k, v in (ln.rsplit(" ", 1) for ln in text.splitlines() if ln and ln[0] != "#")}


def test_bad_job_requests(service: Service) -> None:
    client = service.client()
    cap = upload(client, capture_zip()).json()
    r = client.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "tiny", "config": {"lmrm_weights": "/etc"}})
    assert r.status_code == 422 and "lmrm_weights" in r.json()["error"]
    r = client.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "tiny", "config": {"tto": {"steps": 0}}})
    assert r.status_code == 422 and "steps" in r.json()["error"]
    r = client.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "huge"})
    assert r.status_code == 422
    assert client.post("/v1/jobs", json={"capture_id": "cap_nope", "preset": "tiny"}).status_code == 404
    with service.client(KEY_B) as other:
        assert other.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "tiny"}).status_code == 404
    assert client.get("/v1/jobs", params={"capture_id": cap["id"]}).json()["total"] == 0  # nothing was queued
    before = metrics(service)  # other tests may have left canceled messages in the gpu queue: compare, not pin
    gpu = client.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "gpu"}).json()
    assert gpu["queue"] == "gpu" and gpu["state"] == "queued"  # the gpu preset goes to the gpu workers
    assert "no live worker takes the 'gpu' queue" in gpu["waiting"]  # flagged, not queued silently
    after = metrics(service)
    # the first stage (validate) of a gpu job runs on the cpu queue (services/lifecycle.py stage_queue)
    for name in ('neumatex_queue_depth{queue="cpu"}', 'neumatex_jobs{state="queued"}'):
        assert after.get(name, 0.0) == before.get(name, 0.0) + 1.0, (name, before, after)
    assert client.post(f"/v1/jobs/{gpu['id']}/cancel").json()["state"] == "canceled"
    assert client.post(f"/v1/jobs/{gpu['id']}/retry", json={"from_stage": "nope"}).status_code == 422
    client.close()


def test_multi_file_form_and_init_upload_commit(service: Service) -> None:
    with service.client() as c:
        form = [("files", (p.relative_to(EXAMPLE).as_posix(), p.read_bytes(), "application/octet-stream"))
                for p in FILES]  # fmt: skip
        r = c.post("/v1/captures", files=form, params={"name": "form"})
        assert r.status_code == 201, r.text
        assert r.json()["frames"] == 23 and r.json()["files"] == len(FILES)
        up = c.post("/v1/uploads", json={"name": "parts"}).json()
        half = len(form) // 2
        a = c.post(f"/v1/uploads/{up['id']}/files", files=form[:half])
        assert a.status_code == 200 and a.json()["files"] == half
        again = c.post(f"/v1/uploads/{up['id']}/files", files=form[:1])
        assert again.status_code == 409
        early = c.post(f"/v1/uploads/{up['id']}/commit")  # incomplete: missing images
        assert early.status_code == 422 and "not found" in problems(early) + early.json()["error"]
        with service.client(KEY_B) as other:
            assert other.post(f"/v1/uploads/{up['id']}/files", files=form[half:]).status_code == 404
        b = c.post(f"/v1/uploads/{up['id']}/files", files=form[half:])
        assert b.status_code == 200 and b.json()["files"] == len(form)
        done = c.post(f"/v1/uploads/{up['id']}/commit")
        assert done.status_code == 201 and done.json()["frames"] == 23
        assert c.post(f"/v1/uploads/{up['id']}/commit").status_code == 404  # consumed
        assert not (storage(service) / "staging" / up["id"]).exists()
