"""The Python client (neumatex_client) and `neumatex submit | jobs | job` against the real service, and webhooks: the
client uploads the example capture in chunks, submits a tiny job, follows it to the end and downloads its asset;
`neumatex submit DIR --wait --out` on a batch of three captures, one of which fails in its job, gives two asset
zips, one error line naming the failed capture and its problem, exit 1, and a signed webhook per job (the first
answered 500, then delivered after the backoff); a bad key is a clear error and exit 3; a webhook receiver in the
test gets one signed POST per terminal job (completed, canceled), the first answered 500 and retried; the client's
own retries with backoff honour Retry-After; the client's models match the app's OpenAPI schema."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from datetime import datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest

from neumatex_client import AuthError, Client, Conflict, Invalid, ServiceUnreachable, verify_signature
from neumatex_client.client import _capture_files
from neumatex_client.models import SCHEMA_NAMES
from services.cluster import REPO, Proc, wait_for

from .helpers import EXAMPLE, KEY_A, TINY, Service, blank_masks


class Receiver(ThreadingHTTPServer):
    """A webhook receiver: records every POST (path, headers, body, the status it answered); `fail_first` paths
    answer 500 to their first POST."""

    def __init__(self, fail_first: tuple[str, ...] = ()) -> None:
        self.posts: list[dict[str, Any]] = []
        self.fail_first = set(fail_first)
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                status = 500 if self.path in receiver.fail_first else 200
                receiver.fail_first.discard(self.path)
                receiver.posts.append({"path": self.path, "headers": dict(self.headers), "body": body,
                                       "status": status})  # fmt: skip
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *_: Any) -> None:
                pass

        super().__init__(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server_address[1]}"
        threading.Thread(target=self.serve_forever, daemon=True).start()

    def ok(self, path: str) -> list[dict[str, Any]]:
        return [p for p in self.posts if p["path"] == path and p["status"] == 200]


@pytest.fixture(scope="module")
def worker(service: Service) -> Iterator[Proc]:
    w = service.start_worker()
    yield w
    w.stop()


@pytest.fixture(scope="module")
def receiver(service: Service) -> Iterator[Receiver]:  # one per database: its first /flaky answer is a 500
    r = Receiver(fail_first=("/flaky",))
    yield r
    r.shutdown()


def _check_signed(post: dict[str, Any], secret: str) -> dict[str, Any]:
    sig = post["headers"]["X-NeuMatEx-Signature"]
    assert verify_signature(secret, post["body"], sig), sig
    assert not verify_signature(secret, post["body"] + b" ", sig)  # the body is what is signed
    assert not verify_signature("whsec_other", post["body"], sig)
    assert not verify_signature(secret, post["body"], sig, now=time.time() + 3600)  # an old delivery replayed
    return dict(json.loads(post["body"]))


def test_client_upload_submit_wait_download_and_webhooks(service: Service, worker: Proc, receiver: Receiver,
                                                         tmp_path: Path) -> None:  # fmt: skip
    with Client(service.url, KEY_A) as c:
        assert c.quota().tenant == "a"
        sent: list[tuple[int, int]] = []
        cap = c.upload_capture(EXAMPLE, chunk_bytes=1 << 20, progress=lambda a, b: sent.append((a, b)))
        assert cap.frames == 23 and cap.files == len(_capture_files(EXAMPLE, ()))
        assert len(sent) >= 3 and sent[-1][0] == sent[-1][1]  # several requests of the init/upload/commit flow
        # A request whose answer was lost and that is sent again is recognised; a real clash still raises.
        up = c.request("POST", "/v1/uploads", json={"name": "again"}).json()["id"]
        files = _capture_files(EXAMPLE, ())
        c._upload_chunk(up, files[:3])
        c._upload_chunk(up, files[:3])
        with pytest.raises(Conflict, match="already uploaded"):
            c._upload_chunk(up, files[2:5])
        c.request("DELETE", f"/v1/uploads/{up}")

        with pytest.raises(Invalid, match="http or https"):
            c.create_job(cap.id, preset="tiny", config=TINY, webhook_url="ftp://example.com/x")
        job = c.create_job(cap.id, preset="tiny", config=TINY, webhook_url=receiver.url + "/flaky")
        queued = c.create_job(cap.id, preset="tiny", config=TINY, webhook_url=receiver.url + "/canceled")
        assert c.cancel(queued.id).state == "canceled"
        events: list[Any] = []
        done = c.wait(job.id, timeout=150, on_event=events.append)
        assert done.state == "completed", done.error
        progress = [e.data["progress"] for e in events if "progress" in e.data]
        assert progress and progress[-1] == 1.0 and events[-1].event == "end"
        asset = c.download_asset(job.id, tmp_path)
        with zipfile.ZipFile(asset) as z:
            assert z.testzip() is None and "manifest.json" in z.namelist()
            assert json.loads(z.read("manifest.json"))["metrics"]["tto_steps"] == 12

        # Webhooks: one signed POST per terminal job; the first try of /flaky got a 500 and was retried.
        secret = c.webhook_secret()
        wait_for(lambda: receiver.ok("/flaky") and receiver.ok("/canceled"), 30, "both webhooks")
        body = _check_signed(receiver.ok("/flaky")[0], secret)
        assert body["job_id"] == job.id and body["state"] == "completed" and body["event"] == "job.completed"
        assert body["asset_url"] == f"{service.url}/v1/jobs/{job.id}/asset.zip" and body["metrics"]["tto"]["steps"]
        assert [p["status"] for p in receiver.posts if p["path"] == "/flaky"] == [500, 200]
        canceled = _check_signed(receiver.ok("/canceled")[0], secret)
        assert canceled["job_id"] == queued.id and canceled["state"] == "canceled" and canceled["asset_url"] is None
        shown = wait_for(lambda: (j := c.get_job(job.id)).webhooks and j.webhooks[0].status == "delivered" and j,
                         10, "the delivery recorded")  # fmt: skip
        (d,) = shown.webhooks
        assert d.attempts == 2 and [a.status_code for a in d.log] == [500, 200] and d.log[0].error
        assert d.url == receiver.url + "/flaky" and shown.webhook_url == d.url and d.next_at is None
        assert len(c.get_job(queued.id).webhooks) == 1
        time.sleep(1.0)  # no second delivery of the same ending
        assert len(receiver.ok("/flaky")) == 1 and len(receiver.ok("/canceled")) == 1


def _run_cli(*args: str, key: str | None = KEY_A, timeout: float = 240,
             module: str = "neumatex_client") -> subprocess.CompletedProcess[str]:  # fmt: skip
    """`python -m neumatex_client ARGS`, or with module="neumatex_core.cli" the `neumatex` command itself (its
    dispatch to the client; 2 s more, as it imports torch)."""
    env = {k: v for k, v in os.environ.items() if k not in ("NEUMATEX_API_KEY", "NEUMATEX_URL")}
    if key is not None:
        env["NEUMATEX_API_KEY"] = key
    return subprocess.run([sys.executable, "-m", module, *args], env=env, cwd=REPO, text=True,
                          capture_output=True, timeout=timeout)  # fmt: skip


def test_cli_submit_batch_wait_out(service: Service, worker: Proc, receiver: Receiver, tmp_path: Path) -> None:
    """Three captures in one `neumatex submit DIR --wait --out`, one broken in a way only its job finds (masks all
    zero: it uploads, then its TTO fails): two asset zips, one error line naming that capture and the problem, exit
    1 (the documented "a job failed; the others still ran"), and a signed webhook for each of the three, the first
    answered 500 and delivered on a later try after the backoff."""
    batch = tmp_path / "batch"
    for name in ("pot-a", "pot-b", "pot-c"):
        shutil.copytree(EXAMPLE, batch / name, ignore=shutil.ignore_patterns("photos", "gbuffers"))
    for rel, data in blank_masks().items():
        (batch / "pot-c" / rel).write_bytes(data)
    receiver.fail_first.add("/batch")  # the receiver fails the batch's first delivery
    out = tmp_path / "assets"
    t0 = time.monotonic()
    r = _run_cli("submit", str(batch), "--preset", "tiny", "--config", json.dumps(TINY), "--wait", "--out",
                 str(out), "--url", service.url, "--webhook", receiver.url + "/batch", "--timeout", "200",
                 module="neumatex_core.cli")
    print(f"submit of 3 captures: {time.monotonic() - t0:.1f} s")
    assert r.returncode == 1, r.stdout + r.stderr  # EXIT_FAILED: some failed, the others still ran
    assert "Traceback" not in r.stderr
    assert all(f"{n}: job_" in r.stderr for n in ("pot-a", "pot-b", "pot-c")) and "100%" in r.stderr  # bars
    zips = sorted(out.glob("*.zip"))
    assert [z.name for z in zips] == ["pot-a.zip", "pot-b.zip"], r.stdout
    for z in zips:
        with zipfile.ZipFile(z) as f:
            assert "manifest.json" in f.namelist()
    lines = [line.split("\t") for line in r.stdout.strip().splitlines()]
    assert [(ln[0], ln[2].split(" ")[0]) for ln in lines] == [("pot-a", "completed"), ("pot-b", "completed"),
                                                               ("pot-c", "failed")], r.stdout  # fmt: skip
    ids = {ln[1] for ln in lines if ln[0] != "pot-c"}
    failed_id = lines[2][1]
    # one line names the broken capture, its job and the problem in the pipeline's words; then the count
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert errors == [f"error: pot-c ({failed_id}) failed: stage tto: the mesh covers no pixel of any photo",
                      "error: 1 of 3 captures did not give an asset"], r.stderr  # fmt: skip
    with Client(service.url, KEY_A) as c:
        secret = c.webhook_secret()
        wait_for(lambda: len(receiver.ok("/batch")) == 3, 30, "the batch's webhooks")
        bodies = {(b := _check_signed(p, secret))["job_id"]: b for p in receiver.ok("/batch")}
        assert set(bodies) == ids | {failed_id}
        assert {bodies[i]["event"] for i in ids} == {"job.completed"}
        failed = bodies[failed_id]
        assert failed["event"] == "job.failed" and failed["state"] == "failed" and failed["asset_url"] is None
        assert "covers no pixel" in failed["error"]
        # the first delivery got the 500 and was sent again after the backoff (WEBHOOK_BACKOFF_S 0.5 s)
        statuses = [p["status"] for p in receiver.posts if p["path"] == "/batch"]
        assert statuses.count(500) == 1 and statuses.count(200) == 3, statuses
        flaky_id = json.loads(next(p["body"] for p in receiver.posts if p["path"] == "/batch"))["job_id"]
        (d,) = wait_for(lambda: [w for w in c.get_job(flaky_id).webhooks if w.status == "delivered"], 10,
                        "the retried delivery recorded")  # fmt: skip
        assert d.attempts == 2 and [a.status_code for a in d.log] == [500, 200], d.log
        gap = (datetime.fromisoformat(str(d.log[1].at)) - datetime.fromisoformat(str(d.log[0].at))).total_seconds()
        assert gap >= 0.45, gap  # backed off before trying again
        for other in (ids | {failed_id}) - {flaky_id}:  # a job's status may be 0.5 s stale (services/fastpath.py)
            (w,) = wait_for(lambda o=other: [w for w in c.get_job(o).webhooks if w.status == "delivered"], 10,
                            f"the delivery of {other} recorded")  # fmt: skip
            assert w.attempts == 1

    # status: a line per job, exit 1 naming the failed one; 0 when all named jobs completed
    st = _run_cli("status", *sorted(ids), failed_id, "--url", service.url, module="neumatex_core.cli")
    assert st.returncode == 1 and f"error: job {failed_id} failed" in st.stderr, st.stdout + st.stderr
    assert [ln.split("\t")[1] for ln in st.stdout.strip().splitlines()] == ["completed", "completed", "failed"]
    st = _run_cli("status", *sorted(ids), "--url", service.url)
    assert st.returncode == 0 and st.stdout.count("\tcompleted\t") == 2, st.stdout + st.stderr
    # jobs / job: exit 0 and the job named
    listed = _run_cli("jobs", "--url", service.url, "--state", "completed")
    assert listed.returncode == 0 and all(i in listed.stdout for i in ids), listed.stdout + listed.stderr
    one = _run_cli("job", sorted(ids)[0], "--url", service.url)
    assert one.returncode == 0 and "completed" in one.stdout and "webhook" in one.stdout, one.stdout + one.stderr
    shown = json.loads(_run_cli("job", sorted(ids)[0], "--url", service.url, "--json").stdout)
    assert shown["webhooks"][0]["status"] == "delivered"
    got = _run_cli("download", sorted(ids)[0], "--out", str(tmp_path / "dl"), "--url", service.url)
    assert got.returncode == 0 and zipfile.is_zipfile(tmp_path / "dl" / f"{sorted(ids)[0]}.zip"), got.stderr
    late = _run_cli("cancel", sorted(ids)[0], "--url", service.url)
    assert late.returncode == 1 and "only queued or running jobs can be canceled" in late.stderr, late.stderr
    again = _run_cli("retry", sorted(ids)[0], "--url", service.url)
    assert again.returncode == 1 and "retry needs a failed or canceled job" in again.stderr, again.stderr


def test_bad_key_and_bad_input_are_clear(service: Service, tmp_path: Path) -> None:
    with Client(service.url, "nmx_not_a_key_0123456789") as c, pytest.raises(AuthError) as err:
        c.list_jobs()
    assert err.value.status == 401 and "unknown or revoked API key" in str(err.value)
    r = _run_cli("jobs", "--url", service.url, key="nmx_not_a_key_0123456789", module="neumatex_core.cli")
    assert r.returncode == 3 and "unknown or revoked API key" in r.stderr, r.stderr
    r = _run_cli("submit", str(EXAMPLE), "--url", service.url, "--api-key", "nmx_wrong_0123456789")
    assert r.returncode == 3 and "API key" in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = _run_cli("jobs", "--url", service.url, key=None)
    assert r.returncode == 2 and "NEUMATEX_API_KEY" in r.stderr
    r = _run_cli("submit", str(tmp_path), "--url", service.url)
    assert r.returncode == 2 and "holds no capture" in r.stderr
    # A broken capture in a batch: named with the server's words, exit 1, no job for it.
    broken = tmp_path / "broken"
    shutil.copytree(EXAMPLE, broken, ignore=shutil.ignore_patterns("photos", "gbuffers"))
    (broken / "mesh.obj").write_text("this is not a mesh\n")
    r = _run_cli("submit", str(broken), "--url", service.url, "--preset", "tiny", "--no-progress")
    assert r.returncode == 1 and "broken" in r.stderr and "mesh.obj" in r.stderr, r.stderr


class Flaky(ThreadingHTTPServer):
    """Answers 503 with Retry-After: 1 to the first `fails` requests, then a quota body."""

    def __init__(self, fails: int) -> None:
        self.times: list[float] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                server.times.append(time.monotonic())
                if len(server.times) <= fails:
                    body, status = b'{"error": "the service is restarting"}', 503
                else:
                    body, status = json.dumps({"tenant": "a", "work_retention_s": None, "jobs": {"active": 0,
                                               "limit": None}, "storage": {"used_bytes": 1, "limit_bytes": None,
                                               "captures_bytes": 1, "uploads_bytes": 0, "jobs_bytes": 0}}).encode(), 200
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Retry-After", "1")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *_: Any) -> None:
                pass

        super().__init__(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server_address[1]}"
        threading.Thread(target=self.serve_forever, daemon=True).start()


def test_client_retries_with_backoff() -> None:
    flaky = Flaky(fails=2)
    try:
        with Client(flaky.url, "k", backoff_s=0.05) as c:
            assert c.quota().storage.used_bytes == 1
        gaps = [b - a for a, b in zip(flaky.times, flaky.times[1:], strict=False)]
        assert len(flaky.times) == 3 and all(g >= 0.95 for g in gaps), gaps  # Retry-After honoured
        with Client(flaky.url, "k", retries=1, backoff_s=0.05, max_backoff_s=0.1) as c:
            flaky.times.clear()
            with pytest.raises(Exception, match="the service is restarting"):
                c.quota()  # 503 twice: retries spent, the server's words in the error
    finally:
        flaky.shutdown()
        flaky.server_close()
    with Client(f"http://127.0.0.1:{flaky.server_address[1]}", "k", retries=2, backoff_s=0.05) as c:
        t0 = time.monotonic()
        with pytest.raises(ServiceUnreachable, match="3 tries"):
            c.quota()
        assert time.monotonic() - t0 >= 0.1  # backed off between the tries


def test_client_models_match_openapi() -> None:
    from services.main import app

    schemas = app.openapi()["components"]["schemas"]
    for model, name in SCHEMA_NAMES.items():
        schema = schemas.get(name) or schemas[f"{name}-Output"]
        assert set(model.model_fields) == set(schema["properties"]), (model.__name__, name)
        required = {k for k, f in model.model_fields.items() if f.is_required()}
        assert required == set(schema.get("required", [])), (model.__name__, name)
    job_create = schemas["JobCreate"]["properties"]
    assert {"capture_id", "preset", "config", "queue", "idempotency_key", "webhook_url"} == set(job_create)


def test_webhook_url_checks() -> None:
    from services.webhooks import url_problem

    for url in ("http://127.0.0.1:9/hook", "http://10.1.2.3/hook", "http://[::1]/x", "http://169.254.169.254/x",
                "http://[::ffff:192.168.0.1]/x"):  # fmt: skip
        problem = url_problem(url, allow_private=False)
        assert problem and "loopback, private or reserved" in problem, (url, problem)
        assert url_problem(url, allow_private=True) is None
    assert url_problem("https://93.184.216.34/hook", allow_private=False) is None  # a public address
    assert "http or https" in (url_problem("file:///etc/passwd") or "")
    assert "no host" in (url_problem("http:///x") or "")
    assert "not a valid URL" in (url_problem("http://h:99999999/") or "")
