"""Container health checks for docker-compose.yml, with the standard library only (the slim images have no curl
or procps).

    python deploy/healthcheck.py http URL     # exit 0 when GET URL answers 2xx within 5 s
    python deploy/healthcheck.py proc WORD    # exit 0 when another process's command line holds WORD
"""

from __future__ import annotations

import os
import sys
import urllib.request
from pathlib import Path


def http_ok(url: str, timeout_s: float = 5.0) -> bool:
    """True when GET url answers with a 2xx status."""
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as r:
            return 200 <= int(r.status) < 300
    except Exception as exc:
        print(f"{url}: {exc}", file=sys.stderr)
        return False


def process_running(word: str) -> bool:
    """True when a process other than this one has `word` as one of its command-line arguments (or in one)."""
    me = os.getpid()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == me:
            continue
        try:
            args = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:  # the process ended meanwhile
            continue
        if any(word.encode() in a for a in args) and b"healthcheck.py" not in b" ".join(args):
            return True
    print(f"no process runs {word!r}", file=sys.stderr)
    return False


def main(argv: list[str]) -> int:
    if len(argv) == 2 and argv[0] == "http":
        return 0 if http_ok(argv[1]) else 1
    if len(argv) == 2 and argv[0] == "proc":
        return 0 if process_running(argv[1]) else 1
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
