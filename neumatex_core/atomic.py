"""Atomic file writes: a reader (or a resumed run) sees either the old file or the whole new one, never half of it.

    with replaced_atomically(path) as tmp:      # any writer: images, torch.save, zip files
        write_image(tmp, pixels)
    write_json_atomic(path, {"complete": True})  # indented, sorted keys, a final newline (diff-friendly, stable bytes)

The temporary file sits beside the target (same folder, so the rename stays on one file system), is hidden (a
leading dot), names the process (two processes never share one) and keeps the target's suffix (writers such as
OpenImageIO pick the format by it). If the body raises, the temporary file is removed and the target is untouched.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any


@contextmanager
def replaced_atomically(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; once the body has written it, rename it onto `path`."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def is_temporary(name: str) -> bool:
    """True for the name of a temporary file of `replaced_atomically` (or an older "<name>.tmp"): one that a
    stopped process may have left, and that a reader or a copier skips."""
    return name.endswith(".tmp") or (name.startswith(".") and ".tmp" in name)


def write_json_atomic(path: str | Path, data: Any) -> None:
    """`data` as JSON (indent 1, sorted keys, final newline) at `path`, atomically."""
    with replaced_atomically(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
