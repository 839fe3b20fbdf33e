"""The job lifecycle (services/lifecycle.py): per-stage queues (validate, prepare_views and export on `cpu`, lmrm
and tto on the job's queue), checked on the routing function and on a real gpu-queue job run by a cpu and a gpu
worker; and progress streams woken through Redis pub/sub: an event reaches the stream well under a second after
its commit, while an event row written behind the lifecycle's back (no wake-up) is only seen at the slow safety
poll, so the stream does not poll the database every 0.2 s."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import httpx
import pytest
import redis

from neumatex_core.pipeline import STAGES
from services import lifecycle
from services.routes.jobs import SAFETY_POLL_S

from .helpers import KEY_A, Service, capture_zip, db_time, job, sql, submit, upload, wait_state

CPU_STAGES = {"validate", "prepare_views", "export"}


def test_stage_queues() -> None:
    assert lifecycle.job_queue("gpu") == "gpu" and lifecycle.job_queue("tiny") == "cpu"
    assert lifecycle.job_queue("tiny", "gpu") == "gpu" and lifecycle.job_queue("gpu", "cpu") == "cpu"
    for stage in STAGES:
        assert lifecycle.stage_queue(stage, "cpu") == "cpu"
        assert lifecycle.stage_queue(stage, "gpu") == ("cpu" if stage in CPU_STAGES else "gpu")
    assert [s for s in STAGES if lifecycle.stage_queue(s, "gpu") == "gpu"] == ["lmrm", "tto"]
    with pytest.raises(ValueError, match="unknown stage"):
        lifecycle.stage_queue("nope", "gpu")


class Stream:
    """A job's SSE stream read on a thread: every event with the monotonic time it arrived."""

    def __init__(self, service: Service, job_id: str):
        self.events: list[tuple[float, dict[str, Any]]] = []
        self.changed = threading.Condition()
        self.url = f"{service.url}/v1/jobs/{job_id}/events"
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        with httpx.stream("GET", self.url, headers={"Authorization": f"Bearer {KEY_A}"},
                          timeout=httpx.Timeout(60, read=60)) as r:  # fmt: skip
            kind = None
            for line in r.iter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: "):
                    with self.changed:
                        self.events.append((time.monotonic(), {"event": kind, **json.loads(line[6:])}))
                        self.changed.notify_all()
                    if kind == "end":
                        return

    def wait(self, match: Any, timeout: float) -> float | None:
        """When the first event matching `match(event)` arrived (None: not within `timeout` seconds)."""
        end = time.monotonic() + timeout
        with self.changed:
            while True:
                hit = next((t for t, e in self.events if match(e)), None)
                if hit is not None or time.monotonic() >= end:
                    return hit
                self.changed.wait(end - time.monotonic())


def add_event_row(service: Service, job_id: str, kind: str) -> None:
    """An event row written straight into the database: no wake-up is published for it."""
    sql(service, "INSERT INTO events (job_id, kind, data, created_at) VALUES (:job, :kind, :data, :at)", job=job_id,
        kind=kind, data="{}", at=db_time())


def test_progress_stream_is_woken_by_redis_not_by_fast_polling(service: Service) -> None:
    assert SAFETY_POLL_S >= 5.0
    with service.client() as c:
        cap = upload(c, capture_zip()).json()
        j = submit(c, cap["id"])  # no worker runs in this test: it stays queued
        stream = Stream(service, j["id"])
        assert stream.wait(lambda e: e["event"] == "state" and e["state"] == "queued", 30) is not None
        # Behind the lifecycle's back: not seen at once (no 0.2 s polling), only at the safety poll.
        t0 = time.monotonic()
        add_event_row(service, j["id"], "probe")
        assert stream.wait(lambda e: e["event"] == "probe", 1.5) is None, "the stream polls the database quickly"
        seen = stream.wait(lambda e: e["event"] == "probe", SAFETY_POLL_S + 5)
        assert seen is not None, "the safety poll did not pick up the event"
        # A wake-up on the job's channel makes the stream read at once.
        add_event_row(service, j["id"], "probe2")
        t1 = time.monotonic()
        redis.Redis.from_url(service.redis.url).publish(lifecycle.channel(j["id"]), "1")
        woken = stream.wait(lambda e: e["event"] == "probe2", 5)
        assert woken is not None and woken - t1 < 0.5, "a wake-up did not make the stream read"
        # Through the lifecycle (cancel): the event is streamed well under a second after its commit.
        r = c.post(f"/v1/jobs/{j['id']}/cancel")
        t2 = time.monotonic()
        assert r.status_code == 200, r.text
        got = stream.wait(lambda e: e["event"] == "state" and e["state"] == "canceled", 5)
        assert got is not None and got - t2 < 0.5, f"the canceled event came {got and got - t2} s after the commit"
        assert stream.wait(lambda e: e["event"] == "end", 5) is not None
        stream.thread.join(5)
    print(f"safety poll after {seen - t0:.2f} s; wake-up {woken - t1:.3f} s; commit to stream {got - t2:.3f} s")


def pool_parent(worker: str) -> int:
    """The parent pid of a stage run's worker ("host:pid", a prefork pool process): its Celery worker."""
    with open(f"/proc/{worker.rsplit(':', 1)[1]}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[1])


def test_gpu_queue_job_runs_its_cpu_stages_on_the_cpu_worker(service: Service) -> None:
    cpu, gpu = service.start_worker("cpu"), service.start_worker("gpu")
    try:
        with service.client() as c:
            cap = upload(c, capture_zip()).json()
            j = submit(c, cap["id"], queue="gpu")
            assert j["queue"] == "gpu"
            done = wait_state(c, j["id"], ("completed", "failed"), 240, service)
            assert done["state"] == "completed", done["error"]
            runs = {r["stage"]: r["worker"] for r in job(c, j["id"])["stage_runs"]}
        assert set(runs) == set(STAGES)
        assert {pool_parent(runs[s]) for s in CPU_STAGES} == {cpu.proc.pid if cpu.proc else -1}, runs
        assert {pool_parent(runs[s]) for s in ("lmrm", "tto")} == {gpu.proc.pid if gpu.proc else -1}, runs
    finally:
        for w in (cpu, gpu):
            w.stop()
