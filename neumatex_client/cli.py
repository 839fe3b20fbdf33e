"""`neumatex submit | status | jobs | job | cancel | retry | download` (also `python -m neumatex_client ...`): the job
service from a pipeline.

    neumatex submit CAPTURE... [--preset PRESET] [--config JSON|@file.json] [--queue QUEUE]
                    [--webhook URL] [--wait [--out DIR] [--timeout S]] [--url URL] [--api-key KEY]
    neumatex status [JOB...] [--json]
    neumatex jobs [--state STATE] [--limit N] [--json]
    neumatex job ID [--json]
    neumatex cancel ID... | retry ID [--from-stage STAGE] | download ID [--out DIR]

CAPTURE is a capture folder (with transforms.json), a capture .zip, or a folder of those (a batch). The URL comes
from --url, else $NEUMATEX_URL, else http://127.0.0.1:8000; the key from --api-key, else $NEUMATEX_API_KEY.

Exit codes (EXIT_*): 0 all went well (every job completed, with --wait); 1 a capture was refused or a job failed,
was canceled or did not end within --timeout (each named on stderr; the others still ran); 2 bad usage (arguments,
no key, a path that is not a capture); 3 the API key was refused; 4 the service could not be reached. `status`
with job ids: 0 when every one of them is completed, 1 when any failed or was canceled (named on stderr), 5 when
none failed but some are still queued or running (a pipeline polls on 5).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from tqdm import tqdm

from neumatex_client.client import DEFAULT_URL, Client, Event
from neumatex_client.errors import ApiError, AuthError, NeuMatExError, ServiceUnreachable, WaitTimeout
from neumatex_client.models import Job

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_AUTH, EXIT_UNREACHABLE, EXIT_PENDING = 0, 1, 2, 3, 4, 5


class UsageError(Exception):
    pass


def _is_capture(p: Path) -> bool:
    return (p.is_dir() and (p / "transforms.json").is_file()) or (p.is_file() and p.suffix.lower() == ".zip")


def expand_captures(paths: list[str]) -> list[Path]:
    """Each argument as captures: itself when it is one, else the captures directly inside it (a batch)."""
    out: list[Path] = []
    for arg in paths:
        p = Path(arg)
        if p.name == "transforms.json" and p.is_file():
            p = p.parent
        if _is_capture(p):
            out.append(p)
        elif p.is_dir():
            inside = sorted(c for c in p.iterdir() if not c.name.startswith(".") and _is_capture(c))
            if not inside:
                raise UsageError(f"{arg} is not a capture (no transforms.json) and holds no capture folders or zips")
            out.extend(inside)
        else:
            raise UsageError(f"{arg} does not exist" if not p.exists() else f"{arg} is not a capture folder or zip")
    return out


def _config(text: str | None) -> dict[str, Any]:
    if not text:
        return {}
    try:
        raw = Path(text[1:]).read_text() if text.startswith("@") else text
        value = json.loads(raw)
    except (OSError, ValueError) as exc:
        raise UsageError(f"--config must be a JSON object or @file.json: {exc}") from None
    if not isinstance(value, dict):
        raise UsageError("--config must be a JSON object, e.g. '{\"init\": \"random\", \"tto\": {\"steps\": 50}}'")
    return value


def _unique(folder: Path, name: str, taken: set[str]) -> Path:
    stem, n = name or "asset", 1
    candidate = f"{stem}.zip"
    while candidate in taken or (folder / candidate).exists():
        n += 1
        candidate = f"{stem}-{n}.zip"
    taken.add(candidate)
    return folder / candidate


class Submission:
    """One capture of a submit: its upload, job and progress bar."""

    def __init__(self, path: Path, position: int, show: bool):
        self.path, self.name = path, path.stem if path.suffix.lower() == ".zip" else path.name
        self.job: Job | None = None
        self.problem = ""
        self.asset: Path | None = None
        self.bar = tqdm(total=100, desc=f"{self.name}: upload", position=position, leave=True, disable=not show,
                        bar_format="{desc:<36.36} {percentage:3.0f}%|{bar}| [{elapsed}{postfix}]")  # fmt: skip
        self.lock = threading.Lock()

    def set(self, fraction: float, desc: str | None = None, postfix: str | None = None) -> None:
        with self.lock:
            if desc is not None:
                self.bar.set_description_str(desc, refresh=False)
            if postfix is not None:
                self.bar.set_postfix_str(postfix, refresh=False)
            self.bar.n = round(100 * min(max(fraction, 0.0), 1.0), 1)
            self.bar.refresh()

    def uploaded(self, sent: int, total: int) -> None:
        self.set(sent / max(total, 1))

    def on_event(self, ev: Event) -> None:
        d = ev.data
        if "progress" in d:
            stage = d.get("stage", "")
            self.set(float(d["progress"]), postfix=f"{stage} {d.get('message', '')}"[:60])
        elif ev.event == "state":
            self.set(self.bar.n / 100, postfix=str(d.get("state", "")))


def accepted(client: Client, schema: str, field: str) -> tuple[str, ...]:
    """The values the service accepts for `field` of its request body `schema` (the enum in its OpenAPI
    document), so the choices are written once, on the server; () when the document does not say."""
    try:
        prop = client.request("GET", "/openapi.json").json()["components"]["schemas"][schema]["properties"][field]
    except (ApiError, ValueError, KeyError, TypeError):
        return ()
    for option in (prop, *prop.get("anyOf", [])):
        if isinstance(option, dict) and "enum" in option:
            return tuple(str(v) for v in option["enum"])
    return ()


def _check_choice(client: Client, schema: str, field: str, value: str | None) -> None:
    choices = accepted(client, schema, field) if value is not None else ()
    if choices and value not in choices:
        raise UsageError(f"--{field} {value!r} is not one the service offers (choose from {', '.join(choices)})")


def cmd_submit(args: argparse.Namespace, client: Client) -> int:
    captures = expand_captures(args.captures)
    config = _config(args.config)
    if args.out and not args.wait:
        raise UsageError("--out needs --wait (assets are downloaded once their jobs complete)")
    for field in ("preset", "queue"):  # before anything is uploaded
        _check_choice(client, "JobCreate", field, getattr(args, field))
    show = not args.no_progress
    subs = [Submission(p, i, show) for i, p in enumerate(captures)]
    for sub in subs:
        try:
            cap = client.upload_capture(sub.path, exclude=args.exclude or (), progress=sub.uploaded)
            sub.job = client.create_job(cap.id, preset=args.preset, config=config, queue=args.queue,
                                        webhook_url=args.webhook)  # fmt: skip
            sub.set(sub.job.progress, desc=f"{sub.name}: {sub.job.id}", postfix=sub.job.state)
        except (AuthError, ServiceUnreachable):
            raise
        except ApiError as exc:
            sub.problem = f"{sub.name} ({sub.path}) was refused: {exc}"
            sub.set(0.0, postfix="refused")
    if args.wait:
        out = Path(args.out) if args.out else None
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
        taken: set[str] = set()
        waiting = [s for s in subs if s.job is not None]

        def follow(sub: Submission) -> None:
            assert sub.job is not None
            try:
                sub.job = client.wait(sub.job.id, timeout=args.timeout, on_event=sub.on_event)
            except WaitTimeout as exc:
                sub.problem = f"{sub.name}: {exc}"
                return
            job = sub.job
            sub.set(job.progress, postfix=job.state)
            if job.state != "completed":
                why = job.error or job.message or job.state
                sub.problem = f"{sub.name} ({job.id}) {job.state}: {why}"
            elif out is not None:
                with sub.lock:
                    target = _unique(out, sub.name, taken)
                sub.asset = client.download_asset(job.id, target)

        if waiting:
            with ThreadPoolExecutor(min(len(waiting), 16)) as pool:
                list(pool.map(follow, waiting))
    for sub in subs:
        sub.bar.close()
    for sub in subs:
        if sub.job is not None:
            shown = f" -> {sub.asset}" if sub.asset else ""
            print(f"{sub.name}\t{sub.job.id}\t{sub.job.state}{shown}")
    failed = [s for s in subs if s.problem]
    for sub in failed:
        print(f"error: {sub.problem}", file=sys.stderr)
    if failed:
        print(f"error: {len(failed)} of {len(subs)} captures did not give an asset", file=sys.stderr)
    return EXIT_FAILED if failed else EXIT_OK


def cmd_jobs(args: argparse.Namespace, client: Client) -> int:
    page = client.list_jobs(state=args.state, capture_id=args.capture, limit=args.limit, offset=args.offset)
    if args.json:
        print(page.model_dump_json(indent=1))
        return EXIT_OK
    print(f"{'job':<26} {'state':<10} {'stage':<14} {'progress':>8}  {'capture':<26} created")
    for j in page.items:
        print(f"{j.id:<26} {j.state:<10} {j.stage:<14} {j.progress:>8.0%}  {j.capture_id:<26} "
              f"{j.created_at:%Y-%m-%d %H:%M:%S}")  # fmt: skip
    more = f"; next page: --offset {page.next_offset}" if page.next_offset is not None else ""
    print(f"{len(page.items)} of {page.total} jobs{more}")
    return EXIT_OK


def cmd_status(args: argparse.Namespace, client: Client) -> int:
    """One line per job (tab-separated: id, state, stage, progress, ETA or the error); without ids the queued and
    running jobs. Exit code: see the module docstring."""
    if not args.ids:
        jobs = [j for state in ("running", "queued") for j in client.list_jobs(state=state, limit=500).items]
    else:
        jobs = [client.get_job(ident) for ident in args.ids]
    if args.json:
        print(json.dumps([json.loads(j.model_dump_json()) for j in jobs], indent=1))
    else:
        for j in jobs:
            eta = f"ETA {j.eta_s:.0f} s" if j.eta_s is not None else ""
            print(f"{j.id}\t{j.state}\t{j.stage}\t{j.progress:.0%}\t{j.error or eta}")
    if not args.ids:
        return EXIT_OK
    bad = [j for j in jobs if j.state in ("failed", "canceled")]
    for j in bad:
        print(f"error: job {j.id} {j.state}" + (f": {j.error}" if j.error else ""), file=sys.stderr)
    if bad:
        return EXIT_FAILED
    return EXIT_OK if all(j.state == "completed" for j in jobs) else EXIT_PENDING


def cmd_job(args: argparse.Namespace, client: Client) -> int:
    job = client.get_job(args.id)
    if args.json:
        print(job.model_dump_json(indent=1))
        return EXIT_OK
    rows = [("job", job.id), ("state", job.state), ("stage", f"{job.stage} ({job.stage_fraction:.0%})"),
            ("progress", f"{job.progress:.0%}" + (f", ETA {job.eta_s:.0f} s" if job.eta_s is not None else "")),
            ("message", job.message), ("capture", job.capture_id), ("preset", job.preset), ("queue", job.queue),
            ("created", f"{job.created_at:%Y-%m-%d %H:%M:%S}"), ("stages done", ", ".join(job.stages_done))]
    if job.error:
        rows.append(("error", job.error))
    if job.waiting:
        rows.append(("waiting", job.waiting))
    for stage, m in job.metrics.items():
        rows.append((f"metrics {stage}", ", ".join(f"{k}={v}" for k, v in m.items())))
    if job.state == "completed":
        rows.append(("asset", f"{client.url}/v1/jobs/{job.id}/asset.zip"))
    for d in job.webhooks:
        rows.append(("webhook", f"{d.state} -> {d.url}: {d.status} after {d.attempts} attempt(s)"))
    for k, v in rows:
        print(f"{k:<16} {v}")
    return EXIT_OK


def cmd_cancel(args: argparse.Namespace, client: Client) -> int:
    for ident in args.ids:
        print(f"{ident}\t{client.cancel(ident).state}")
    return EXIT_OK


def cmd_retry(args: argparse.Namespace, client: Client) -> int:
    job = client.retry(args.id, from_stage=args.from_stage)
    print(f"{job.id}\t{job.state}\t{job.message}")
    return EXIT_OK


def cmd_download(args: argparse.Namespace, client: Client) -> int:
    job = client.get_job(args.id)
    if job.state != "completed":
        print(f"error: job {job.id} is {job.state}; only completed jobs have an asset", file=sys.stderr)
        return EXIT_FAILED
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(client.download_asset(job.id, out / f"{job.id}.zip"))
    return EXIT_OK


def parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--url", default=None, help=f"the service (default: $NEUMATEX_URL or {DEFAULT_URL})")
    common.add_argument("--api-key", default=None, help="API key (default: $NEUMATEX_API_KEY)")
    ap = argparse.ArgumentParser(prog="neumatex", description="NeuMatEx job service client",
                                 epilog="exit codes: 0 ok, 1 a capture or job failed, 2 usage, 3 API key refused, "
                                 "4 service unreachable, 5 (status) jobs still queued or running")  # fmt: skip
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("submit", parents=[common], help="upload captures and start an extraction job for each",
                       description="Upload each CAPTURE (folder with transforms.json, .zip, or a folder of those: "
                       "a batch) and start a job for it; with --wait follow every job with a progress bar, "
                       "download the assets into --out and exit 1 if any job failed (named on stderr).")
    p.add_argument("captures", nargs="+", metavar="CAPTURE")
    p.add_argument("--preset", default="cpu", help="the extraction preset (default cpu); an unknown one is refused "
                   "before uploading, with the service's presets named")
    p.add_argument("--config", default=None, help="job config overrides: JSON object or @file.json")
    p.add_argument("--queue", default=None, help="where the job's lmrm and tto stages run (default: gpu for the "
                   "gpu preset, else cpu; the other stages run on cpu)")
    p.add_argument("--webhook", default=None, metavar="URL", help="POSTed a signed JSON body when each job ends")
    p.add_argument("--exclude", action="append", metavar="GLOB", help="leave out matching paths of folders")
    p.add_argument("--wait", action="store_true", help="follow the jobs until they end")
    p.add_argument("--out", default=None, metavar="DIR", help="with --wait: download each asset zip here")
    p.add_argument("--timeout", type=float, default=None, metavar="S", help="with --wait: give up after S seconds")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p = sub.add_parser("status", parents=[common], help="one line per job; exit 0 all completed, 1 one failed or "
                       "was canceled, 5 some still queued or running")
    p.add_argument("ids", nargs="*", metavar="JOB", help="job ids (none: this tenant's queued and running jobs)")
    p.add_argument("--json", action="store_true", help="the job records as JSON")
    p = sub.add_parser("jobs", parents=[common], help="list this tenant's jobs")
    p.add_argument("--state", choices=("queued", "running", "completed", "failed", "canceled"))
    p.add_argument("--capture", default=None, metavar="CAPTURE_ID")
    p.add_argument("--limit", type=int, default=50)
    p.add_argument("--offset", type=int, default=0)
    p.add_argument("--json", action="store_true", help="the page as JSON")
    p = sub.add_parser("job", parents=[common], help="show one job")
    p.add_argument("id", metavar="ID")
    p.add_argument("--json", action="store_true", help="the job record as JSON")
    p = sub.add_parser("cancel", parents=[common], help="cancel queued or running jobs")
    p.add_argument("ids", nargs="+", metavar="ID")
    p = sub.add_parser("retry", parents=[common], help="run a failed or canceled job again")
    p.add_argument("id", metavar="ID")
    p.add_argument("--from-stage", default=None, metavar="STAGE", help="rerun from this stage (also on a completed "
                   "job); the service names its stages when given another")
    p = sub.add_parser("download", parents=[common], help="download a completed job's asset zip")
    p.add_argument("id", metavar="ID")
    p.add_argument("--out", default=".", metavar="DIR", help="folder for <job id>.zip (default: here)")
    return ap


COMMANDS = {"submit": cmd_submit, "status": cmd_status, "jobs": cmd_jobs, "job": cmd_job, "cancel": cmd_cancel,
            "retry": cmd_retry, "download": cmd_download}


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        with Client(args.url, args.api_key) as client:
            return COMMANDS[args.command](args, client)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except AuthError as exc:
        print(f"error: the service refused the API key: {exc}", file=sys.stderr)
        return EXIT_AUTH
    except ServiceUnreachable as exc:
        print(f"error: the service could not be reached: {exc}", file=sys.stderr)
        return EXIT_UNREACHABLE
    except ApiError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_FAILED
    except NeuMatExError as exc:  # no API key, not a capture
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
