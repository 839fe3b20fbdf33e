"""A real S3-compatible server for the tests: moto's standalone server (`moto_server`, from moto[server]) started
as a subprocess on a free port, with a fresh bucket per test (`bucket()`); and the settings that point the service
at it (`env(bucket)`: NEUMATEX_STORAGE=s3 and the standard AWS credential variables)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from services.cluster import free_port, wait_for

KEY_ID, SECRET, REGION = "testing", "testing", "us-east-1"


class MotoServer:
    """moto_server on 127.0.0.1:<free port>, its output in `log`."""

    def __init__(self, log: Path):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = log
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> MotoServer:
        exe = shutil.which("moto_server") or str(Path(sys.executable).parent / "moto_server")
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen([exe, "-H", "127.0.0.1", "-p", str(self.port)], stdout=out,
                                         stderr=subprocess.STDOUT)  # fmt: skip
        wait_for(self._up, 60, "moto_server")
        return self

    def _up(self) -> bool:
        import httpx

        assert self.proc is not None
        if self.proc.poll() is not None:
            raise RuntimeError(f"moto_server exited ({self.proc.returncode}): {self.log.read_text()[-2000:]}")
        return httpx.get(self.url + "/", timeout=2).status_code < 500

    def client(self) -> Any:
        import boto3

        return boto3.client("s3", endpoint_url=self.url, region_name=REGION, aws_access_key_id=KEY_ID,
                            aws_secret_access_key=SECRET)  # fmt: skip

    def bucket(self) -> str:
        """A new, empty bucket."""
        name = f"nmx-{uuid.uuid4().hex[:12]}"
        self.client().create_bucket(Bucket=name)
        return name

    def keys(self, bucket: str, prefix: str = "") -> list[str]:
        pages = self.client().get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix)
        return sorted(o["Key"] for page in pages for o in page.get("Contents", []))

    def env(self, bucket: str) -> dict[str, str]:
        """The service's settings for this server and bucket (the names docker-compose uses)."""
        return {"NEUMATEX_STORAGE": "s3", "NEUMATEX_S3_ENDPOINT_URL": self.url, "NEUMATEX_S3_BUCKET": bucket,
                "NEUMATEX_S3_REGION": REGION, "AWS_ACCESS_KEY_ID": KEY_ID, "AWS_SECRET_ACCESS_KEY": SECRET}

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None


@contextmanager
def moto_server(folder: Path) -> Iterator[MotoServer]:
    """A running moto_server (its log in `folder`), stopped afterwards; use it in a fixture:
    `with moto_server(tmp_path_factory.mktemp("moto")) as server: yield server`."""
    os.environ.setdefault("AWS_EC2_METADATA_DISABLED", "true")  # boto3 never asks an instance for credentials
    server = MotoServer(folder / "moto.log").start()
    try:
        yield server
    finally:
        server.stop()
