"""The job service under load, on this machine (services.cluster: real redis-server, uvicorn API, Celery workers),
driven by load generators in their own processes, each figure printed next to its reference and next to what
limits it (CPU seconds per second of the API's processes, of the generator and of everything else on the machine,
from /proc).

1. status: `wrk` (closed loop: each of `--connections` keep-alive connections sends its next request when the last
   answer came; 1 thread, so it takes one core at most) against GET /v1/jobs/{id} (Authorization header; the fast
   path, services/fastpath.py) and against GET /healthz (no auth, no database: the framework alone) in the same run:
   requests/s, p50/p99, the ratio of the two, and one connection alone. A closed loop reads latency at saturation
   (mean latency = connections / throughput), so both are also read at a fixed offered rate `--rate` over the same
   connections: wrk pacing each connection with exponential waits (Poisson arrivals), and `hey` (1 CPU) whose
   connections each tick at rate/connections in step (bursts of `--connections` requests: a harsher pattern).
2. upload: a capture zip padded to `--upload-mb` MB (the example capture plus a stored, incompressible notes.txt)
   POSTed raw with curl to /v1/captures (local storage), as MB/s and as a ratio to writing the same bytes to the
   same filesystem in the same run (1 MiB writes; without and with a final fsync), best of `--repeats` each; the
   server's Server-Timing header says where the time went.
3. jobs: jobs/hour with 1 and then 2 workers on `--preset` (cpu; each worker one torch thread, so 2 workers use
   both cores): `--jobs` jobs submitted at once, from the first submit to the last completion; worker CPU use and
   the jobs' own stage timings.

    .venv/bin/python bench/service.py --only status,upload   # ~1 min
    .venv/bin/python bench/service.py --only jobs             # cpu preset, 4 + 4 jobs of minutes each: ~30-45 min
    .venv/bin/python bench/service.py --quick                 # short runs, 64 MB upload, 2 tiny jobs

Needs wrk, hey and curl (apt; `make sysdeps`). Appends one JSON line to bench/results/service.jsonl.
"""

from __future__ import annotations

import argparse
import functools
import io
import json
import mmap
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import _busy_cpu_seconds, argument_parser, write_result  # noqa: E402

from services.cluster import FAST, REPO, Cluster, wait_for  # noqa: E402

KEY = "nmx_bench_0123456789abcdefghijklmnop"
AUTH = f"Authorization: Bearer {KEY}"
EXAMPLE = REPO / "examples" / "teapot"
CPUS = os.cpu_count() or 1


# -- measuring ---------------------------------------------------------------------------------------------------
def session_cpu_s(sid: int) -> float:
    """CPU seconds (user + system, with those of exited children) of every process in session `sid` (services.cluster
    starts each process in its own session: the API with its workers, a Celery worker with its pool)."""
    total = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # the process ended meanwhile
        if int(fields[3]) == sid:
            total += sum(int(x) for x in fields[11:15])  # utime stime cutime cstime
    return total / os.sysconf("SC_CLK_TCK")


def children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


class CpuMeter:
    """Cores used (CPU seconds per wall second) during a `with` block by the processes of the given sessions, by this
    process's waited-for children (the load generator) and by everything else on the machine."""

    def __init__(self, sessions: dict[str, int], generator: bool = True):
        self.sessions, self.generator = sessions, generator
        self.cores: dict[str, float] = {}

    def __enter__(self) -> CpuMeter:
        self.t0, self.busy0, self.gen0 = time.perf_counter(), _busy_cpu_seconds() or 0.0, children_cpu_s()
        self.own0 = sum(os.times()[:2])
        self.s0 = {k: session_cpu_s(v) for k, v in self.sessions.items()}
        return self

    def __exit__(self, *_: Any) -> None:
        wall = time.perf_counter() - self.t0
        used = {k: session_cpu_s(v) - self.s0[k] for k, v in self.sessions.items()}
        if self.generator:
            used["load generator"] = children_cpu_s() - self.gen0
        used["bench script"] = sum(os.times()[:2]) - self.own0
        busy = (_busy_cpu_seconds() or 0.0) - self.busy0
        used["everything else"] = max(0.0, busy - sum(used.values()))
        self.cores = {k: round(v / wall, 2) for k, v in used.items()}
        self.cores["machine busy"] = round(busy / wall, 2)

    def text(self) -> str:
        return ", ".join(f"{k} {v:.2f}" for k, v in self.cores.items()) + f" cores (of {CPUS})"


def load_now() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} ({CPUS} CPUs)"


def seconds_of(text: str) -> float:
    """wrk's durations: '512.00us', '16.39ms', '1.20s', '1.00m'."""
    m = re.fullmatch(r"([0-9.]+)(us|ms|s|m)", text)
    if m is None:
        raise ValueError(f"not a wrk duration: {text!r}")
    return float(m.group(1)) * {"us": 1e-6, "ms": 1e-3, "s": 1.0, "m": 60.0}[m.group(2)]


def need(tool: str) -> str:
    exe = shutil.which(tool)
    if exe is None:
        raise SystemExit(f"{tool} not found: `make sysdeps` installs it (apt-get install -y {tool})")
    return exe


# wrk's delay() hook (docs: wrk's SCRIPTING): each connection waits an exponential time before each request, so the
# arrivals of all connections together are close to a Poisson process at `rate` (open loop while answers are much
# faster than connections / rate); wrk times each request from its sending, so the wait is not counted.
POISSON_LUA = """
local mean_ms
function init(args)
  mean_ms = tonumber(args[1])
  math.randomseed(os.time())
end
function delay()
  return -math.log(1 - math.random()) * mean_ms + 0.5
end
"""


def wrk(url: str, connections: int, seconds: float, headers: tuple[str, ...] = (),
        rate: float | None = None, folder: Path | None = None) -> dict[str, Any]:
    """wrk -t1 (one thread: one core at most) with `connections` keep-alive connections for `seconds`: closed loop,
    or with `rate` (requests/s over all connections) Poisson arrivals paced by POISSON_LUA (written to `folder`)."""
    cmd = [need("wrk"), "-t1", f"-c{connections}", f"-d{max(1, round(seconds))}s", "--latency", "--timeout", "10s"]
    for h in headers:
        cmd += ["-H", h]
    if rate is not None:
        assert folder is not None
        script = folder / "bench-poisson.lua"
        script.write_text(POISSON_LUA)
        cmd += ["-s", str(script)]
    cmd.append(url)
    if rate is not None:
        cmd += ["--", f"{1e3 * connections / rate:g}"]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    pct = {p: seconds_of(v) for p, v in re.findall(r"^\s+(50|75|90|99)%\s+(\S+)$", out, re.M)}
    sock = re.search(r"Socket errors: connect (\d+), read (\d+), write (\d+), timeout (\d+)", out)
    non2xx = re.search(r"Non-2xx or 3xx responses: (\d+)", out)
    done = re.search(r"(\d+) requests in", out)
    rps = re.search(r"Requests/sec:\s+([0-9.]+)", out)
    if rps is None or "50" not in pct or done is None:
        raise RuntimeError(f"unexpected wrk output:\n{out}")
    return {"generator": "wrk -t1 " + ("(closed loop)" if rate is None else f"(Poisson arrivals, {rate:g}/s offered)"),
            "offered_per_s": rate, "connections": connections, "requests": int(done.group(1)),
            "requests_per_s": float(rps.group(1)), "p50_ms": 1e3 * pct["50"], "p90_ms": 1e3 * pct["90"],
            "p99_ms": 1e3 * pct["99"], "non_2xx": int(non2xx.group(1)) if non2xx else 0,
            "socket_errors": sum(int(x) for x in sock.groups()) if sock else 0}  # fmt: skip


def hey(url: str, connections: int, rate: float, seconds: float, headers: tuple[str, ...] = ()) -> dict[str, Any]:
    """hey at a fixed offered rate: `connections` workers each paced to rate/connections requests/s, 1 CPU. A late
    answer delays that worker's next request, so the achieved rate falls below the offered one when the server
    cannot keep up (read it next to the latency)."""
    cmd = [need("hey"), "-z", f"{max(1, round(seconds))}s", "-c", str(connections), "-q", f"{rate / connections:g}",
           "-cpus", "1", "-t", "10"]  # fmt: skip
    for h in headers:
        cmd += ["-H", h]
    out = subprocess.run([*cmd, url], capture_output=True, text=True, check=True).stdout
    pct = {p: float(v) for p, v in re.findall(r"^\s+(50|90|99)% in ([0-9.]+) secs", out, re.M)}
    codes = {int(c): int(n) for c, n in re.findall(r"\[(\d+)\]\s+(\d+) responses", out)}
    rps = re.search(r"Requests/sec:\s+([0-9.]+)", out)
    if rps is None or "99" not in pct:
        raise RuntimeError(f"unexpected hey output:\n{out}")
    errors = re.search(r"Error distribution:(.*)", out, re.S)
    return {"generator": "hey -cpus 1 (fixed rate per connection)", "connections": connections,
            "offered_per_s": rate, "requests": sum(codes.values()), "requests_per_s": float(rps.group(1)),
            "p50_ms": 1e3 * pct["50"], "p90_ms": 1e3 * pct["90"], "p99_ms": 1e3 * pct["99"],
            "non_2xx": sum(n for c, n in codes.items() if not 200 <= c < 300),
            "errors": errors.group(1).strip()[:500] if errors else ""}  # fmt: skip


def measured(sessions: dict[str, int], run: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    with CpuMeter(sessions) as meter:
        res = run()
    res["cores"] = meter.cores
    return res


def limit_of(cores: dict[str, float], process: str) -> str:
    """What held a run back, in words, from the cores used: one Python process (the API's event loop runs on one
    core), the machine's CPUs, or neither (then the client or the wait itself)."""
    mine = cores.get(process, 0.0)
    if mine >= 0.85:
        return f"the {process} process is CPU-bound ({mine:.2f} cores: one Python event loop)"
    if cores.get("machine busy", 0.0) >= 0.9 * CPUS:
        return f"the machine's {CPUS} CPUs are saturated ({', '.join(f'{k} {v:.2f}' for k, v in cores.items())})"
    return f"not CPU ({process} {mine:.2f} cores, machine {cores.get('machine busy', 0.0):.2f} of {CPUS})"


# -- the sections ---------------------------------------------------------------------------------------------------
def capture_zip(pad_to: int = 0) -> bytes:
    """The example capture (without photos/ and gbuffers/) as a zip, padded to `pad_to` bytes with a stored
    (uncompressed) file of random bytes."""
    def build(pad: int) -> bytes:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
            for p in sorted(EXAMPLE.rglob("*")):
                rel = p.relative_to(EXAMPLE).as_posix()
                if p.is_file() and rel.split("/")[0] not in ("photos", "gbuffers"):
                    z.write(p, "teapot/" + rel)
            if pad:
                z.writestr(zipfile.ZipInfo("teapot/notes.txt"), os.urandom(pad), compress_type=zipfile.ZIP_STORED)
        return buf.getvalue()

    small = build(0)
    if pad_to <= len(small):
        return small
    overhead = len(build(1)) - len(small) - 1  # the padding file's headers
    return build(pad_to - len(small) - overhead)


def status(cluster: Cluster, job_id: str, args: argparse.Namespace) -> dict[str, Any]:
    assert cluster.api is not None and cluster.api.proc is not None
    api = {"API": cluster.api.proc.pid}
    # the API's own port: the fast path's speed (services/fastpath.py); the proxy's port is measured after
    job_url, health_url = f"{cluster.api_url}/v1/jobs/{job_id}", f"{cluster.api_url}/healthz"
    n, secs = args.connections, args.seconds
    out: dict[str, Any] = {"load_before": os.getloadavg()}
    wrk(job_url, n, 1, (AUTH,))  # warm-up: connections, caches
    out["job"] = measured(api, lambda: wrk(job_url, n, secs, (AUTH,)))
    out["healthz"] = measured(api, lambda: wrk(health_url, n, secs))
    out["job_one_connection"] = wrk(job_url, 1, min(secs, 3), (AUTH,))
    out["healthz_one_connection"] = wrk(health_url, 1, min(secs, 3))
    out["ratio_to_healthz"] = out["job"]["requests_per_s"] / out["healthz"]["requests_per_s"]
    folder = cluster.root
    out["job_poisson"] = measured(api, lambda: wrk(job_url, n, secs, (AUTH,), args.rate, folder))
    out["healthz_poisson"] = measured(api, lambda: wrk(health_url, n, secs, (), args.rate, folder))
    if shutil.which("hey"):
        out["job_fixed_rate"] = measured(api, lambda: hey(job_url, n, args.rate, secs, (AUTH,)))
        out["healthz_fixed_rate"] = measured(api, lambda: hey(health_url, n, args.rate, secs))
    else:
        print("status: hey not found (apt-get install -y hey): no fixed-rate run")
    if cluster.proxy is not None and cluster.proxy.proc is not None:  # what clients see behind nginx
        via, both = f"{cluster.url}/v1/jobs/{job_id}", {**api, "proxy": cluster.proxy.proc.pid}
        wrk(via, n, 1, (AUTH,))
        out["job_via_proxy"] = measured(both, lambda: wrk(via, n, secs, (AUTH,)))
        out["job_poisson_via_proxy"] = measured(both, lambda: wrk(via, n, secs, (AUTH,), args.rate, folder))
    out["load_after"] = os.getloadavg()

    print(f"status: {load_now()}; wrk -t1 (one thread, one core at most), {n} connections, {secs:.0f} s each")
    for name, key in (("GET /v1/jobs/{id}", "job"), ("GET /healthz", "healthz")):
        r = out[key]
        print(f"  {name:18s} closed loop: {r['requests_per_s']:7.0f} req/s, p50 {r['p50_ms']:6.1f} ms, p99 "
              f"{r['p99_ms']:6.1f} ms (non-2xx {r['non_2xx']}, socket errors {r['socket_errors']}); "
              f"{limit_of(r['cores'], 'API')}; cores: {', '.join(f'{k} {v:.2f}' for k, v in r['cores'].items())}")
        one = out[f"{key}_one_connection"]
        print(f"  {name:18s} one connection: {one['requests_per_s']:7.0f} req/s, p50 {one['p50_ms']:.2f} ms")
    print(f"  status / healthz requests/s: {out['ratio_to_healthz']:.2f}  (target: GET /v1/jobs/{{id}} >= 1,000 "
          f"req/s with p99 <= 50 ms at 100 connections; closed loop, mean latency = {n} / throughput)")
    if "job_via_proxy" in out:
        r = out["job_via_proxy"]
        print(f"  GET /v1/jobs/{{id}}  closed loop through the proxy (nginx): {r['requests_per_s']:.0f} req/s, p50 "
              f"{r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms (non-2xx {r['non_2xx']}); cores: "
              f"{', '.join(f'{k} {v:.2f}' for k, v in r['cores'].items())}")
    for name, key in (("GET /v1/jobs/{id}", "job_poisson"), ("GET /healthz", "healthz_poisson"),
                      ("GET /v1/jobs/{id}", "job_fixed_rate"), ("GET /healthz", "healthz_fixed_rate"),
                      ("GET /v1/jobs/{id}", "job_poisson_via_proxy")):  # fmt: skip
        if key in out:
            r = out[key]
            how = "Poisson arrivals (wrk)" if "poisson" in key else "fixed rate per connection (hey, ticks in step)"
            how += " through the proxy" if key.endswith("via_proxy") else ""
            print(f"  {name:18s} {r['offered_per_s']:.0f}/s offered, {how}: {r['requests_per_s']:.0f} "
                  f"req/s, p50 {r['p50_ms']:.1f} ms, p90 {r['p90_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms "
                  f"(non-2xx {r['non_2xx']}); cores: {', '.join(f'{k} {v:.2f}' for k, v in r['cores'].items())}")
    return out


def seconds_list(runs: list[dict[str, Any]]) -> str:
    return ", ".join(f"{r['seconds']:.2f}" for r in runs)


def disk_write_seconds(folder: Path, data: bytes) -> float:
    """Seconds to write `data` to a new file in `folder` in 1 MiB writes (as servers stream) and fsync it: the
    same work a durable upload does (a new file's pages, then the disk). The file is removed afterwards."""
    path = folder / f"bench-disk-reference-{time.monotonic_ns()}.bin"
    t0 = time.perf_counter()
    with open(path, "wb") as f:
        view = memoryview(data)
        for i in range(0, len(data), 1 << 20):
            f.write(view[i:i + (1 << 20)])
        f.flush()
        os.fsync(f.fileno())
    seconds = time.perf_counter() - t0
    path.unlink()
    return seconds


def direct_write_seconds(folder: Path, data: bytes) -> tuple[float, int]:
    """(seconds, bytes) to write `data` (whole MiBs of it) to a new file with O_DIRECT in 1 MiB writes: the raw
    disk, what `dd oflag=direct bs=1M` measures, without the page cache (whose speed on a VM depends on whether the
    host backs the pages already, see bench/README.md)."""
    path = folder / f"bench-disk-direct-{time.monotonic_ns()}.bin"
    block = 1 << 20
    n = len(data) // block * block
    buf = mmap.mmap(-1, block)  # page-aligned, as O_DIRECT needs
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_DIRECT, 0o644)
    try:
        t0 = time.perf_counter()
        for i in range(0, n, block):
            buf[:] = data[i:i + block]
            os.write(fd, buf)
        os.fsync(fd)
        seconds = time.perf_counter() - t0
    finally:
        os.close(fd)
        buf.close()
        path.unlink()
    return seconds, n


# The product's own client uploading a capture folder (neumatex_client: an upload session, files larger than its
# chunk as raw PUTs, the rest in forms, then the commit), timed inside its own process.
CLIENT_UPLOAD = """
import json, sys, time
from neumatex_client.client import Client
client = Client(sys.argv[1], sys.argv[2])
t0 = time.perf_counter()
cap = client.upload_capture(sys.argv[3])
print(json.dumps({"seconds": time.perf_counter() - t0, "capture_id": cap.id, "bytes": cap.bytes}))
"""


def upload(cluster: Cluster, args: argparse.Namespace) -> dict[str, Any]:
    """Three measurements interleaved `--repeats` times, each on fresh files (see the module's docstring): the
    disk reference, the zip POSTed by curl, the capture folder uploaded by the client; each capture is deleted
    after it is measured."""
    assert cluster.api is not None and cluster.api.proc is not None
    body = capture_zip(int(args.upload_mb * 1e6))
    folder = cluster.storage.parent  # the same filesystem as the storage folder
    src, tree = folder / "bench-capture.zip", folder / "bench-capture"
    src.write_bytes(body)
    with zipfile.ZipFile(src) as z:
        z.extractall(tree)
    pids = {"API": cluster.api.proc.pid}
    if cluster.proxy is not None and cluster.proxy.proc is not None:
        pids["proxy"] = cluster.proxy.proc.pid
    headers_file = folder / "bench-upload-headers.txt"
    curl = [need("curl"), "-sS", "-o", str(folder / "bench-upload-response.json"), "-D", str(headers_file),
            "-w", "%{http_code} %{time_total}", "-H", AUTH, "-H", "Content-Type: application/zip", "-H", "Expect:",
            "--data-binary", f"@{src}", f"{cluster.url}/v1/captures?name=bench-upload"]  # fmt: skip

    def zip_run() -> dict[str, Any]:
        code, total = subprocess.run(curl, capture_output=True, text=True, check=True).stdout.split()
        if int(code) != 201:
            raise SystemExit(f"upload failed: {code} {(folder / 'bench-upload-response.json').read_text()}")
        timing = next((line.split(":", 1)[1] for line in headers_file.read_text().splitlines()
                       if line.lower().startswith("server-timing:")), "")  # fmt: skip
        server = {k.strip(): float(v) / 1e3 for k, _, v in (x.partition(";dur=") for x in timing.split(",")
                                                            if x.strip())}  # fmt: skip
        cap = json.loads((folder / "bench-upload-response.json").read_text())
        return {"seconds": float(total), "server_seconds": server, "capture_id": cap["id"]}

    def folder_run() -> dict[str, Any]:
        cmd = [sys.executable, "-c", CLIENT_UPLOAD, cluster.url, KEY, str(tree / "teapot")]
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
        if out.returncode != 0:
            raise SystemExit(f"the client's upload failed:\n{out.stderr[-2000:]}")
        return dict(json.loads(out.stdout.strip().splitlines()[-1]))

    runs: dict[str, list[dict[str, Any]]] = {"raw": [], "disk": [], "zip": [], "folder": []}
    with httpx.Client(base_url=cluster.api_url, headers={"Authorization": f"Bearer {KEY}"}, timeout=600) as api:
        for _ in range(args.repeats):
            seconds, n = direct_write_seconds(folder, body)
            runs["raw"].append({"seconds": seconds * len(body) / n})  # as if all of `body` had been written
            runs["disk"].append({"seconds": disk_write_seconds(folder, body)})
            for name, run in (("zip", zip_run), ("folder", folder_run)):
                runs[name].append(measured(pids, run))
                assert api.delete(f"/v1/captures/{runs[name][-1]['capture_id']}").status_code == 200
    shutil.rmtree(tree)
    src.unlink()
    mb = len(body) / 1e6
    raw = mb / min(r["seconds"] for r in runs["raw"])  # the best of the repeats, as for the uploads
    disk = mb / min(r["seconds"] for r in runs["disk"])
    res: dict[str, Any] = {"bytes": len(body), "front": "nginx (deploy/nginx/)" if "proxy" in pids else "the API",
                           "disk_raw_mb_per_s": raw, "disk_raw_seconds": [r["seconds"] for r in runs["raw"]],
                           "disk_write_fsync_mb_per_s": disk, "disk_seconds": [r["seconds"] for r in runs["disk"]],
                           "load": os.getloadavg()}  # fmt: skip
    print(f"upload: {load_now()}; {mb:.0f} MB capture to {res['front']} (local storage, durable: fsynced before 201)")
    print(f"  raw disk write: {raw:.0f} MB/s (O_DIRECT, 1 MiB writes, a new file; best of "
          f"{seconds_list(runs['raw'])} s); through the page cache + fsync: {disk:.0f} MB/s (best of "
          f"{seconds_list(runs['disk'])} s)")
    for name, what in (("zip", "zip POSTed by curl to /v1/captures"),
                       ("folder", "folder uploaded by neumatex_client (session: PUT large files, forms, commit)")):
        best = min(runs[name], key=lambda r: float(r["seconds"]))
        mb_s = mb / best["seconds"]
        res[name] = {**best, "mb_per_s": mb_s, "ratio_to_disk_raw": mb_s / raw, "ratio_to_disk_fsync": mb_s / disk,
                     "all_seconds": [r["seconds"] for r in runs[name]]}  # fmt: skip
        print(f"  {what}: {mb_s:.0f} MB/s ({best['seconds']:.2f} s; all {seconds_list(runs[name])} s): ratio to "
              f"the raw disk {mb_s / raw:.2f} (target >= 0.5), to the page cache + fsync {mb_s / disk:.2f}")
        server = best.get("server_seconds", {})
        if server:
            print("    server time: " + ", ".join(f"{k} {v:.2f} s" for k, v in server.items()))
        print(f"    {limit_of(best['cores'], 'API')}; cores: "
              + ", ".join(f"{k} {v:.2f}" for k, v in best["cores"].items()))
    return res


def all_completed(client: httpx.Client, ids: list[str]) -> bool:
    """Whether every job completed (SystemExit when one failed or was canceled)."""
    states = [client.get(f"/v1/jobs/{i}").json() for i in ids]
    bad = [j for j in states if j["state"] in ("failed", "canceled")]
    if bad:
        raise SystemExit(f"a benchmark job ended {bad[0]['state']}: {bad[0]['error']}")
    return all(j["state"] == "completed" for j in states)


def jobs(cluster: Cluster, client: httpx.Client, capture_id: str, args: argparse.Namespace) -> dict[str, Any]:
    body = {"capture_id": capture_id, "preset": args.preset, "config": json.loads(args.config)}
    out: dict[str, Any] = {"preset": args.preset, "config": body["config"]}
    for n_workers in (1, 2):
        while len(cluster.workers) < n_workers:
            cluster.start_worker()
        time.sleep(3.0)  # the new worker's presence row (the API routes nothing by it, but waiting notes do)
        sessions = {f"worker {i + 1}": w.proc.pid for i, w in enumerate(cluster.workers) if w.proc is not None}
        with CpuMeter(sessions, generator=False) as meter:
            t0 = time.perf_counter()
            ids = []
            for _ in range(args.jobs):
                r = client.post("/v1/jobs", json=body)
                if r.status_code != 201:
                    raise SystemExit(f"job submission failed: {r.status_code} {r.text}")
                ids.append(r.json()["id"])
            wait_for(functools.partial(all_completed, client, ids), 4 * 3600, f"{args.jobs} jobs", every=0.5)
            wall = time.perf_counter() - t0
        finished = [client.get(f"/v1/jobs/{i}").json() for i in ids]
        stage_s = {st: sum(float(j["timings"].get(st, 0.0)) for j in finished) / len(finished)
                   for st in finished[0]["timings"]}  # fmt: skip
        res = {"workers": n_workers, "jobs": args.jobs, "seconds": wall, "jobs_per_hour": 3600 * args.jobs / wall,
               "mean_stage_seconds": stage_s, "cores": meter.cores, "load": os.getloadavg()}  # fmt: skip
        out[f"workers_{n_workers}"] = res
        print(f"jobs: {load_now()}; {n_workers} worker(s): {args.jobs} {args.preset} jobs in {wall:.1f} s = "
              f"{res['jobs_per_hour']:.1f} jobs/hour; mean stage seconds "
              f"{', '.join(f'{k} {v:.1f}' for k, v in stage_s.items())}")
        between = wall * n_workers / args.jobs - sum(stage_s.values())
        res["seconds_per_job_outside_stages"] = between
        print(f"  cores: {meter.text()}; per job {sum(stage_s.values()):.1f} s in stages and about {between:.1f} s "
              "outside them (queue wait for a free worker excluded: dispatch, claims, startup)")
    out["speedup_2_over_1"] = out["workers_2"]["jobs_per_hour"] / out["workers_1"]["jobs_per_hour"]
    c2 = out["workers_2"]["cores"]
    workers2 = sum(v for k, v in c2.items() if k.startswith("worker"))
    print(f"jobs: 2 workers / 1 worker = {out['speedup_2_over_1']:.2f}x (target >= 1.8x); with 2 workers they used "
          f"{workers2:.2f} of {CPUS} cores, everything else {c2['everything else']:.2f}"
          + (" (the CPUs were shared: a quiet machine is needed for the target)"
             if c2["everything else"] > 0.2 else ""))  # fmt: skip
    return out


def main() -> None:
    ap = argument_parser(__doc__)
    ap.add_argument("--only", default="status,upload,jobs", help="comma-separated subset of status,upload,jobs")
    ap.add_argument("--connections", type=int, default=100)
    ap.add_argument("--seconds", type=float, default=10.0, help="per status run")
    ap.add_argument("--rate", type=float, default=1000.0, help="offered requests/s of the fixed-rate status runs")
    ap.add_argument("--upload-mb", type=float, default=256.0)
    ap.add_argument("--repeats", type=int, default=3, help="uploads and disk writes each; the best is reported")
    ap.add_argument("--jobs", type=int, default=4, help="jobs per measurement (1 worker, then 2)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--config", default='{"device": "cpu"}', help="the jobs' config overrides (JSON)")
    ap.add_argument("--quick", action="store_true", help="4 s status runs, a 64 MB upload, 2 tiny jobs")
    ap.add_argument("--no-proxy", dest="proxy", action="store_false",
                    help="talk to the API directly instead of through nginx (deploy/nginx/, services/proxy.py)")
    ap.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                    help="extra environment of the service's processes, e.g. UVICORN_WORKERS=2 (repeatable)")
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.upload_mb, args.jobs, args.preset = 4.0, 64.0, 2, "tiny"
        args.config = '{"init": "random", "device": "cpu"}'
    parts = [p.strip() for p in args.only.split(",") if p.strip()]
    unknown = set(parts) - {"status", "upload", "jobs"}
    if unknown:
        raise SystemExit(f"--only: unknown section(s) {sorted(unknown)}; choose from status, upload, jobs")
    root = Path(tempfile.mkdtemp(prefix="neumatex-bench-service-"))
    extra = dict(kv.split("=", 1) for kv in args.env)
    cluster = Cluster(root, {**FAST, "NEUMATEX_MAX_UPLOAD_BYTES": str(2 * 1024**3),
                             "NEUMATEX_MAX_CAPTURE_BYTES": str(2 * 1024**3), **extra}, proxy=args.proxy)  # fmt: skip
    record: dict[str, Any] = {"load_at_start": os.getloadavg()}
    try:
        cluster.redis.start()
        cluster.add_tenant("bench", KEY)
        cluster.start_api()
        with httpx.Client(base_url=cluster.url, headers={"Authorization": f"Bearer {KEY}"}, timeout=600) as client:
            r = client.post("/v1/captures", content=capture_zip(), headers={"Content-Type": "application/zip"})
            assert r.status_code == 201, r.text
            cap = r.json()
            if "status" in parts:
                # a job on the gpu queue, which no worker here takes: it stays queued (its record keeps its size)
                r = client.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "tiny", "queue": "gpu",
                                                  "config": {"init": "random", "device": "cpu"}})  # fmt: skip
                assert r.status_code == 201, r.text
                record["status"] = status(cluster, r.json()["id"], args)
                client.post(f"/v1/jobs/{r.json()['id']}/cancel")
            if "upload" in parts:
                record["upload"] = upload(cluster, args)
            if "jobs" in parts:
                record["jobs"] = jobs(cluster, client, cap["id"], args)
    finally:
        cluster.stop()
        shutil.rmtree(root, ignore_errors=True)
    record["args"] = vars(args)
    print(f"appended to {write_result('service', record)}")


if __name__ == "__main__":
    main()
