"""One job through two worker processes that share no folder (docs/service.md, "Across machines"): S3 storage (a
real moto server), PostgreSQL (a real server), Redis; the API and beat on one data folder, each worker on its own
data and scratch folders, so everything a worker reads or writes passes through the bucket and the database.

The first worker is killed with SIGKILL in the middle of TTO. Beat's reaper re-queues the job; the second worker
downloads the finished stages and TTO's last stored checkpoint from the bucket, resumes and finishes. Nothing is
lost (the asset arrives, every stage's outputs are in the bucket) and nothing runs twice (each stage finishes once,
the early stages are not re-run, TTO resumes after step 1 rather than starting over).
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import pytest

from .helpers import KEY_A, Service, capture_zip, job, sse_events, submit, upload, wait_for, wait_state
from .postgres import Postgres
from .s3server import moto_server

STAGES = ("validate", "prepare_views", "lmrm", "tto", "export")
TTO_STEPS = 500  # long enough (about 4 s on the tiny preset; 200 took 2-3 s in 2026-12) that the kill lands mid-TTO


def own_folders(root: Path) -> dict[str, str]:
    """A worker's own data, temp and scratch folders (nothing shared with the API or the other worker)."""
    for sub in ("data", "tmp", "scratch"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    return {"NEUMATEX_DATA_DIR": str(root / "data"), "TMPDIR": str(root / "tmp"),
            "NEUMATEX_SCRATCH_DIR": str(root / "scratch")}  # fmt: skip


def files_under(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file()]


def test_one_job_two_workers_no_shared_folder_s3_postgres_kill9(postgres: Postgres,
                                                                 tmp_path_factory: pytest.TempPathFactory) -> None:
    root = tmp_path_factory.mktemp("distributed")
    with moto_server(root) as moto:
        bucket = moto.bucket()
        svc = Service(root / "api", postgres.create_database("distributed"))
        svc.env.update(moto.env(bucket))
        try:
            svc.redis.start()
            svc.add_tenant("a", KEY_A)
            svc.start_api()
            svc.start_beat()
            first = svc.start_worker(env=own_folders(root / "worker1"))
            with svc.client() as c:
                cap = upload(c, capture_zip()).json()
                j = submit(c, cap["id"], tto={"steps": TTO_STEPS, "checkpoint_every": 10})
                job_id = j["id"]
                tto_key = f"work/{job_id}/tto/checkpoint.pt"

                def mid_tto() -> bool:
                    now = job(c, job_id)
                    return (now["state"] == "running" and now["stage"] == "tto" and now["stage_fraction"] >= 0.2
                            and tto_key in moto.keys(bucket, f"work/{job_id}/tto/"))  # fmt: skip

                wait_for(mid_tto, 240, "TTO past 20% with its checkpoint stored in the bucket", every=0.1)
                first.kill9()
                second = svc.start_worker(env=own_folders(root / "worker2"))
                done = wait_state(c, job_id, ("completed", "failed"), 300, svc)
                assert done["state"] == "completed", done["error"]
                events = sse_events(svc, job_id)
                archive = c.get(f"/v1/jobs/{job_id}/asset.zip")
            second.stop()
        finally:
            svc.stop()
        keys = moto.keys(bucket)
        history = moto.client().get_object(Bucket=bucket, Key=f"work/{job_id}/tto/history.json")["Body"].read()

    # the asset arrived, from the bucket
    assert archive.status_code == 200
    with zipfile.ZipFile(io.BytesIO(archive.content)) as z:
        assert "manifest.json" in z.namelist() and z.testzip() is None
    for stage in STAGES:
        assert f"work/{job_id}/{stage}/done.json" in keys, stage
    assert f"assets/{job_id}/asset.zip" in keys

    # each stage finished exactly once; the early stages were not re-run; TTO was lost once, then finished
    runs: dict[str, list[dict[str, Any]]] = {s: [r for r in done["stage_runs"] if r["stage"] == s] for s in STAGES}
    assert all([r["status"] for r in runs[s]].count("finished") == 1 for s in STAGES), runs
    assert all(len(runs[s]) == 1 for s in STAGES[:3]), runs
    early = {r["worker"] for s in STAGES[:3] for r in runs[s]}
    assert len(early) == 1
    assert [r["status"] for r in runs["tto"]] == ["lost", "finished"], runs["tto"]
    assert runs["tto"][0]["worker"] in early and runs["tto"][1]["worker"] not in early
    assert runs["export"][0]["worker"] == runs["tto"][1]["worker"]
    assert done["attempt"] == 2
    requeued = [e for e in events if e["event"] == "requeued"]
    assert len(requeued) == 1 and requeued[0]["stage"] == "tto"

    # TTO resumed from the checkpoint the first worker stored, not from step 1; every step is in the history once
    resumed = [e["metrics"]["step"] for e in events if e["event"] == "progress" and e.get("attempt") == 2
               and e["stage"] == "tto" and "step" in e["metrics"]]  # fmt: skip
    assert resumed and resumed[0] > 10, resumed
    assert [int(r["step"]) for r in json.loads(history)] == list(range(1, TTO_STEPS + 1))

    # no folder was shared: nothing of the job on the API's local storage, and each worker's scratch is empty again
    assert not files_under(root / "api" / "data" / "storage") if (root / "api" / "data" / "storage").exists() else True
    for w in ("worker1", "worker2"):
        left = [p for p in files_under(root / w / "scratch") if job_id in str(p)]
        assert w == "worker1" or not left, left  # the killed worker's scratch may keep its last run's files
