"""Storage of captures, stage outputs and assets, by key (a relative POSIX path).

Layout: captures/<capture_id>/ (the capture folder), staging/<upload_id>/ (uploads not yet committed),
work/<job_id>/<stage>/ (the pipeline's stage outputs), assets/<job_id>/asset/ and assets/<job_id>/asset.zip.
The local backend is a folder; the pipeline reads and writes it in place. Writes that must be all-or-nothing go
to a staging key first and are moved into place with one rename.
"""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path, PurePosixPath


class StorageError(Exception):
    pass


class LocalStorage:
    """A folder. Every key is checked to stay inside it."""

    def __init__(self, root: Path):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        rel = PurePosixPath(key)
        if "\x00" in key:
            raise StorageError(f"storage key {key!r} holds a NUL character")
        if rel.is_absolute() or ".." in rel.parts:
            raise StorageError(f"storage key {key!r} escapes the storage folder")
        p = (self.root / rel).resolve()
        if not p.is_relative_to(self.root):
            raise StorageError(f"storage key {key!r} escapes the storage folder")
        return p

    def exists(self, key: str) -> bool:
        return self.path(key).exists()

    def delete(self, key: str) -> None:
        p = self.path(key)
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        elif p.exists():
            p.unlink()

    def move(self, src: str, dst: str) -> None:
        """Atomic within the folder: dst appears complete or not at all."""
        d = self.path(dst)
        d.parent.mkdir(parents=True, exist_ok=True)
        os.replace(self.path(src), d)

    def list(self, key: str) -> list[str]:
        """Every file below key, as keys relative to it, sorted."""
        base = self.path(key)
        if not base.is_dir():
            return []
        return sorted(p.relative_to(base).as_posix() for p in base.rglob("*") if p.is_file())

    def size(self, key: str) -> int:
        return self.path(key).stat().st_size

    def check_writable(self) -> None:
        """Write, read back and delete a probe file (readiness)."""
        probe = self.root / f".probe-{uuid.uuid4().hex}"
        try:
            probe.write_bytes(b"ok")
            if probe.read_bytes() != b"ok":
                raise StorageError(f"{self.root}: probe file read back wrong")
        except OSError as exc:
            raise StorageError(f"{self.root}: not writable ({exc.strerror})") from None
        finally:
            probe.unlink(missing_ok=True)


def get_storage() -> LocalStorage:
    from services.core.config import get_settings

    return LocalStorage(get_settings().local_root)
