"""Bad-input battery against the real service (issue 15, part A): uploads, zips, JSON, images, meshes, environment
maps, query parameters and headers. Every case asserts the status code (a 4xx, or 507 for a full storage), the
message (one sentence naming the user's file and the problem; never the internal ".files.zip" nor a server path),
that nothing changed in the storage folder outside the upload's own staging folder, and that another tenant was
served meanwhile (its GETs run in a thread during the request and all answer 200)."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from zip_bombs import bomb_zip, folder_bytes

from neumatex_core.imageio import write_image
from services.cluster import REPO, Proc, free_port, wait_for

from .helpers import EXAMPLE, KEY_A, KEY_B, TINY, Service, capture_zip, other_tenant_served, sql, upload

LIMIT = 8 * 1024**2  # the tests' max_upload_bytes (helpers.Service)
FILES = sorted(p for p in EXAMPLE.rglob("*") if p.is_file() and p.relative_to(EXAMPLE).parts[0] not in
               ("photos", "gbuffers"))  # fmt: skip
Case = Callable[[httpx.Client], httpx.Response]


# ------------------------------------------------------------------------------------------------------- helpers


def listing(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in root.rglob("*")} if root.is_dir() else set()


def form(files: list[tuple[bytes, bytes]], boundary: bytes = b"nmx-battery-boundary") -> tuple[bytes, dict[str, str]]:
    """A multipart/form-data body written by hand (httpx would escape a NUL in a file name)."""
    body = b""
    for name, data in files:
        body += (b"--" + boundary + b'\r\nContent-Disposition: form-data; name="files"; filename="' + name +
                 b'"\r\nContent-Type: application/octet-stream\r\n\r\n' + data + b"\r\n")  # fmt: skip
    return body + b"--" + boundary + b"--\r\n", {"Content-Type": f"multipart/form-data; boundary={boundary.decode()}"}


def post_form(files: list[tuple[bytes, bytes]], path: str = "/v1/captures") -> Case:
    body, headers = form(files)
    return lambda c: c.post(path, content=body, headers=headers)


Parts = list[tuple[bytes, bytes]]


def example_form(extra: Parts | None = None, drop: tuple[str, ...] = ()) -> Parts:
    out = [(p.relative_to(EXAMPLE).as_posix().encode(), p.read_bytes()) for p in FILES
           if p.relative_to(EXAMPLE).as_posix() not in drop]  # fmt: skip
    return out + list(extra or [])


def transforms(**changes: Any) -> bytes:
    t = json.loads((EXAMPLE / "transforms.json").read_text())
    t.update(changes)
    return json.dumps(t).encode()


def with_file(name: str, data: bytes, drop: tuple[str, ...] = ()) -> Case:
    """The example capture as a zip with `name` replaced by (or added as) `data`."""
    z = capture_zip(extra={name: data}, drop=(name, *drop))
    return lambda c: upload(c, z)


def image_bytes(pixels: np.ndarray, suffix: str, tmp: Path) -> bytes:
    path = tmp / f"img{suffix}"
    write_image(path, pixels)
    return path.read_bytes()


def zip_of(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------------ fixtures


@pytest.fixture(scope="module")
def world(service: Service, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Tenant A's capture and a completed-looking job with an asset, tenant B's capture, scratch files."""
    tmp = tmp_path_factory.mktemp("battery")
    with service.client(KEY_A) as a, service.client(KEY_B) as b:
        cap_a = upload(a, capture_zip()).json()
        cap_b = upload(b, capture_zip()).json()
        r = a.post("/v1/jobs", json={"capture_id": cap_a["id"], "preset": "tiny", "config": {**TINY, "tto": {}}})
        assert r.status_code in (200, 201), r.text
        job_id = r.json()["id"]
        a.post(f"/v1/jobs/{job_id}/cancel")  # no worker runs here; marked completed below with a small asset
    asset = service.storage / "assets" / job_id / "asset"
    asset.mkdir(parents=True)
    (asset / "manifest.json").write_text("{}")
    sql(service, "UPDATE jobs SET state = 'completed', asset_key = :key WHERE id = :id", key=f"assets/{job_id}",
        id=job_id)
    return {"cap_a": cap_a["id"], "cap_b": cap_b["id"], "job": job_id, "tmp": tmp}


def run_case(service: Service, world: dict[str, Any], case: Case, status: int, *words: str,
             staged: bool = False) -> httpx.Response:
    """Run `case` as tenant A while tenant B is served; check status, words of the message, the storage."""
    before = listing(service.storage)
    with other_tenant_served(service, world["cap_b"]), service.client(KEY_A) as c:
        r = case(c)
    text = r.text
    assert r.status_code == status, text
    body = r.json()
    message = body["error"] + " " + json.dumps(body.get("problems", []))
    for w in words:
        assert w in message, f"{w!r} not in {message}"
    assert ".files.zip" not in text and str(service.root) not in text and str(REPO) not in text, text
    after = listing(service.storage)
    changed = (after - before) | (before - after)
    if staged:  # a session upload may change its own staging folder, nothing else
        changed = {p for p in changed if not p.startswith("staging/")}
    assert not changed, f"the storage changed outside the upload's folder: {sorted(changed)[:10]}"
    return r


# -------------------------------------------------------------------------------------------------------- cases

CLASH = {"x.png": b"a", "x.png/y.png": b"b"}
DEEP = b'{"frames": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
CASES: dict[str, tuple[Callable[[Path], Case], int, tuple[str, ...]]] = {
    # zips
    "zip bomb 4000 x 1 MiB": (lambda t: (lambda c: upload(c, bomb_zip(t / "b4000.zip", 4000, 1 << 20).read_bytes())),
                              422, ("the uploaded zip cannot be unpacked safely", "zip bomb")),
    "zip bomb 2040 x 1 MB": (lambda t: (lambda c: upload(c, bomb_zip(t / "b2040.zip", 2040, 10**6).read_bytes())),
                             422, ("the uploaded zip", "expands", "zip bomb")),
    "zip with lying sizes": (lambda t: (lambda c: upload(c, bomb_zip(t / "liar.zip", 50, 1 << 20, 100).read_bytes())),
                             422, ("the uploaded zip", "bomb/0000.png", "cannot be extracted")),
    "zip x.png and x.png/y.png": (lambda t: (lambda c: upload(c, capture_zip(extra=CLASH))),
                                  422, ("'teapot/x.png' is both a file and a folder",)),
    "zip 300-character member": (lambda t: (lambda c: upload(c, capture_zip(extra={"a" * 300 + ".png": b"x"}))),
                                 422, ("longer than 255 bytes", "characters")),
    "zip slip": (lambda t: (lambda c: upload(c, capture_zip(extra={"../../escaped.txt": b"owned"}))),
                 422, ("../../escaped.txt", "zip-slip")),
    "zip symlink": (lambda t: (lambda c: upload(c, _symlink_zip())), 422, ("images/000.png", "symbolic link")),
    "zip too many files": (lambda t: (lambda c: upload(c, zip_of({f"f{i}.txt": b"x" for i in range(201)}))),
                           422, ("201 files", "at most 200")),
    "not a zip": (lambda t: (lambda c: upload(c, b"this is not a zip at all")), 422, ("the uploaded zip", "not a")),
    "named zip": (lambda t: (lambda c: c.post("/v1/captures", content=b"PK\x05\x06" + b"\0" * 10, headers={
        "Content-Type": "application/zip", "Content-Disposition": 'attachment; filename="C:\\\\caps\\\\mine.zip"'})),
        422, ("'mine.zip'",)),
    "zip without transforms.json": (lambda t: with_file("notes.txt", b"hi", ("transforms.json",)),
                                    422, ("transforms.json", "not found")),
    # forms
    "form x.png and x.png/y.png": (lambda t: post_form(example_form([(b"x.png", b"a"), (b"x.png/y.png", b"b")])),
                                   422, ("'x.png/y.png'", "both a file and a folder")),
    "form NUL in a file name": (lambda t: post_form(example_form([(b"images/a\0b.png", b"x")])),
                                422, ("'images/a\\\\x00b.png'", "NUL")),
    "form 300-character name": (lambda t: post_form(example_form([(b"b" * 300 + b".png", b"x")])),
                                422, ("longer than 255 bytes",)),
    "form file twice": (lambda t: post_form(example_form([(b"mesh.obj", b"again")])), 409, ("'mesh.obj'", "twice")),
    "form no files": (lambda t: post_form([]), 422, ("holds no files",)),
    "form malformed": (lambda t: (lambda c: c.post("/v1/captures", content=b"garbage",
                                                   headers={"Content-Type": "multipart/form-data"})),
                       400, ("boundary",)),
    "form file type": (lambda t: post_form(example_form([(b"tools/run.sh", b"#!/bin/sh")])),
                       415, ("tools/run.sh", "file type")),
    "form over the limit": (lambda t: post_form(example_form([(b"big.png", b"\0" * (LIMIT + 1))])),
                            413, ("larger than the limit",)),
    # request
    "content type": (lambda t: (lambda c: c.post("/v1/captures", content=b"x", headers={"Content-Type": "text/plain"})),
                     415, ("content type 'text/plain'",)),
    "content length over the limit": (lambda t: (lambda c: upload(c, os.urandom(LIMIT + 1))),
                                      413, ("larger than the limit",)),
    # transforms.json
    "deeply nested JSON": (lambda t: with_file("transforms.json", DEEP),
                           422, ("transforms.json", "nested too deeply")),
    "transforms.json not JSON": (lambda t: with_file("transforms.json", b"{nope"),
                                 422, ("transforms.json", "not valid JSON")),
    "transforms.json wrong types": (lambda t: with_file("transforms.json", transforms(frames="none")),
                                    422, ("transforms.json", "frames")),
    # images
    "corrupt image": (lambda t: with_file("images/003.png", b"not a png"), 422, ("images/003.png",)),
    "image of the wrong size": (lambda t: with_file("images/001.png", image_bytes(np.zeros((32, 32, 3)), ".png", t)),
                                422, ("images/001.png", "32x32")),
    # meshes
    "degenerate mesh": (lambda t: with_file("mesh.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"),
                        422, ("mesh.obj", "degenerate")),
    "mesh at one point": (lambda t: with_file("mesh.obj", b"v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n"),
                          422, ("mesh.obj", "one point")),
    "mesh too small for the views": (lambda t: with_file("mesh.obj", _tiny_mesh()), 422, ("mesh.obj", "too small")),
    "mesh not a mesh": (lambda t: with_file("mesh.obj", b"\x00\x01garbage"), 422, ("mesh.obj",)),
    # environment maps
    "8-bit PNG envmap": (lambda t: (lambda c: upload(c, capture_zip(
        extra={"envmap.png": image_bytes(np.full((16, 32, 3), 0.5), ".png", t),
               "transforms.json": transforms(envmap="envmap.png")}, drop=("transforms.json",)))),
        422, ("envmap.png", "8- or 16-bit", "EXR")),
    "envmap with negative radiance": (lambda t: with_file("envmap.exr", image_bytes(-np.ones((16, 32, 3)), ".exr", t)),
                                      422, ("envmap.exr", "negative")),
    "envmap not 2:1": (lambda t: with_file("envmap.exr", image_bytes(np.ones((16, 16, 3)), ".exr", t)),
                       422, ("envmap.exr", "twice as wide")),
    # query parameters and headers
    "huge offset on captures": (lambda t: (lambda c: c.get("/v1/captures", params={"offset": "99999999999999999999"})),
                                422, ("offset",)),
    "huge offset on jobs": (lambda t: (lambda c: c.get("/v1/jobs", params={"offset": "99999999999999999999"})),
                            422, ("offset",)),
}  # fmt: skip


def _symlink_zip() -> bytes:
    import stat

    info = zipfile.ZipInfo("teapot/images/000.png")
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr(info, "/etc/passwd")
    return buf.getvalue()


def _tiny_mesh() -> bytes:
    lines = []
    for line in (EXAMPLE / "mesh.obj").read_text().splitlines():
        if line.startswith("v "):
            x, y, z = (float(v) * 1e-5 for v in line.split()[1:4])
            line = f"v {x:.12f} {y:.12f} {z:.12f}"
        lines.append(line)
    return ("\n".join(lines) + "\n").encode()


@pytest.mark.parametrize("kind", list(CASES))
def test_bad_input(service: Service, world: dict[str, Any], kind: str) -> None:
    make, status, words = CASES[kind]
    run_case(service, world, make(world["tmp"]), status, *words)


def test_last_event_id_not_a_number(service: Service, world: dict[str, Any]) -> None:
    def events(value: bytes) -> Case:
        return lambda c: c.get(f"/v1/jobs/{world['job']}/events", headers={b"Last-Event-ID": value})

    for value in (b"abc", "²".encode(), b"99999999999999999999999", b"-1"):
        run_case(service, world, events(value), 400, "Last-Event-ID", "whole number")


def test_nul_in_an_asset_file_path(service: Service, world: dict[str, Any]) -> None:
    r = run_case(service, world, lambda c: c.get(f"/v1/jobs/{world['job']}/asset/files/manifest%00.json"),
                 404, "asset file")
    assert "manifest" in r.json()["error"]
    with service.client() as c:  # the route works for a real file
        assert c.get(f"/v1/jobs/{world['job']}/asset/files/manifest.json").status_code == 200


def test_session_uploads_reject_bad_names_and_clashes(service: Service, world: dict[str, Any]) -> None:
    with service.client() as c:
        up = c.post("/v1/uploads", json={"name": "parts"}).json()["id"]
    files = f"/v1/uploads/{up}/files"
    with service.client() as c:
        body, headers = form([(b"x.png", b"a")])
        assert c.post(files, content=body, headers=headers).status_code == 200
    run_case(service, world, post_form([(b"x.png/y.png", b"b")], files), 422, "'x.png/y.png'", "both a file and a "
             "folder", staged=True)  # fmt: skip
    run_case(service, world, post_form([(b"a\0.png", b"b")], files), 422, "NUL", staged=True)
    run_case(service, world, post_form([(b"x.png", b"b")], files), 409, "x.png", "already uploaded", staged=True)
    with service.client() as c:
        assert c.delete(f"/v1/uploads/{up}").status_code == 204


def test_zip_example_of_the_docs_is_accepted(service: Service, world: dict[str, Any], tmp_path: Path) -> None:
    """docs/service.md: `zip -r teapot.zip examples/teapot -x ...`, run from the repository (a folder in a folder)."""
    z = tmp_path / "teapot.zip"
    subprocess.run(["zip", "-qr", str(z), "examples/teapot", "-x", "examples/teapot/photos/*",
                    "examples/teapot/gbuffers/*"], cwd=REPO, check=True)  # fmt: skip
    with service.client() as c:
        r = upload(c, z.read_bytes())
        assert r.status_code == 201 and r.json()["frames"] == 23, r.text


def test_obj_with_a_latin1_comment_is_accepted(service: Service, world: dict[str, Any]) -> None:
    obj = b"# mod\xe8le \xe0 Paris\n" + (EXAMPLE / "mesh.obj").read_bytes()
    with service.client() as c:
        r = upload(c, capture_zip(extra={"mesh.obj": obj}, drop=("mesh.obj",)))
        assert r.status_code == 201, r.text


@pytest.mark.parametrize("kind", ["zip", "form"])
def test_unbounded_chunked_body_is_cut_at_the_limit(service: Service, world: dict[str, Any], kind: str) -> None:
    """A body that never ends (chunked, no Content-Length): 413 once the limit passed; the staging folder and the
    API's TMPDIR never hold much more than the limit; nothing is left."""
    sent = [0]
    cap = 64 * LIMIT  # a safety net for the test itself: the server should stop it long before

    def endless() -> Iterator[bytes]:
        if kind == "form":
            yield (b'--bnd\r\nContent-Disposition: form-data; name="files"; filename="images/big.png"\r\n'
                   b"Content-Type: application/octet-stream\r\n\r\n")  # fmt: skip
        chunk = b"\0" * (256 * 1024)
        while sent[0] < cap:
            sent[0] += len(chunk)
            yield chunk

    headers = {"Content-Type": "application/zip" if kind == "zip" else "multipart/form-data; boundary=bnd"}
    watched = [service.storage / "staging", service.root / "tmp"]
    peak, done = [0], threading.Event()

    def watch() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], sum(folder_bytes(f) for f in watched))
            time.sleep(0.002)

    before = listing(service.storage)
    t = threading.Thread(target=watch)
    t.start()
    try:
        with other_tenant_served(service, world["cap_b"]), service.client() as c:
            try:
                r = c.post("/v1/captures", content=endless(), headers=headers)
                assert r.status_code == 413 and "larger than the limit" in r.json()["error"], r.text
            except (httpx.WriteError, httpx.RemoteProtocolError, httpx.ReadError):
                pass  # the server answered 413 and closed the connection while the client was still sending
    finally:
        done.set()
        t.join()
    assert sent[0] < cap, "the server read the whole endless body"
    assert peak[0] <= LIMIT + (2 << 20), f"{peak[0]} bytes on disk for a limit of {LIMIT}"
    assert listing(service.storage) == before and folder_bytes(service.root / "tmp") == 0


@pytest.fixture(scope="module")
def full_api(service: Service) -> Iterator[str]:
    """A second API process on the same database and storage whose free-space reserve exceeds any disk."""
    port = free_port()
    env = {**service.env, "NEUMATEX_MIN_FREE_BYTES": str(10**18)}
    proc = Proc([sys.executable, "-m", "uvicorn", "services.main:app", "--host", "127.0.0.1", "--port",
                 str(port), "--log-level", "warning"], env, service.root / "api-full.log").start()  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    wait_for(lambda: httpx.get(url + "/healthz", timeout=2).status_code == 200, 120, "the second API")
    yield url
    proc.stop()


@pytest.mark.parametrize("kind", ["zip", "form"])
def test_upload_into_a_full_storage_is_507(service: Service, world: dict[str, Any], full_api: str, kind: str) -> None:
    def case(c: httpx.Client) -> httpx.Response:
        with httpx.Client(base_url=full_api, headers={"Authorization": f"Bearer {KEY_A}"}, timeout=60) as full:
            if kind == "zip":  # small bodies: the 507 comes before anything is read
                return upload(full, zip_of({"teapot/transforms.json": transforms()}))
            return post_form([(b"transforms.json", transforms())])(full)

    run_case(service, world, case, 507, "the storage is full")
