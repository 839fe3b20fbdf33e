"""Storage of captures, stage outputs and assets, by key (a relative POSIX path), behind one interface (`Storage`)
with two backends: `LocalStorage` (a folder, possibly a shared mount) and `S3Storage` (an S3-compatible bucket:
AWS S3, MinIO, Ceph RGW, ...). `get_storage()` picks the backend from the settings (NEUMATEX_STORAGE=local|s3).

Layout (docs/service.md, "Storage"): captures/<capture_id>/ (the capture folder), staging/<upload_id>/ (uploads
not yet committed), work/<job_id>/<stage>/ (the pipeline's stage outputs, done.json last),
assets/<job_id>/asset/, assets/<job_id>/asset.zip and assets/<job_id>/viewer/ (the viewer's bundle).

Commit semantics: what must appear whole is built in a local folder first (`workspace`) and moved in with
`commit_tree` / `commit_file`. On a folder that is one rename. S3 has no rename (a server-side copy is a second
full write per object and a tree still appears object by object), so the S3 backend writes the final keys and
makes a tree count as present only through a marker written last: a single PUT is atomic (an object appears whole
or not at all), so `commit_tree(..., last=(...))` uploads the named files after every other one (done.json of a
stage, manifest.json of an asset, bundle.json of a viewer bundle), and a capture's marker is its database row,
written after its objects.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import uuid
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mypy_boto3_s3 import S3Client

CHUNK = 1 << 20  # streaming reads (downloads) in 1 MiB chunks
PART = 16 * 1024**2  # S3 multipart uploads/downloads: 16 MiB parts


class StorageError(Exception):
    """A key that is not allowed (escapes the storage) or a backend failure, in words."""


class NotStored(StorageError, FileNotFoundError):
    """The key holds no file."""


def check_key(key: str) -> str:
    """The key as a normalised relative POSIX path ('a//b/./c' -> 'a/b/c'); StorageError when it is absolute,
    empty, climbs out ('..') or holds a NUL character."""
    if "\x00" in key:
        raise StorageError(f"storage key {key!r} holds a NUL character")
    rel = PurePosixPath(key)
    if rel.is_absolute() or ".." in rel.parts:
        raise StorageError(f"storage key {key!r} escapes the storage folder")
    norm = rel.as_posix()
    if norm in ("", "."):
        raise StorageError(f"storage key {key!r} names the whole storage")
    return norm


def folder_bytes(folder: Path) -> int:
    """Bytes of the files below `folder` (0 when it does not exist; files vanishing meanwhile are skipped)."""
    total = 0
    stack = [folder]
    while stack:
        try:
            entries = list(os.scandir(stack.pop()))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for e in entries:
            try:
                if e.is_dir(follow_symlinks=False):
                    stack.append(Path(e.path))
                elif e.is_file(follow_symlinks=False):
                    total += e.stat(follow_symlinks=False).st_size
            except FileNotFoundError:
                pass
    return total


def sync_tree(folder: Path) -> None:
    """fsync every file under `folder` and the folders themselves (the data, then the names); `folder` may be
    a single file."""
    for path in [folder, *(sorted(folder.rglob("*")) if folder.is_dir() else [])]:
        if not path.is_symlink():
            _fsync(path)


def start_sync(path: Path) -> None:
    """Begin flushing a file or folder to disk on a background thread, so that the disk works while the request
    goes on (validation, the client's next files); best effort, since the commit's sync_tree is what counts."""

    def run() -> None:
        try:
            sync_tree(path)
        except OSError:
            pass

    threading.Thread(target=run, name="start-sync", daemon=True).start()


def sync_tree_name(path: Path) -> None:
    """fsync the folder holding `path`, so that its (new) name is on disk."""
    _fsync(path.parent)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if path.is_dir() else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def local_files(folder: Path) -> list[str]:
    """The files below a local folder as relative POSIX paths, sorted (links are not followed)."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() and not p.is_symlink())


def ordered(files: Iterable[str], last: Iterable[str]) -> list[str]:
    """`files` with the names in `last` moved to the end, in the order `last` gives them (the commit markers)."""
    files, last = list(files), [n for n in last]
    return [f for f in files if f not in last] + [f for f in last if f in files]


class Storage(ABC):
    """What the service needs from a storage. Keys are relative POSIX paths; a "folder" is a key prefix."""

    @abstractmethod
    def local_path(self, key: str) -> Path | None:
        """The key's path on this machine when the backend is a local folder (read and write it in place), else
        None (the bytes live elsewhere: use the operations below)."""

    @abstractmethod
    def is_file(self, key: str) -> bool:
        """Whether `key` is a stored file."""

    @abstractmethod
    def exists(self, key: str) -> bool:
        """Whether `key` is a stored file or a folder holding at least one file."""

    @abstractmethod
    def delete(self, key: str) -> None:
        """Remove the file `key`, or every file under the folder `key` (nothing there: nothing happens)."""

    @abstractmethod
    def list(self, key: str) -> list[str]:
        """Every file under the folder `key`, as keys relative to it, sorted ([] when there is none)."""

    @abstractmethod
    def sizes(self, key: str) -> dict[str, int]:
        """Every file under the folder `key` (relative name -> bytes), in one listing."""

    @abstractmethod
    def size(self, key: str) -> int:
        """Bytes of the file `key` (NotStored when it is not a file)."""

    @abstractmethod
    def usage(self, key: str) -> int:
        """Bytes of the file `key`, or of every file under the folder `key` (0 when nothing is there)."""

    @abstractmethod
    def ages(self, key: str) -> dict[str, float]:
        """The entries right under the folder `key` (name -> last modified, unix seconds): for finding what is
        old enough to remove (abandoned uploads, work folders past their retention)."""

    @abstractmethod
    def put_file(self, src: Path, key: str) -> None:
        """Store the local file `src` as `key` (it appears whole; an existing file is replaced)."""

    @abstractmethod
    def get_file(self, key: str, dest: Path) -> None:
        """Write the file `key` to the local path `dest` (NotStored when it is not a file)."""

    @abstractmethod
    def put_tree(self, src: Path, key: str, last: Iterable[str] = ()) -> int:
        """Store every file of the local folder `src` under the folder `key` (src is kept), the relative names in
        `last` after all the others (markers); returns the number of files."""

    @abstractmethod
    def get_tree(self, key: str, dest: Path) -> int:
        """Write every file under the folder `key` below the local folder `dest`; returns the number of files."""

    @abstractmethod
    def read_chunks(self, key: str, chunk: int = CHUNK) -> tuple[int, Iterator[bytes]]:
        """(size in bytes, the bytes in chunks) of the file `key`, for streaming it out; NotStored when missing."""

    @abstractmethod
    def workspace(self, key: str) -> Path:
        """A local folder (created, possibly non-empty) to build something in before it is committed near `key`:
        local: the storage's own folder at `key` (same file system, so committing is a rename); S3: the same key
        under the scratch folder. The caller removes it (shutil.rmtree) when done."""

    @abstractmethod
    def commit_tree(self, src: Path, key: str, last: Iterable[str] = (), replace: bool = False) -> None:
        """Move the local folder `src` (consumed) into the folder `key`; with replace, what was under `key` is
        removed first. Local: one rename (the folder appears whole); S3: the files uploaded, `last` after all the
        others (readers take the tree as present only once its marker is there)."""

    @abstractmethod
    def commit_file(self, src: Path, key: str) -> None:
        """Move the local file `src` (consumed) to `key`: it appears whole (a rename, or one PUT)."""

    @abstractmethod
    def check_writable(self) -> None:
        """Write, read back and delete a probe (readiness); StorageError saying why not."""

    def read_bytes(self, key: str) -> bytes:
        """The whole file `key` (small files: manifests, records)."""
        return b"".join(self.read_chunks(key)[1])

    @contextmanager
    def local_tree(self, key: str) -> Iterator[Path]:
        """The folder `key` as a local folder for reading: in place for a local backend, else downloaded into a
        temporary folder that is removed afterwards."""
        local = self.local_path(key)
        if local is not None:
            yield local
            return
        tmp = self.workspace(f"tmp/{uuid.uuid4().hex}")
        try:
            self.get_tree(key, tmp)
            yield tmp
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


class LocalStorage(Storage):
    """A folder. Every key is checked to stay inside it (symbolic links included)."""

    def __init__(self, root: Path):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        """The key's path; StorageError when it escapes the folder (also through a link)."""
        rel = check_key(key)
        p = (self.root / rel).resolve()
        if not p.is_relative_to(self.root) or p == self.root:
            raise StorageError(f"storage key {key!r} escapes the storage folder")
        return p

    def local_path(self, key: str) -> Path:
        return self.path(key)

    def is_file(self, key: str) -> bool:
        return self.path(key).is_file()

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
        base = self.path(key)
        return local_files(base) if base.is_dir() else []

    def sizes(self, key: str) -> dict[str, int]:
        base = self.path(key)
        out: dict[str, int] = {}
        stack = [("", base)]
        while stack:  # one os.scandir walk, like folder_bytes (no Path objects per file)
            prefix, folder = stack.pop()
            try:
                entries = list(os.scandir(folder))
            except (FileNotFoundError, NotADirectoryError):
                continue
            for e in entries:
                try:
                    if e.is_dir(follow_symlinks=False):
                        stack.append((f"{prefix}{e.name}/", Path(e.path)))
                    elif e.is_file(follow_symlinks=False):
                        out[prefix + e.name] = e.stat(follow_symlinks=False).st_size
                except FileNotFoundError:
                    pass
        return out

    def size(self, key: str) -> int:
        p = self.path(key)
        if not p.is_file():
            raise NotStored(f"storage key {key!r} is not a stored file")
        return p.stat().st_size

    def usage(self, key: str) -> int:
        p = self.path(key)
        return folder_bytes(p) if p.is_dir() else p.stat().st_size if p.is_file() else 0

    def ages(self, key: str) -> dict[str, float]:
        base = self.path(key)
        if not base.is_dir():
            return {}
        out = {}
        for p in base.iterdir():
            try:
                out[p.name] = p.stat().st_mtime
            except FileNotFoundError:
                pass
        return out

    def put_file(self, src: Path, key: str) -> None:
        dst = self.path(key)
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_name(f".{dst.name}.{uuid.uuid4().hex}.tmp")
        try:
            shutil.copyfile(src, tmp)
            os.replace(tmp, dst)
        finally:
            tmp.unlink(missing_ok=True)

    def get_file(self, key: str, dest: Path) -> None:
        p = self.path(key)
        if not p.is_file():
            raise NotStored(f"storage key {key!r} is not a stored file")
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(p, dest)

    def put_tree(self, src: Path, key: str, last: Iterable[str] = ()) -> int:
        files = ordered(local_files(src), last)
        for rel in files:
            self.put_file(src / rel, f"{key}/{rel}")
        return len(files)

    def get_tree(self, key: str, dest: Path) -> int:
        files = self.list(key)
        for rel in files:
            self.get_file(f"{key}/{rel}", dest / rel)
        return len(files)

    def read_chunks(self, key: str, chunk: int = CHUNK) -> tuple[int, Iterator[bytes]]:
        p = self.path(key)
        try:
            f = open(p, "rb")
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            raise NotStored(f"storage key {key!r} is not a stored file") from None

        def chunks() -> Iterator[bytes]:
            with f:
                while data := f.read(chunk):
                    yield data

        return os.fstat(f.fileno()).st_size, chunks()

    def workspace(self, key: str) -> Path:
        p = self.path(key)
        p.mkdir(parents=True, exist_ok=True)
        return p

    def commit_tree(self, src: Path, key: str, last: Iterable[str] = (), replace: bool = False) -> None:
        dst = self.path(key)
        if replace:
            self.delete(key)
        dst.parent.mkdir(parents=True, exist_ok=True)
        sync_tree(src)  # on disk before it appears: a committed capture or stage survives a power cut
        try:
            os.replace(src, dst)  # one rename: the folder appears whole
        except OSError:
            if dst.exists() or src.stat().st_dev == dst.parent.stat().st_dev:
                raise
            shutil.move(src, dst)  # another file system (not a workspace): copied, then removed
            sync_tree(dst)
        sync_tree_name(dst)

    def commit_file(self, src: Path, key: str) -> None:
        dst = self.path(key)
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.stat().st_dev == dst.parent.stat().st_dev:
            os.replace(src, dst)
        else:
            self.put_file(src, key)
            src.unlink()

    def check_writable(self) -> None:
        probe = self.root / f".probe-{uuid.uuid4().hex}"
        try:
            probe.write_bytes(b"ok")
            if probe.read_bytes() != b"ok":
                raise StorageError(f"{self.root}: probe file read back wrong")
        except OSError as exc:
            raise StorageError(f"{self.root}: not writable ({exc.strerror})") from None
        finally:
            probe.unlink(missing_ok=True)


class S3Storage(Storage):
    """An S3-compatible bucket (boto3). Keys live under `prefix` in `bucket`; credentials come from the standard
    AWS sources (AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY, a profile, an instance role) unless given. Local work
    (uploads being unpacked, `local_tree` downloads) happens under `scratch`."""

    def __init__(self, bucket: str, endpoint_url: str | None = None, region: str | None = None, prefix: str = "",
                 scratch: Path | None = None, access_key_id: str | None = None,
                 secret_access_key: str | None = None, client: S3Client | None = None):
        import boto3
        from boto3.s3.transfer import TransferConfig
        from botocore.config import Config

        if not bucket:
            raise StorageError("S3 storage needs a bucket (NEUMATEX_S3_BUCKET)")
        self.bucket = bucket
        self.prefix = check_key(prefix) + "/" if prefix.strip("/") else ""
        self.scratch = Path(scratch or Path(tempfile.gettempdir()) / "neumatex-scratch").resolve()
        self.client: S3Client = client or boto3.session.Session().client(
            "s3", endpoint_url=endpoint_url or None, region_name=region or None,
            aws_access_key_id=access_key_id or None, aws_secret_access_key=secret_access_key or None,
            config=Config(retries={"max_attempts": 5, "mode": "standard"}, max_pool_connections=32))
        self.transfer = TransferConfig(multipart_threshold=PART, multipart_chunksize=PART, max_concurrency=8,
                                       use_threads=True)  # fmt: skip

    # -- keys -------------------------------------------------------------------------------------------------
    def _key(self, key: str) -> str:
        return self.prefix + check_key(key)

    def _folder(self, key: str) -> str:
        return self._key(key) + "/"

    def _objects(self, key: str) -> Iterator[dict[str, Any]]:
        """Every object under the folder `key` (ListObjectsV2, 1000 per page), without the empty "folder" objects
        that some tools make (keys ending in '/')."""
        pages = self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=self._folder(key))
        try:
            for page in pages:
                yield from (o for o in page.get("Contents", []) if not o["Key"].endswith("/"))  # type: ignore[misc]
        except StorageError:
            raise
        except Exception as exc:  # no such bucket, credentials refused, the server unreachable
            raise self._error(exc, key) from None

    def _error(self, exc: Exception, key: str) -> StorageError:
        from botocore.exceptions import ClientError

        if isinstance(exc, ClientError):
            code = exc.response.get("Error", {}).get("Code", "")
            if code in ("404", "NoSuchKey", "NotFound"):
                return NotStored(f"storage key {key!r} is not a stored file")
            return StorageError(f"S3 bucket {self.bucket!r}: {code or 'error'} for key {key!r} ({exc})")
        return StorageError(f"S3 bucket {self.bucket!r}: {type(exc).__name__} for key {key!r} ({exc})")

    # -- the interface ------------------------------------------------------------------------------------------
    def local_path(self, key: str) -> None:
        check_key(key)
        return None

    def is_file(self, key: str) -> bool:
        try:
            self.client.head_object(Bucket=self.bucket, Key=self._key(key))
            return True
        except Exception as exc:
            err = self._error(exc, key)
            if isinstance(err, NotStored):
                return False
            raise err from None

    def exists(self, key: str) -> bool:
        if self.is_file(key):
            return True
        r = self.client.list_objects_v2(Bucket=self.bucket, Prefix=self._folder(key), MaxKeys=1)
        return bool(r.get("KeyCount", 0))

    def delete(self, key: str) -> None:
        full = self._key(key)
        keys = [full, *(o["Key"] for o in self._objects(key))]
        for i in range(0, len(keys), 1000):  # DeleteObjects takes up to 1000 keys; missing keys are no error
            batch = [{"Key": k} for k in keys[i:i + 1000]]
            r = self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})  # type: ignore[typeddict-item]
            if r.get("Errors"):
                e = r["Errors"][0]
                raise StorageError(f"S3 bucket {self.bucket!r}: could not delete {e.get('Key')!r} "
                                   f"({e.get('Code')}: {e.get('Message')})")  # fmt: skip

    def list(self, key: str) -> list[str]:
        n = len(self._folder(key))
        return sorted(o["Key"][n:] for o in self._objects(key))

    def sizes(self, key: str) -> dict[str, int]:
        n = len(self._folder(key))
        return {o["Key"][n:]: int(o["Size"]) for o in self._objects(key)}

    def size(self, key: str) -> int:
        try:
            return int(self.client.head_object(Bucket=self.bucket, Key=self._key(key))["ContentLength"])
        except Exception as exc:
            raise self._error(exc, key) from None

    def usage(self, key: str) -> int:
        total = sum(int(o["Size"]) for o in self._objects(key))
        return total if total else (self.size(key) if self.is_file(key) else 0)

    def ages(self, key: str) -> dict[str, float]:
        n = len(self._folder(key))
        out: dict[str, float] = {}
        for o in self._objects(key):
            name = o["Key"][n:].split("/", 1)[0]
            out[name] = max(out.get(name, 0.0), o["LastModified"].timestamp())
        return out

    def put_file(self, src: Path, key: str) -> None:
        try:  # one PUT below PART, else a multipart upload: either way the object appears whole at the end
            self.client.upload_file(str(src), self.bucket, self._key(key), Config=self.transfer)
        except Exception as exc:
            raise self._error(exc, key) from None

    def get_file(self, key: str, dest: Path) -> None:
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            self.client.download_file(self.bucket, self._key(key), str(dest), Config=self.transfer)
        except Exception as exc:
            dest.unlink(missing_ok=True)
            raise self._error(exc, key) from None

    def put_tree(self, src: Path, key: str, last: Iterable[str] = ()) -> int:
        files = ordered(local_files(src), last)
        markers = [f for f in files if f in set(last)]
        self._put_many(src, key, [f for f in files if f not in markers])
        for rel in markers:  # after every other file has been stored
            self.put_file(src / rel, f"{key}/{rel}")
        return len(files)

    def _put_many(self, src: Path, key: str, files: Sequence[str]) -> None:
        """Upload small files concurrently (a round trip each dominates); big ones use multipart threads."""
        from concurrent.futures import ThreadPoolExecutor

        if len(files) <= 1:
            for rel in files:
                self.put_file(src / rel, f"{key}/{rel}")
            return
        with ThreadPoolExecutor(8) as pool:
            for _ in pool.map(lambda rel: self.put_file(src / rel, f"{key}/{rel}"), files):
                pass

    def get_tree(self, key: str, dest: Path) -> int:
        from concurrent.futures import ThreadPoolExecutor

        files = self.list(key)
        for rel in files:
            check_key(rel)  # a stored name may not climb out of dest
        with ThreadPoolExecutor(8) as pool:
            for _ in pool.map(lambda rel: self.get_file(f"{key}/{rel}", dest / rel), files):
                pass
        return len(files)

    def read_chunks(self, key: str, chunk: int = CHUNK) -> tuple[int, Iterator[bytes]]:
        try:
            r = self.client.get_object(Bucket=self.bucket, Key=self._key(key))
        except Exception as exc:
            raise self._error(exc, key) from None
        body = r["Body"]

        def chunks() -> Iterator[bytes]:
            try:
                yield from body.iter_chunks(chunk)
            finally:
                body.close()

        return int(r["ContentLength"]), chunks()

    def workspace(self, key: str) -> Path:
        p = self.scratch / check_key(key)
        p.mkdir(parents=True, exist_ok=True)
        return p

    def commit_tree(self, src: Path, key: str, last: Iterable[str] = (), replace: bool = False) -> None:
        if replace:
            self.delete(key)
        self.put_tree(src, key, last)
        shutil.rmtree(src, ignore_errors=True)

    def commit_file(self, src: Path, key: str) -> None:
        self.put_file(src, key)
        src.unlink(missing_ok=True)

    def check_writable(self) -> None:
        key = f".probe-{uuid.uuid4().hex}"
        try:
            self.client.put_object(Bucket=self.bucket, Key=self._key(key), Body=b"ok")
            got = self.client.get_object(Bucket=self.bucket, Key=self._key(key))["Body"].read()
            if got != b"ok":
                raise StorageError(f"S3 bucket {self.bucket!r}: probe object read back wrong")
        except StorageError:
            raise
        except Exception as exc:
            raise self._error(exc, key) from None
        finally:
            try:
                self.client.delete_object(Bucket=self.bucket, Key=self._key(key))
            except Exception:
                pass


def storage_from(settings: Any) -> Storage:
    """The backend the settings name (Settings.storage: "local" or "s3")."""
    if settings.storage == "s3":
        return S3Storage(settings.s3_bucket, settings.s3_endpoint_url, settings.s3_region, settings.s3_prefix,
                         settings.scratch_dir, settings.s3_access_key_id or None,
                         settings.s3_secret_access_key or None)  # fmt: skip
    return LocalStorage(settings.local_root)


_cached: tuple[Any, Storage] | None = None
_lock = threading.Lock()


def get_storage() -> Storage:
    """The configured storage, made once per process and settings object (a boto3 client is thread-safe once
    made, but making one is not: hence the lock)."""
    global _cached
    from services.core.config import get_settings

    st = get_settings()
    with _lock:
        if _cached is None or _cached[0] is not st:
            _cached = (st, storage_from(st))
        return _cached[1]

