"""Hostile or careless capture input in the core (issue 15, part A): zip bombs of many small members, bytes counted
while writing, bad member names, deeply nested JSON, a zip of a folder inside a folder, 8-bit environment maps,
small negative HDR noise, degenerate meshes, an OBJ with a Latin-1 comment, and a CLI without tracebacks."""

from __future__ import annotations

import errno
import os
import subprocess
import threading
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from capture_fixtures import read_transforms, write_capture, write_transforms, zip_capture
from zip_bombs import bomb_zip, folder_bytes

from neumatex_core.capture import CaptureError, Problem, extract_zip, load_capture, validate_capture
from neumatex_core.capture.archive import DEFAULT_MAX_TOTAL_BYTES, name_problem
from neumatex_core.cli import main
from neumatex_core.geometry.mesh import MeshError, load_mesh
from neumatex_core.imageio import write_image
from neumatex_core.lighting.envmap import NEGATIVE_NOISE_FRACTION, EnvironmentMap, EnvmapError


def messages(problems: list[Problem]) -> str:
    return "\n".join(map(str, problems))


@contextmanager
def peak_bytes(folder: Path) -> Iterator[list[int]]:
    """The most bytes seen under `folder` while the block ran (sampled every millisecond)."""
    peak, done = [0], threading.Event()

    def watch() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], folder_bytes(folder))
            time.sleep(0.001)

    t = threading.Thread(target=watch)
    t.start()
    try:
        yield peak
    finally:
        done.set()
        t.join()


# ------------------------------------------------------------------------------------------------- zip bombs


def test_4000_member_bomb_is_refused_before_writing(tmp_path: Path) -> None:
    z = bomb_zip(tmp_path / "bomb.zip", 4000, 1 << 20)  # 4.2 GB declared, 4.5 MB packed
    dest = tmp_path / "dest"
    with peak_bytes(tmp_path / "dest") as peak, pytest.raises(CaptureError) as info:
        extract_zip(z, dest)  # default limits: 2 GiB, 10,000 files, ratio 200
    text = messages(info.value.problems)
    assert "unpacks to 4194304000 bytes" in text and "zip bomb" in text, text
    assert peak[0] <= DEFAULT_MAX_TOTAL_BYTES and peak[0] == 0 and not dest.exists()


def test_2040_small_members_are_a_bomb_too(tmp_path: Path) -> None:
    # each member is under the 1 MiB per-member ratio threshold and the total under 2 GiB: the whole archive's
    # ratio gives it away
    z = bomb_zip(tmp_path / "bomb.zip", 2040, 1_000_000)
    with pytest.raises(CaptureError) as info:
        extract_zip(z, tmp_path / "dest")
    assert "bomb.zip: expands" in messages(info.value.problems) and "zip bomb" in messages(info.value.problems)
    assert not (tmp_path / "dest").exists()


def test_lying_bomb_is_cut_while_writing_and_removed(tmp_path: Path) -> None:
    # the central directory declares 1000 bytes per member: the checks before extraction pass; the bytes written
    # are counted against the declared size, so at most 4000 x 1000 bytes can ever reach the disk
    z = bomb_zip(tmp_path / "liar.zip", 4000, 1 << 20, declared_bytes=1000)
    dest = tmp_path / "dest"
    with peak_bytes(dest) as peak, pytest.raises(CaptureError) as info:
        extract_zip(z, dest, max_ratio=1e9)
    assert "cannot be extracted" in messages(info.value.problems)
    assert peak[0] <= 4000 * 1000 and not dest.exists()


def test_total_limit_is_counted_while_writing(tmp_path: Path) -> None:
    # honest members, a total limit between the first and the second: the second is cut mid-write, all removed
    z = tmp_path / "two.zip"
    with zipfile.ZipFile(z, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("a.bin", os.urandom(300_000))
        zf.writestr("b.bin", os.urandom(300_000))
    dest = tmp_path / "dest"
    data = bytearray(z.read_bytes())  # declare 100 bytes for b.bin: the declared total (300,100) passes the limit
    second = data.find(b"PK\x01\x02", data.find(b"PK\x01\x02") + 1)
    data[second + 24 : second + 28] = (100).to_bytes(4, "little")
    z.write_bytes(bytes(data))
    with peak_bytes(dest) as peak, pytest.raises(CaptureError):
        extract_zip(z, dest, max_total_bytes=350_000)
    assert peak[0] <= 350_000 and not dest.exists()


@pytest.mark.parametrize(("name", "words"), [
    ("images/a\0b.png", "NUL"),
    ("images/" + "x" * 300 + ".png", "longer than 255 bytes"),
    ("../up.png", "zip-slip"),
])  # fmt: skip
def test_bad_member_names(tmp_path: Path, name: str, words: str) -> None:
    assert words in (name_problem(name) or "")


def test_file_and_folder_of_the_same_name(tmp_path: Path) -> None:
    z = tmp_path / "clash.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("x.png", b"a")
        zf.writestr("x.png/y.png", b"b")
    with pytest.raises(CaptureError) as info:
        extract_zip(z, tmp_path / "dest")
    assert "'x.png' is both a file and a folder" in messages(info.value.problems)
    assert not (tmp_path / "dest").exists()


# -------------------------------------------------------------------------------------------- transforms.json


def test_deeply_nested_json_is_a_problem_not_a_crash(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = write_capture(tmp_path / "cap")
    (root / "transforms.json").write_text('{"frames": ' + "[" * 100_000 + "]" * 100_000 + "}")
    problems = validate_capture(root)
    assert [p.file for p in problems] == ["transforms.json"] and "nested too deeply" in problems[0].message
    assert main(["validate", str(root)]) == 1
    out = capsys.readouterr()
    assert "nested too deeply" in out.out and "Traceback" not in out.out + out.err


def test_zip_of_a_folder_inside_a_folder_loads(tmp_path: Path) -> None:
    # what `zip -r teapot.zip examples/teapot` (docs/service.md) makes: examples/teapot/transforms.json
    root = write_capture(tmp_path / "cap")
    z = zip_capture(root, tmp_path / "nested.zip", top_level="examples/teapot")
    assert validate_capture(z) == []
    with load_capture(z) as capture:
        assert capture.root.name == "teapot"


# ------------------------------------------------------------------------------------------- environment maps


def test_8bit_png_envmap_is_refused_with_the_reason(tmp_path: Path) -> None:
    root = write_capture(tmp_path / "cap")
    write_image(root / "envmap.png", np.full((16, 32, 3), 0.5, np.float32))
    data = read_transforms(root)
    data["envmap"] = "envmap.png"
    write_transforms(root, data)
    problems = validate_capture(root)
    assert [p.file for p in problems] == ["envmap.png"], problems
    assert "8- or 16-bit" in problems[0].message and "EXR" in problems[0].message
    with pytest.raises(EnvmapError, match="HDR"):
        EnvironmentMap.from_file(root / "envmap.png")
    with load_capture(root) as capture, pytest.raises(EnvmapError, match="HDR"):
        capture.load_envmap()


def test_negative_noise_one_threshold_for_validate_and_loaders(tmp_path: Path) -> None:
    root = write_capture(tmp_path / "cap")  # a constant map of 1.0: the tolerance is NEGATIVE_NOISE_FRACTION
    pixels = np.ones((16, 32, 3), np.float32)
    pixels[1, 1] = -0.5 * NEGATIVE_NOISE_FRACTION
    write_image(root / "envmap.exr", pixels)
    assert validate_capture(root) == []
    with load_capture(root) as capture:
        assert capture.load_envmap().min() == 0.0
    assert float(EnvironmentMap.from_file(root / "envmap.exr").texels.min()) == 0.0
    pixels[1, 1] = -2 * NEGATIVE_NOISE_FRACTION
    write_image(root / "envmap.exr", pixels)
    assert "negative values" in messages(validate_capture(root))
    with load_capture(root) as capture, pytest.raises(EnvmapError, match="negative"):
        capture.load_envmap()
    with pytest.raises(EnvmapError, match="negative"):
        EnvironmentMap.from_file(root / "envmap.exr")


# ------------------------------------------------------------------------------------------------------ meshes


@pytest.mark.parametrize(("obj", "words"), [
    ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nf 3 2 1\n", "all 2 faces are degenerate"),
    ("v 1 1 1\nv 1 1 1\nv 1 1 1\nf 1 2 3\n", "one point"),
])  # fmt: skip
def test_degenerate_meshes_are_caught_at_validation(tmp_path: Path, obj: str, words: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    root = write_capture(tmp_path / "cap")
    (root / "mesh.obj").write_text(obj)
    problems = validate_capture(root)
    assert any(p.file == "mesh.obj" and words in p.message for p in problems), problems
    assert str(tmp_path) not in messages(problems)  # no server paths
    with pytest.raises(MeshError, match=words):
        load_mesh(root / "mesh.obj")
    assert main(["extract", str(root), "--out", str(tmp_path / "out"), "--preset", "tiny", "--init", "random"]) != 0
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err


def test_mesh_too_small_for_the_views(tmp_path: Path) -> None:
    root = write_capture(tmp_path / "cap")
    mesh = load_mesh(root / "mesh.obj", smooth=False)
    lines = [f"v {x * 1e-4:.9f} {y * 1e-4:.9f} {z * 1e-4:.9f}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    (root / "mesh.obj").write_text("\n".join(lines) + "\n")
    problems = validate_capture(root)
    assert any(p.file == "mesh.obj" and "too small for the views" in p.message for p in problems), problems


def test_obj_with_a_latin1_comment_loads(tmp_path: Path) -> None:
    root = write_capture(tmp_path / "cap")
    data = (root / "mesh.obj").read_bytes()
    (root / "mesh.obj").write_bytes(b"# mod\xe8le cr\xe9\xe9 \xe0 Paris\n" + data)
    assert validate_capture(root) == []
    assert load_mesh(root / "mesh.obj").num_faces == load_mesh(root / "mesh.obj", smooth=False).num_faces > 0


def test_cli_debug_flag_shows_the_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["extract", str(tmp_path / "cap"), "--preset", "tiny"]  # no --out: bad input
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "error: give the capture and the output" in err and "Traceback" not in err
    with pytest.raises(ValueError, match="give the capture"):
        main(["--debug", *args])


def test_full_disk_while_extracting_removes_what_was_written(tmp_path: Path) -> None:
    small = tmp_path / "small"
    small.mkdir()
    mount = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(small)], capture_output=True)
    if mount.returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        z = tmp_path / "big.zip"  # 3 MiB of random bytes for a 2 MiB file system
        with zipfile.ZipFile(z, "w") as zf:
            for i in range(3):
                zf.writestr(f"f{i}.png", os.urandom(1 << 20))
        with pytest.raises(OSError) as info:
            extract_zip(z, small / "dest")
        assert info.value.errno == errno.ENOSPC and not (small / "dest").exists()
    finally:
        subprocess.run(["umount", str(small)], check=False)
