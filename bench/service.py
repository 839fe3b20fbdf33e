"""The job service under load, on this machine (services.cluster: real redis-server, uvicorn API, Celery workers).

1. Status requests: `--clients` concurrent clients (default 100) GET /v1/jobs/{id} for `--seconds`; requests/s and
   p50/p99 latency, and as a ratio to GET /healthz (no auth, no database: the framework and the clients alone) in
   the same run, plus the p50 of one client alone. The clients run in this process on the same CPUs as the API
   (one uvicorn process).
2. Upload: a capture zip padded to `--upload-mb` MB (a stored, incompressible notes.txt) POSTed to /v1/captures
   (streamed to storage, unpacked safely, validated, committed), as MB/s and as a ratio to writing the same bytes
   to the same disk (1 MiB writes, no fsync, like the server) in the same run (ratio < 1: slower than the disk).
3. Jobs per hour on the tiny preset (random init) with 1 and then 2 workers: `--jobs` jobs submitted at once,
   from the first submit to the last completion.

    .venv/bin/python bench/service.py                 # ~5 min on a busy 2-core CPU
    .venv/bin/python bench/service.py --quick         # fewer jobs and a shorter status run
"""

from __future__ import annotations

import argparse
import asyncio
import io
import os
import statistics
import sys
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import write_result  # noqa: E402

from services.cluster import FAST, REPO, Cluster, wait_for  # noqa: E402

KEY = "nmx_bench_0123456789abcdefghijklmnop"
EXAMPLE = REPO / "examples" / "teapot"
TINY = {"preset": "tiny", "config": {"init": "random", "device": "cpu"}}


def capture_zip(pad_bytes: int = 0) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(EXAMPLE.rglob("*")):
            rel = p.relative_to(EXAMPLE).as_posix()
            if p.is_file() and rel.split("/")[0] not in ("photos", "gbuffers"):
                z.write(p, "teapot/" + rel)
        if pad_bytes:
            z.writestr(zipfile.ZipInfo("teapot/notes.txt"), os.urandom(pad_bytes), compress_type=zipfile.ZIP_STORED)
    return buf.getvalue()


def percentile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


async def status_load(url: str, path: str, clients: int, seconds: float) -> dict[str, Any]:
    latencies: list[float] = []
    errors = 0
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=url, headers={"Authorization": f"Bearer {KEY}"}, limits=limits,
                                 timeout=30) as client:  # fmt: skip
        end = time.perf_counter() + seconds

        async def one() -> None:
            nonlocal errors
            while time.perf_counter() < end:
                t0 = time.perf_counter()
                r = await client.get(path)
                latencies.append(time.perf_counter() - t0)
                errors += r.status_code != 200

        t0 = time.perf_counter()
        await asyncio.gather(*(one() for _ in range(clients)))
        wall = time.perf_counter() - t0
    return {"clients": clients, "requests": len(latencies), "errors": errors, "seconds": wall,
            "requests_per_s": len(latencies) / wall, "p50_ms": 1e3 * statistics.median(latencies),
            "p99_ms": 1e3 * percentile(latencies, 0.99)}  # fmt: skip


def sequential_p50_ms(client: httpx.Client, path: str, n: int = 300) -> float:
    """p50 latency of one client making `n` requests in a row (the server's own cost per request)."""
    lat = []
    for _ in range(n):
        t0 = time.perf_counter()
        client.get(path)
        lat.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(lat)


def disk_write_mb_s(data: bytes, folder: Path) -> float:
    target = folder / "reference.bin"
    t0 = time.perf_counter()
    with open(target, "wb") as f:
        for i in range(0, len(data), 1 << 20):
            f.write(data[i:i + (1 << 20)])
    seconds = time.perf_counter() - t0
    target.unlink()
    return len(data) / 1e6 / seconds


def jobs_per_hour(cluster: Cluster, client: httpx.Client, capture_id: str, n: int) -> dict[str, Any]:
    t0 = time.perf_counter()
    ids = [client.post("/v1/jobs", json={"capture_id": capture_id, **TINY}).json()["id"] for _ in range(n)]

    def all_done() -> bool:
        states = [client.get(f"/v1/jobs/{i}").json()["state"] for i in ids]
        if "failed" in states:
            raise SystemExit(f"a benchmark job failed: {[client.get(f'/v1/jobs/{i}').json()['error'] for i in ids]}")
        return all(s == "completed" for s in states)

    wait_for(all_done, 3600, f"{n} jobs", every=0.5)
    wall = time.perf_counter() - t0
    return {"jobs": n, "seconds": wall, "jobs_per_hour": 3600 * n / wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--upload-mb", type=float, default=64.0)
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--parts", default="status,upload,jobs", help="comma-separated subset of status,upload,jobs")
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.jobs, args.upload_mb = 5.0, 2, 32.0
    root = Path(tempfile.mkdtemp(prefix="neumatex-bench-service-"))
    cluster = Cluster(root, {**FAST, "NEUMATEX_MAX_UPLOAD_BYTES": str(2 * 1024**3)})
    record: dict[str, Any] = {}
    try:
        cluster.redis.start()
        cluster.add_tenant("bench", KEY)
        cluster.start_api()
        client = httpx.Client(base_url=cluster.url, headers={"Authorization": f"Bearer {KEY}"}, timeout=600)
        cap = client.post("/v1/captures", content=capture_zip(), headers={"Content-Type": "application/zip"}).json()
        job = client.post("/v1/jobs", json={"capture_id": cap["id"], **TINY}).json()  # stays queued: no worker yet
        parts = args.parts.split(",")
        if "status" in parts:
            status = asyncio.run(status_load(cluster.url, f"/v1/jobs/{job['id']}", args.clients, args.seconds))
            health = asyncio.run(status_load(cluster.url, "/healthz", args.clients, args.seconds))
            for name, res in (("GET /v1/jobs/{id}", status), ("GET /healthz (reference)", health)):
                print(f"{name}: {res['requests_per_s']:.0f} requests/s with {args.clients} clients, p50 "
                      f"{res['p50_ms']:.1f} ms, p99 {res['p99_ms']:.1f} ms ({res['errors']} errors)")
            for name, res, path in (("GET /v1/jobs/{id}", status, f"/v1/jobs/{job['id']}"),
                                    ("GET /healthz", health, "/healthz")):  # fmt: skip
                res["one_client_p50_ms"] = sequential_p50_ms(client, path)
                print(f"{name}: one client alone: p50 {res['one_client_p50_ms']:.2f} ms")
            status["ratio_to_healthz"] = status["requests_per_s"] / health["requests_per_s"]
            print(f"status / healthz requests/s: {status['ratio_to_healthz']:.2f}")
            record["status"], record["healthz"] = status, health
        client.post(f"/v1/jobs/{job['id']}/cancel")
        if "upload" in parts:
            record["upload"] = upload(client, cluster, args.upload_mb)
        if "jobs" in parts:
            record["jobs"] = jobs(cluster, client, cap["id"], args.jobs)
        client.close()
    finally:
        cluster.stop()
    record["args"] = vars(args)
    path = write_result("service", record)
    print(f"appended to {path}")


def upload(client: httpx.Client, cluster: Cluster, upload_mb: float) -> dict[str, Any]:
    body = capture_zip(int(upload_mb * 1e6))
    ref = disk_write_mb_s(body, cluster.storage)
    t0 = time.perf_counter()
    r = client.post("/v1/captures", content=body, headers={"Content-Type": "application/zip"})
    seconds = time.perf_counter() - t0
    assert r.status_code == 201, r.text
    mb_s = len(body) / 1e6 / seconds
    parts = {k: float(v) / 1e3 for k, _, v in (x.strip().partition(";dur=") for x in
                                               r.headers.get("server-timing", "").split(",") if x)}  # fmt: skip
    print("upload: server time " + ", ".join(f"{k} {v:.2f} s" for k, v in parts.items()))
    print(f"upload: {len(body) / 1e6:.0f} MB in {seconds:.2f} s = {mb_s:.0f} MB/s (incl. unpack + validation); "
          f"disk write {ref:.0f} MB/s; ratio {mb_s / ref:.3f}")
    return {"bytes": len(body), "seconds": seconds, "mb_per_s": mb_s, "disk_write_mb_per_s": ref,
            "ratio_to_disk": mb_s / ref, "server_seconds": parts}


def jobs(cluster: Cluster, client: httpx.Client, capture_id: str, n_jobs: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for n_workers in (1, 2):
        while len(cluster.workers) < n_workers:
            cluster.start_worker()
        time.sleep(2.0)
        res = jobs_per_hour(cluster, client, capture_id, n_jobs)
        res["workers"] = n_workers
        out[f"workers_{n_workers}"] = res
        print(f"jobs: {n_workers} worker(s): {res['jobs']} tiny jobs in {res['seconds']:.1f} s = "
              f"{res['jobs_per_hour']:.0f} jobs/hour")
    out["speedup_2_over_1"] = out["workers_2"]["jobs_per_hour"] / out["workers_1"]["jobs_per_hour"]
    print(f"jobs: 2 workers / 1 worker = {out['speedup_2_over_1']:.2f}x ({os.cpu_count()} CPUs)")
    return out


if __name__ == "__main__":
    main()
