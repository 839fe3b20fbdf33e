"""A capture uploaded over HTTP becomes a finished asset; progress seen through SSE only grows; the asset can be
downloaded (manifest, single files, zip); idempotent job creation; listing with filters and paging; metrics."""

from __future__ import annotations

import io
import json
import zipfile

import httpx

from .helpers import KEY_A, KEY_B, METRICS_TOKEN, Service, capture_zip, job, sse_events, submit, upload, wait_state


def test_upload_to_asset_with_monotone_sse_progress(service: Service) -> None:
    worker = service.start_worker()
    with service.client() as c:
        r = upload(c, capture_zip())
        assert r.status_code == 201, r.text
        cap = r.json()
        assert cap["frames"] == 23 and cap["files"] > 40
        first = submit(c, cap["id"], idempotency_key="first-job")
        assert first["state"] in ("queued", "running") and first["preset"] == "tiny"
        again = c.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "tiny", "config": {
            "init": "random", "device": "cpu", "tto": {}}, "idempotency_key": "first-job"})  # fmt: skip
        assert again.status_code == 200 and again.json()["id"] == first["id"]  # replay, not a second job
        clash = c.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "cpu", "idempotency_key": "first-job"})
        assert clash.status_code == 409 and "idempotency" in clash.json()["error"]
        events = sse_events(service, first["id"])
        done = wait_state(c, first["id"], ("completed", "failed"), 30, service)
        assert done["state"] == "completed", done["error"]
        progress = [e["progress"] for e in events if "progress" in e]
        assert len(progress) >= 10
        assert all(b >= a for a, b in zip(progress, progress[1:], strict=False)), progress
        assert progress[-1] == 1.0 and events[-1]["event"] == "end" and events[-1]["state"] == "completed"
        stages = [e["stage"] for e in events if e["event"] == "stage" and e["status"] == "finished"]
        assert stages == ["validate", "prepare_views", "lmrm", "tto", "export"]
        ids = [e["id"] for e in events if e["id"] is not None]
        assert ids == sorted(ids) and len(set(ids)) == len(ids)
        # Resuming the stream after an event id replays only what followed it.
        later = sse_events_after(service, first["id"], ids[-3])
        assert [e["id"] for e in later if e["id"] is not None] == ids[-2:]
        assert done["stages_done"] == list(stages) and done["progress"] == 1.0
        assert [r["stage"] for r in done["stage_runs"]] == stages and {r["status"] for r in done["stage_runs"]} == {
            "finished"}
        assert done["metrics"]["tto"]["steps"] == 12 and done["timings"]["tto"] > 0
        # The asset: manifest, one file, the zip.
        m = c.get(f"/v1/jobs/{first['id']}/asset")
        assert m.status_code == 200, m.text
        manifest = m.json()
        assert "manifest.json" in manifest["files"] and manifest["manifest"]["metrics"]["tto_steps"] == 12
        f = c.get(f"/v1/jobs/{first['id']}/asset/files/manifest.json")
        assert f.status_code == 200 and json.loads(f.content) == manifest["manifest"]
        assert c.get(f"/v1/jobs/{first['id']}/asset/files/../../../jobs.db").status_code == 404
        z = c.get(f"/v1/jobs/{first['id']}/asset.zip")
        assert z.status_code == 200
        names = zipfile.ZipFile(io.BytesIO(z.content)).namelist()
        assert sorted(n for n in names if not n.endswith("/")) == sorted(manifest["files"])
        # Listing: filters and paging; the other tenant sees none of it.
        page = c.get("/v1/jobs", params={"state": "completed", "limit": 1}).json()
        assert page["total"] >= 1 and len(page["items"]) == 1
        assert c.get("/v1/jobs", params={"state": "failed", "capture_id": cap["id"]}).json()["total"] == 0
    with service.client(KEY_B) as other:
        assert other.get("/v1/jobs").json()["total"] == 0
        for path in (f"/v1/jobs/{first['id']}", f"/v1/jobs/{first['id']}/asset", f"/v1/jobs/{first['id']}/asset.zip",
                     f"/v1/jobs/{first['id']}/asset/files/manifest.json", f"/v1/captures/{cap['id']}",
                     f"/v1/jobs/{first['id']}/events"):  # fmt: skip
            r = other.get(path)
            assert r.status_code == 404, (path, r.status_code)
            assert "not found" in r.json()["error"]
        assert other.post(f"/v1/jobs/{first['id']}/cancel").status_code == 404
        assert other.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "tiny"}).status_code == 404
    metrics = service_metrics(service)
    assert 'neumatex_jobs{state="completed"}' in metrics and "neumatex_stage_duration_seconds_bucket" in metrics
    assert 'neumatex_queue_depth{queue="cpu"} 0.0' in metrics
    ready = c_get(service, "/readyz")
    assert ready["status"] == "ready" and set(ready["checks"]) == {"database", "broker", "storage"}
    worker.stop()
    assert job_of(service, first["id"])["state"] == "completed"


def sse_events_after(service: Service, job_id: str, after: int) -> list[dict]:
    out = []
    with httpx.stream("GET", f"{service.url}/v1/jobs/{job_id}/events", timeout=30,
                      headers={"Authorization": f"Bearer {KEY_A}", "Last-Event-ID": str(after)}) as r:  # fmt: skip
        ident = None
        for line in r.iter_lines():
            if line.startswith("id: "):
                ident = int(line[4:])
            elif line.startswith("event: end"):
                break
            elif line.startswith("data: "):
                out.append({"id": ident})
                ident = None
    return out


def service_metrics(service: Service) -> str:
    assert httpx.get(service.url + "/metrics", timeout=30).status_code == 401  # counts over every tenant
    return httpx.get(service.url + "/metrics", headers={"Authorization": f"Bearer {METRICS_TOKEN}"}, timeout=30).text


def c_get(service: Service, path: str) -> dict:
    return dict(httpx.get(service.url + path, timeout=30).json())


def job_of(service: Service, job_id: str) -> dict:
    with service.client() as c:
        return job(c, job_id)
