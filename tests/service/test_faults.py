"""Surviving faults with real processes: kill -9 of the worker in the middle of TTO (re-queued by the reaper on
Celery beat, with the API stopped meanwhile so nothing else can do it), Redis restarted mid-job (and a job
submitted while it was down, sent later by the reaper), a stage message taken by a worker that never claimed it
(sent again by the reaper), the API restarted mid-job, and cancel during TTO followed by
a retry that resumes on the freed worker. Stage runs come from the job record; done.json times and the TTO history
from the stage outputs in storage."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import redis

from neumatex_core.pipeline import STAGES
from services.cluster import FAST

from .helpers import Service, capture_zip, job, sql, sse_events, submit, upload, wait_for, wait_state


@pytest.fixture(scope="module", autouse=True)
def beat(service: Service) -> Iterator[None]:
    """Celery beat: the reaper's schedule (re-queues jobs of vanished workers, sends undispatched ones)."""
    proc = service.start_beat()
    yield
    proc.stop()
    service.beat = None


def job_row(service: Service, job_id: str) -> tuple[str, int, str | None]:
    """(state, attempt, worker) straight from the database (while the API is down)."""
    state, attempt, worker = sql(service, "SELECT state, attempt, worker FROM jobs WHERE id = :id", id=job_id)[0]
    return str(state), int(attempt), worker


def work_dir(service: Service, job_id: str) -> Path:
    return service.root / "data" / "storage" / "work" / job_id


def done_times(service: Service, job_id: str) -> dict[str, int]:
    w = work_dir(service, job_id)
    return {s: (w / s / "done.json").stat().st_mtime_ns for s in STAGES if (w / s / "done.json").is_file()}


def runs_by_stage(j: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = {s: [] for s in STAGES}
    for r in j["stage_runs"]:
        out[r["stage"]].append(r)
    return out


def in_tto(c: Any, job_id: str, at_least: float) -> bool:
    j = job(c, job_id)
    return j["state"] == "running" and j["stage"] == "tto" and j["stage_fraction"] >= at_least


def wait_in_tto(c: Any, job_id: str, at_least: float, what: str) -> None:
    """Wait (180 s) until the job runs its TTO at `at_least` of its steps; a timeout names where the job is."""
    try:
        wait_for(lambda: in_tto(c, job_id, at_least), 180, what, every=0.1)
    except AssertionError as exc:
        j = job(c, job_id)
        where = {k: j.get(k) for k in ("state", "stage", "stage_fraction", "progress", "attempt", "worker", "error")}
        raise AssertionError(f"{exc}; the job now: {where}, timings {j.get('timings')}") from None


def events_of(service: Service, job_id: str) -> list[dict[str, Any]]:
    return sse_events(service, job_id, timeout=60)


def assert_each_stage_once(service: Service, j: dict[str, Any]) -> None:
    """Completed, every stage finished exactly once, TTO steps 1..N each once, the asset published."""
    assert j["state"] == "completed", j["error"]
    runs = runs_by_stage(j)
    assert all([r["status"] for r in runs[s]].count("finished") == 1 for s in STAGES), runs
    history = json.loads((work_dir(service, j["id"]) / "tto" / "history.json").read_text())
    steps = j["config"]["tto"].get("steps", 12)  # the tiny preset: 12
    assert [int(r["step"]) for r in history] == list(range(1, steps + 1))
    assert (service.root / "data" / "storage" / "assets" / j["id"] / "asset" / "manifest.json").is_file()


def test_kill9_worker_during_tto_another_worker_finishes(service: Service) -> None:
    first = service.start_worker()
    with service.client() as c:
        cap = upload(c, capture_zip()).json()
        # 1000 steps (about 6 s here): the poll must see the TTO running, past a checkpoint, before it ends
        j = submit(c, cap["id"], tto={"steps": 1000, "checkpoint_every": 4})
        wait_in_tto(c, j["id"], 1 / 4, "a quarter of the TTO")
        before = done_times(service, j["id"])
        assert set(before) == {"validate", "prepare_views", "lmrm"}
        first.kill9()
        killed_at = time.monotonic()
        assert service.api is not None
        service.api.stop()  # only beat's reaper can re-queue it now
        second = service.start_worker()
        try:
            wait_for(lambda: job_row(service, j["id"])[1] == 2, 120, "the reaper (on beat) to re-queue the job")
        except AssertionError:
            beat_log = service.beat.tail() if service.beat else ""
            print(f"--- beat.log\n{beat_log}\n--- {second.log.name}\n{second.tail()}")
            raise
        requeued_after = time.monotonic() - killed_at
        service.start_api()
    with service.client() as c:
        done = wait_state(c, j["id"], ("completed", "failed"), 240, service)
        assert_each_stage_once(service, done)
        runs = runs_by_stage(done)
        early = {r["worker"] for s in STAGES[:3] for r in runs[s]}
        assert len(early) == 1 and all(len(runs[s]) == 1 for s in STAGES[:3])  # not re-run
        assert [r["status"] for r in runs["tto"]] == ["lost", "finished"]
        assert runs["tto"][0]["worker"] in early and runs["tto"][1]["worker"] not in early
        assert {done_times(service, j["id"])[s] == t for s, t in before.items()} == {True}
        assert done["attempt"] == 2
        events = events_of(service, j["id"])
        requeued = [e for e in events if e["event"] == "requeued"]
        assert len(requeued) == 1 and requeued[0]["stage"] == "tto"
        resumed = [e["metrics"]["step"] for e in events if e["event"] == "progress" and e.get("attempt") == 2
                   and e["stage"] == "tto" and "step" in e["metrics"]]  # fmt: skip
        assert resumed and resumed[0] > 1  # from the checkpoint, not from step 1
        assert sum(1 for e in events if e["event"] == "state" and e["state"] == "completed") == 1
        print(f"re-queued {requeued_after:.1f} s and finished {time.monotonic() - killed_at:.1f} s after the kill")
    second.stop()


def test_redis_restarted_mid_job_no_job_lost(service: Service) -> None:
    worker = service.start_worker()
    with service.client() as c:
        cap = upload(c, capture_zip()).json()
        # 1000 steps (about 6 s here): 24 left a TTO window under a second that the poll missed now and then
        a = submit(c, cap["id"], tto={"steps": 1000})
        wait_in_tto(c, a["id"], 1 / 10, "TTO of job A")
        service.redis.stop()
        b = submit(c, cap["id"])  # accepted while the broker is down: the reaper sends it later
        assert b["state"] == "queued"
        time.sleep(1.0)
        service.redis.start()
        done_a = wait_state(c, a["id"], ("completed", "failed"), 240, service)
        done_b = wait_state(c, b["id"], ("completed", "failed"), 240, service)
    assert_each_stage_once(service, done_a)
    assert_each_stage_once(service, done_b)
    assert all(r["status"] == "finished" for r in done_a["stage_runs"] + done_b["stage_runs"])
    worker.stop()


def test_message_taken_but_never_claimed_is_sent_again_once_its_queue_is_empty(service: Service) -> None:
    """A worker that took a stage message and lost its broker connection before claiming the job leaves the message
    unacknowledged in Redis for the visibility timeout (8 h): the reaper sends it again once the job has waited
    redispatch_after_s unclaimed with its queue empty, and not while the message waits in the queue."""
    broker = redis.Redis.from_url(service.redis.url)
    broker.delete("cpu")  # stale messages of earlier tests' ended jobs (no worker runs now), so counts are this job's
    with service.client() as c:
        cap = upload(c, capture_zip()).json()
        j = submit(c, cap["id"])  # no worker yet: the validate message waits in the cpu queue
        wait_for(lambda: sql(service, "SELECT dispatched_at FROM jobs WHERE id = :id", id=j["id"])[0][0], 30,
                 "the job dispatched")  # fmt: skip
        assert broker.llen("cpu") == 1
        time.sleep(float(FAST["NEUMATEX_REDISPATCH_AFTER_S"]) + 2 * float(FAST["NEUMATEX_REAPER_EVERY_S"]))
        assert broker.llen("cpu") == 1, "a message still waiting in its queue was sent twice"
        assert broker.rpop("cpu") is not None  # taken by a worker that then lost its connection (kombu: BRPOP)
        worker = service.start_worker()
        try:
            done = wait_state(c, j["id"], ("completed", "failed"), 240, service)
        finally:
            worker.stop()
    assert_each_stage_once(service, done)
    assert done["attempt"] == 1


def test_api_restarted_mid_job_job_finishes(service: Service) -> None:
    worker = service.start_worker()
    with service.client() as c:
        cap = upload(c, capture_zip()).json()
        # 1000 steps (about 6 s here): 20 left a TTO window under a second that the poll missed now and then
        j = submit(c, cap["id"], tto={"steps": 1000})
        wait_in_tto(c, j["id"], 1 / 30, "TTO")
    service.restart_api()
    with service.client() as c:
        done = wait_state(c, j["id"], ("completed", "failed"), 240, service)
    assert_each_stage_once(service, done)
    assert all(r["status"] == "finished" for r in done["stage_runs"])
    progress = [e["progress"] for e in events_of(service, j["id"]) if "progress" in e]
    assert all(y >= x for x, y in zip(progress, progress[1:], strict=False)) and progress[-1] == 1.0
    worker.stop()


def test_cancel_during_tto_stops_within_seconds_and_retry_resumes(service: Service) -> None:
    worker = service.start_worker()
    with service.client() as c:
        cap = upload(c, capture_zip()).json()
        # 1000 steps (about 6 s here): the 25 steps left of a 30-step TTO (0.15 s) now and then ended between the
        # poll that saw step 5 and the pause below (the CI run of 2026-12-07), and the stage finished, not stopped.
        j = submit(c, cap["id"], tto={"steps": 1000, "checkpoint_every": 10})
        wait_in_tto(c, j["id"], 20 / 1000, "TTO step 20")
        # The worker is paused while the cancel lands, so the cancel comes between two TTO steps however fast this
        # machine runs them: unpaused, the TTO could end before its next poll saw the cancel.
        with worker.paused():
            t0 = time.monotonic()
            r = c.post(f"/v1/jobs/{j['id']}/cancel")
        assert r.status_code == 200 and r.json()["state"] == "canceled"

        def stopped() -> dict[str, Any] | None:
            return next((e for e in events_of(service, j["id"]) if e["event"] == "worker"), None)

        try:
            event = wait_for(stopped, 30, "the worker to stop", every=0.1)
        except AssertionError as exc:
            runs = [(r["stage"], r["status"]) for r in job(c, j["id"])["stage_runs"]]
            raise AssertionError(f"{exc}; the stage runs now: {runs}") from None
        waited = time.monotonic() - t0
        assert event["status"] == "stopped" and event["reason"] == "canceled" and event["stage"] == "tto"
        assert waited < 5.0, f"the worker took {waited:.1f} s to stop"
        canceled = job(c, j["id"])
        assert canceled["state"] == "canceled" and canceled["worker"] is None
        assert [r["status"] for r in runs_by_stage(canceled)["tto"]] == ["canceled"]
        assert (work_dir(service, j["id"]) / "tto" / "checkpoint.pt").is_file()
        assert not (work_dir(service, j["id"]) / "tto" / "done.json").exists()
        assert c.post(f"/v1/jobs/{j['id']}/cancel").status_code == 409
        # The freed worker takes the retry, which resumes the TTO from its checkpoint.
        before = done_times(service, j["id"])
        r = c.post(f"/v1/jobs/{j['id']}/retry")
        # queued, or already running: the freed worker may claim it before the route has read the job back
        assert r.status_code == 200 and r.json()["state"] in ("queued", "running") and r.json()["stage"] == "tto"
        done = wait_state(c, j["id"], ("completed", "failed"), 240, service)
        assert_each_stage_once(service, done)
        runs = runs_by_stage(done)
        assert [r["status"] for r in runs["tto"]] == ["canceled", "finished"]
        assert len({r["worker"] for r in done["stage_runs"]}) == 1  # the same (freed) worker process
        assert all(len(runs[s]) == 1 for s in STAGES[:3])
        assert {s: done_times(service, j["id"])[s] for s in before} == before
        resumed = [e["metrics"]["step"] for e in events_of(service, j["id"]) if e["event"] == "progress"
                   and e.get("attempt") == 2 and e["stage"] == "tto" and "step" in e["metrics"]]  # fmt: skip
        assert resumed and resumed[0] > 1
        print(f"worker stopped {waited:.2f} s after the cancel request")
    worker.stop()
