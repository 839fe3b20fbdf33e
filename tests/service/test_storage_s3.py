"""Storage behind one interface (services/storage.py): the same tests on the local folder and on an S3 bucket of a
real S3-compatible server (moto_server, tests/service/s3server.py); then the whole service on S3 storage: a capture
uploaded (zip and session), a tiny job run by a worker that shares no folder with the API, the asset downloaded
(zip streamed from the bucket, a file, the manifest, the report), and the capture deleted with its objects."""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from neumatex_core import pipeline
from services.stage_io import publish_asset, stage_paths, store_stage
from services.storage import LocalStorage, NotStored, S3Storage, Storage, StorageError, ordered

from .helpers import KEY_A, TINY, Service, capture_zip, upload, wait_state
from .s3server import REGION, MotoServer, moto_server

BACKENDS = ("local", "s3")


@pytest.fixture(scope="module")
def moto(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MotoServer]:
    with moto_server(tmp_path_factory.mktemp("moto")) as server:
        yield server


@pytest.fixture(params=BACKENDS)
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Storage:
    if request.param == "local":
        return LocalStorage(tmp_path / "storage")
    server: MotoServer = request.getfixturevalue("moto")
    return S3Storage(server.bucket(), server.url, REGION, prefix="svc", scratch=tmp_path / "scratch",
                     access_key_id="testing", secret_access_key="testing")  # fmt: skip


def tree(folder: Path, files: dict[str, bytes]) -> Path:
    for rel, data in files.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(data)
    return folder


FILES = {"transforms.json": b'{"frames": []}', "images/a.png": b"\x89PNG" + bytes(range(256)) * 40,
         "images/deep/b.png": b"b" * 10, "done.json": b"{}"}  # fmt: skip


def test_put_get_tree_list_sizes_usage(store: Storage, tmp_path: Path) -> None:
    src = tree(tmp_path / "src", FILES)
    assert store.put_tree(src, "work/job_1/validate", last=("done.json",)) == len(FILES)
    assert store.list("work/job_1/validate") == sorted(FILES)
    assert store.sizes("work/job_1/validate") == {k: len(v) for k, v in FILES.items()}
    assert store.usage("work/job_1") == sum(len(v) for v in FILES.values())
    assert store.usage("work/job_1/validate/done.json") == 2 and store.size("work/job_1/validate/done.json") == 2
    assert store.is_file("work/job_1/validate/images/a.png") and not store.is_file("work/job_1/validate/images")
    assert store.exists("work/job_1/validate/images") and store.exists("work/job_1")
    assert not store.exists("work/job_") and store.list("work/job_") == [] and store.usage("work/nothing") == 0
    assert list(store.ages("work")) == ["job_1"]
    assert store.get_tree("work/job_1/validate", tmp_path / "back") == len(FILES)
    for rel, data in FILES.items():
        assert (tmp_path / "back" / rel).read_bytes() == data
    store.get_file("work/job_1/validate/images/deep/b.png", tmp_path / "one" / "b.png")
    assert (tmp_path / "one" / "b.png").read_bytes() == b"b" * 10
    with pytest.raises(NotStored):
        store.get_file("work/job_1/validate/missing.png", tmp_path / "one" / "m.png")
    with pytest.raises(NotStored):
        store.size("work/job_1/validate/missing.png")
    with store.local_tree("work/job_1/validate") as local:
        assert (local / "images" / "a.png").read_bytes() == FILES["images/a.png"]


def test_delete_a_file_a_prefix_and_not_its_siblings(store: Storage, tmp_path: Path) -> None:
    src = tree(tmp_path / "src", {"a/x.bin": b"1", "a/sub/y.bin": b"22"})
    for key in ("work/job_1", "work/job_10", "work/job_1.txt"):  # a sibling that starts with the same characters
        store.put_tree(src, key)
    store.put_file(src / "a" / "x.bin", "work/job_1.bin")
    store.delete("work/job_1/a/x.bin")
    assert store.list("work/job_1") == ["a/sub/y.bin"]
    store.delete("work/job_1")
    assert not store.exists("work/job_1") and store.list("work/job_1") == []
    assert store.list("work/job_10") == ["a/sub/y.bin", "a/x.bin"] and store.is_file("work/job_1.bin")
    assert store.list("work/job_1.txt") == ["a/sub/y.bin", "a/x.bin"]
    store.delete("work/job_1")  # nothing there: no error
    store.delete("work")
    assert store.usage("work") == 0 and store.ages("work") == {}


@pytest.mark.parametrize("key", ["../outside", "/etc/passwd", "a/../../b", "a/\x00b", "", ".", "work/.."])
def test_a_key_that_escapes_is_refused(store: Storage, key: str, tmp_path: Path) -> None:
    (tmp_path / "f").write_bytes(b"x")
    for op in (lambda: store.exists(key), lambda: store.delete(key), lambda: store.list(key),
               lambda: store.put_file(tmp_path / "f", key), lambda: store.read_chunks(key),
               lambda: store.workspace(key), lambda: store.usage(key)):  # fmt: skip
        with pytest.raises(StorageError):
            op()


def test_local_keys_may_not_leave_the_folder_through_a_link(tmp_path: Path) -> None:
    store = LocalStorage(tmp_path / "storage")
    (tmp_path / "secret").mkdir()
    (tmp_path / "storage" / "link").symlink_to(tmp_path / "secret")
    with pytest.raises(StorageError, match="escapes"):
        store.path("link/x")


def test_streaming_read(store: Storage, tmp_path: Path) -> None:
    data = os.urandom(3 * 1024**2 + 123)
    (tmp_path / "big.bin").write_bytes(data)
    store.put_file(tmp_path / "big.bin", "assets/job_1/asset.zip")
    size, chunks = store.read_chunks("assets/job_1/asset.zip", chunk=1 << 20)
    parts = list(chunks)
    assert size == len(data) and b"".join(parts) == data and len(parts) >= 4 and max(map(len, parts)) <= 1 << 20
    assert store.read_bytes("assets/job_1/asset.zip") == data
    with pytest.raises(NotStored):
        store.read_chunks("assets/job_1/missing.zip")


def test_commit_moves_a_workspace_in_whole(store: Storage, tmp_path: Path) -> None:
    ws = store.workspace("staging/upl_1")
    tree(ws / "files", FILES)
    (ws / "asset.zip").write_bytes(b"PK")
    store.put_tree(tree(tmp_path / "old", {"stale.txt": b"old"}), "captures/cap_1")
    store.commit_tree(ws / "files", "captures/cap_1", last=("done.json",), replace=True)
    store.commit_file(ws / "asset.zip", "assets/job_1/asset.zip")
    assert store.list("captures/cap_1") == sorted(FILES) and store.read_bytes("assets/job_1/asset.zip") == b"PK"
    assert not (ws / "files").exists() and not (ws / "asset.zip").exists()
    assert ordered(["a", "done.json", "b", "manifest.json"], ("manifest.json", "done.json")) == \
        ["a", "b", "manifest.json", "done.json"]  # fmt: skip
    store.check_writable()


def test_stage_io_downloads_the_finished_stages_and_stores_the_next_done_last(store: Storage,
                                                                             tmp_path: Path) -> None:
    store.put_tree(tree(tmp_path / "cap", {"transforms.json": b"{}"}), "captures/cap_1")
    store.put_tree(tree(tmp_path / "v", {"done.json": b'{"stage": "validate", "metrics": {}}'}),
                   "work/job_1/validate")  # fmt: skip
    with stage_paths("job_1", "captures/cap_1", "prepare_views", store) as (capture_dir, work_dir):
        assert (capture_dir / "transforms.json").read_bytes() == b"{}"
        assert (work_dir / "validate" / "done.json").is_file()
        tree(work_dir / "prepare_views", {"views.json": b"[]", "done.json": b"{}"})
        store_stage("job_1", work_dir, "prepare_views", store)
        asset = tree(work_dir / "export" / "asset", {
            "manifest.json": json.dumps({"files": {}, "capture": f"{capture_dir}/transforms.json"}).encode(),
            "report/index.html": b"<p>report</p>"})  # fmt: skip
        assert publish_asset("job_1", work_dir, store) == "assets/job_1"
    assert store.list("work/job_1/prepare_views") == ["done.json", "views.json"]
    assert store.list("assets/job_1") == ["asset.zip", "asset/manifest.json", "asset/report/index.html"]
    manifest = json.loads(store.read_bytes("assets/job_1/asset/manifest.json"))
    assert manifest["capture"] == "captures/cap_1/transforms.json"  # a storage key, not a server path
    with zipfile.ZipFile(io.BytesIO(store.read_bytes("assets/job_1/asset.zip"))) as z:
        assert sorted(z.namelist()) == ["manifest.json", "report/", "report/index.html"]
    if isinstance(store, S3Storage):  # the stage run's temporary folder is gone
        assert not asset.exists() and not any((tmp_path / "scratch" / "stage-runs").iterdir())
    # a stopped stage keeps its checkpoint (no done.json), and its next run finds it
    with pytest.raises(pipeline.Cancelled):
        with stage_paths("job_1", "captures/cap_1", "tto", store) as (_, work_dir):
            tree(work_dir / "tto", {"checkpoint.pt": b"step 7"})
            raise pipeline.Cancelled("canceled")
    assert store.list("work/job_1/tto") == ["checkpoint.pt"]
    with stage_paths("job_1", "captures/cap_1", "tto", store) as (_, work_dir):
        assert (work_dir / "tto" / "checkpoint.pt").read_bytes() == b"step 7"
        assert not pipeline.is_done(work_dir, "tto")


def test_s3_errors_are_said_in_words(moto: MotoServer, tmp_path: Path) -> None:
    store = S3Storage("no-such-bucket", moto.url, REGION, scratch=tmp_path, access_key_id="testing",
                      secret_access_key="testing")  # fmt: skip
    with pytest.raises(StorageError, match="no-such-bucket.*NoSuchBucket"):
        store.check_writable()
    with pytest.raises(StorageError, match="NoSuchBucket"):
        store.list("work")


# -- the service on S3 ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def s3_service(moto: MotoServer, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Service, str]]:
    root = tmp_path_factory.mktemp("service-s3")
    bucket = moto.bucket()
    svc = Service(root)
    svc.env.update(moto.env(bucket))
    svc.redis.start()
    svc.add_tenant("a", KEY_A)
    svc.start_api()
    svc.start_worker()
    yield svc, bucket
    svc.stop()


def test_service_on_s3_upload_job_download(s3_service: tuple[Service, str], moto: MotoServer) -> None:
    """Needs workers/tasks.py to run stages through services/stage_io.py (stage_paths, store_stage, publish_asset):
    with S3 storage the worker has no folder to read the capture from otherwise."""
    svc, bucket = s3_service
    with svc.client() as c:
        assert c.get("/readyz").json()["checks"]["storage"] == "ok"
        r = upload(c, capture_zip())
        assert r.status_code == 201, r.text
        cap = r.json()
        assert f"captures/{cap['id']}/transforms.json" in moto.keys(bucket, "captures/")
        # a session: files in two requests, kept in the bucket between them, then committed
        up = c.post("/v1/uploads", json={"name": "session"}).json()
        with zipfile.ZipFile(io.BytesIO(capture_zip())) as z:
            form = [("files", (n.removeprefix("teapot/"), z.read(n))) for n in z.namelist() if not n.endswith("/")]
        half = len(form) // 2
        assert c.post(f"/v1/uploads/{up['id']}/files", files=form[:half]).status_code == 200
        assert moto.keys(bucket, f"staging/{up['id']}/files/")
        assert c.post(f"/v1/uploads/{up['id']}/files", files=form[:1]).status_code == 409
        assert c.post(f"/v1/uploads/{up['id']}/files", files=form[half:]).status_code == 200
        done = c.post(f"/v1/uploads/{up['id']}/commit")
        assert done.status_code == 201 and done.json()["frames"] == 23, done.text
        assert moto.keys(bucket, "staging/") == []
        # a job run by the worker from the bucket
        r = c.post("/v1/jobs", json={"capture_id": cap["id"], "preset": "tiny", "config": {**TINY, "tto": {}}})
        assert r.status_code in (200, 201), r.text
        job_id = r.json()["id"]
        j = wait_state(c, job_id, ("completed", "failed"), 600, svc)
        assert j["state"] == "completed", j.get("error")
        keys = moto.keys(bucket)
        for stage in ("validate", "prepare_views", "lmrm", "tto", "export"):
            assert f"work/{job_id}/{stage}/done.json" in keys
        assert f"assets/{job_id}/asset.zip" in keys and f"assets/{job_id}/asset/manifest.json" in keys
        z = c.get(f"/v1/jobs/{job_id}/asset.zip")
        assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
        with zipfile.ZipFile(io.BytesIO(z.content)) as archive:
            assert "manifest.json" in archive.namelist() and archive.testzip() is None
        manifest = c.get(f"/v1/jobs/{job_id}/asset").json()
        assert "manifest.json" in manifest["files"] and manifest["bytes"] > 0
        f = c.get(f"/v1/jobs/{job_id}/asset/files/manifest.json")
        assert f.status_code == 200 and "files" in f.json()
        assert c.get(f"/v1/jobs/{job_id}/asset/files/../../../etc/passwd").status_code == 404
        rep = c.get(f"/v1/jobs/{job_id}/report/index.html")
        assert rep.status_code == 200 and rep.headers["content-type"].startswith("text/html")
        assert str(svc.root) not in rep.text
        assert c.get("/v1/quota").json()["storage"]["jobs_bytes"] > 0
        # nothing of it on a local disk the API and the worker share
        local = svc.root / "data" / "storage"
        assert not any(p.is_file() for p in local.rglob("*")) if local.exists() else True
        # deleting the capture removes its objects, its job's work and asset
        assert c.delete(f"/v1/captures/{cap['id']}").status_code == 200
        left = moto.keys(bucket)
        assert not [k for k in left if k.startswith((f"captures/{cap['id']}/", f"work/{job_id}/",
                                                     f"assets/{job_id}/"))]  # fmt: skip
