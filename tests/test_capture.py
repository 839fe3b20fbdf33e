"""Capture format: loading (folder, zip), validation of every defect class, safe zip extraction, tonemap."""

from __future__ import annotations

import math
import shutil
import stat
import subprocess
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from capture_fixtures import read_transforms, write_capture, write_transforms, zip_capture
from conftest import ENVMAPS

from neumatex_core.capture import (
    Capture,
    CaptureError,
    Problem,
    Tonemap,
    extract_zip,
    load_capture,
    run_validate,
    validate_capture,
)
from neumatex_core.capture.archive import copy_limited
from neumatex_core.geometry.camera import look_at
from neumatex_core.imageio import write_image

STUDIO = ENVMAPS / "studio.exr"


@pytest.fixture
def cap(tmp_path: Path) -> Path:
    return write_capture(tmp_path / "cap")


def edit(root: Path, change: Callable[[dict[str, Any]], None]) -> None:
    data = read_transforms(root)
    change(data)
    write_transforms(root, data)


def find(problems: list[Problem], file: str, *words: str) -> Problem:
    """The problem naming `file` whose message holds every word (fails with the full list otherwise)."""
    for p in problems:
        if p.file == file and all(w.lower() in p.message.lower() for w in words):
            return p
    raise AssertionError(f"no problem for {file} with {words}; got:\n" + "\n".join(map(str, problems)))


# ------------------------------------------------------------------------------------------------ loading


def test_valid_folder_loads_and_validates(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = write_capture(tmp_path / "cap", n_frames=3, resolution=24, masks=True)
    capture = load_capture(root)
    assert isinstance(capture, Capture)
    assert capture.root == root.absolute() and len(capture.frames) == 3
    assert capture.mesh_path.name == "mesh.obj" and capture.envmap_path.name == "envmap.exr"
    np.testing.assert_array_equal(capture.envmap_to_world, np.eye(3))
    assert capture.envmap_scale == 1.0 and capture.tonemap == Tonemap(1.0, "srgb")
    cam = capture.frames[1].camera
    assert (cam.width, cam.height) == (24, 24) and cam.cx == 12.0
    img = capture.load_image(0)
    assert img.shape == (24, 24, 3) and img.dtype == np.float32
    mask = capture.load_mask(0)
    assert mask is not None and mask.dtype == bool and mask.shape == (24, 24) and 0 < mask.sum() < 24 * 24
    assert capture.load_envmap().shape == (16, 32, 3)
    assert capture.load_mesh().num_faces == 320
    assert validate_capture(root) == []
    assert run_validate(str(root)) == 0
    assert capsys.readouterr().out.strip() == "OK: 3 frames, mesh 320 faces, envmap 32x16"


@pytest.mark.parametrize("top_level", [None, "my_capture"])
def test_zip_loads(cap: Path, tmp_path: Path, top_level: str | None) -> None:
    z = zip_capture(cap, tmp_path / "cap.zip", top_level=top_level)
    capture = load_capture(z)
    assert len(capture.frames) == 4 and capture.frames[0].image_path.is_file()
    assert capture.load_image(3).shape == (32, 32, 3)
    assert validate_capture(z) == []
    temp_root = capture.root
    capture.close()
    assert not temp_root.exists()
    given = tmp_path / "given"
    with load_capture(z, workdir=given) as c2:
        assert c2.root.is_relative_to(given) and c2.mesh_path.is_file()
    assert c2.mesh_path.is_file()  # a caller-given folder belongs to the caller


def test_per_frame_intrinsics_override_global(cap: Path) -> None:
    write_image(cap / "images/001.png", np.full((20, 40, 3), 0.5, np.float32))

    def change(d: dict[str, Any]) -> None:
        d["frames"][1].update(fl_x=50.0, w=40, h=20, cx=20.0, cy=10.0)
        d["tonemap"] = {"exposure": 2.5, "transfer": "linear"}
        d["envmap_scale"] = 3.0
        d["envmap_to_world"] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]

    edit(cap, change)
    capture = load_capture(cap)
    c0, c1 = capture.frames[0].camera, capture.frames[1].camera
    assert (c1.fl_x, c1.width, c1.height, c1.cx, c1.cy) == (50.0, 40, 20, 20.0, 10.0)
    assert c1.fl_y == c0.fl_y  # not overridden: the global value
    assert (c0.width, c0.height) == (32, 32)
    assert capture.tonemap == Tonemap(2.5, "linear") and capture.envmap_scale == 3.0
    np.testing.assert_allclose(capture.envmap_to_world[0], [0, 0, 1])
    problems = validate_capture(cap)
    assert not any("001" in p.file for p in problems), problems


def test_load_capture_raises_with_every_structural_problem(cap: Path) -> None:
    (cap / "images/002.png").unlink()

    def change(d: dict[str, Any]) -> None:
        d["frames"][0]["transform_matrix"][0][0] = 2.0
        del d["envmap"]

    edit(cap, change)
    with pytest.raises(CaptureError) as info:
        load_capture(cap)
    problems = info.value.problems
    find(problems, "images/002.png", "not found")
    find(problems, "transforms.json", "frames[0]", "orthonormal")
    find(problems, "transforms.json", '"envmap"')
    assert len(problems) == 3


# ------------------------------------------------------------------------------------------ defect classes


def _garbage(path: Path) -> None:
    path.write_bytes(b"this is not an image" * 5)


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _set_pose(i: int, m: Any) -> Callable[[Path], None]:
    return lambda root: edit(root, lambda d: d["frames"][i].__setitem__("transform_matrix", m))


def _top(key: str, value: Any) -> Callable[[Path], None]:
    return lambda root: edit(root, lambda d: d.__setitem__(key, value))


def _envmap(pixels: np.ndarray) -> Callable[[Path], None]:
    return lambda root: write_image(root / "envmap.exr", pixels.astype(np.float32))


def _env_with(values: dict[tuple[int, int], float]) -> np.ndarray:
    env = np.ones((16, 32, 3), np.float32)
    for (r, c), v in values.items():
        env[r, c, 0] = v
    return env


SCALED = [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.2], [0, 0, 0, 1]]
MIRRORED = [[-1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.2], [0, 0, 0, 1]]
BAD_ROW = [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.2], [0, 0, 1, 1]]
NAN_POSE = [[float("nan"), 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.2], [0, 0, 0, 1]]
AWAY = look_at(np.array([0.0, 0.0, 3.2]), np.array([0.0, 0.0, 10.0]), np.array([0.0, 1.0, 0.0])).tolist()

DEFECTS: dict[str, tuple[Callable[[Path], object], str, tuple[str, ...]]] = {
    "missing image": (lambda r: (r / "images/001.png").unlink(), "images/001.png", ("not found",)),
    "garbage image": (lambda r: _garbage(r / "images/001.png"), "images/001.png", ("cannot be read",)),
    "truncated image": (lambda r: _truncate(r / "images/002.png"), "images/002.png", ("corrupt",)),
    "image size": (
        lambda r: write_image(r / "images/002.png", np.zeros((32, 30, 3), np.float32)),
        "images/002.png",
        ("30x32", "32x32"),
    ),
    "2-channel image": (
        lambda r: write_image(r / "images/000.png", np.zeros((32, 32, 2), np.float32)),
        "images/000.png",
        ("2 channels",),
    ),
    "non-finite pose": (_set_pose(1, NAN_POSE), "transforms.json", ("frames[1]", "non-finite")),
    "scaled pose": (_set_pose(2, SCALED), "transforms.json", ("frames[2]", "orthonormal")),
    "mirrored pose": (_set_pose(2, MIRRORED), "transforms.json", ("frames[2]", "determinant")),
    "last row": (_set_pose(0, BAD_ROW), "transforms.json", ("frames[0]", "last row")),
    "camera looks away": (_set_pose(3, AWAY), "images/003.png", ("does not see the mesh",)),
    "3x4 matrix": (_set_pose(0, SCALED[:3]), "transforms.json", ("frames[0].transform_matrix", "4x4")),
    "mesh no faces": (
        lambda r: (r / "mesh.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
        "mesh.obj",
        ("no triangle faces",),
    ),
    "mesh non-finite": (
        lambda r: (r / "mesh.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
        "mesh.obj",
        ("non-finite",),
    ),
    "mesh missing": (lambda r: (r / "mesh.obj").unlink(), "mesh.obj", ("not found",)),
    "mesh entry absent": (
        lambda r: edit(r, lambda d: d.pop("mesh")),
        "transforms.json",
        ('"mesh"', "mesh file"),
    ),
    "envmap missing": (lambda r: (r / "envmap.exr").unlink(), "envmap.exr", ("not found",)),
    "envmap corrupt": (lambda r: _garbage(r / "envmap.exr"), "envmap.exr", ("cannot be read",)),
    "envmap not 2:1": (_envmap(np.ones((16, 16, 3))), "envmap.exr", ("16x16", "twice as wide")),
    "envmap NaN": (_envmap(_env_with({(1, 1): np.nan, (2, 2): np.nan})), "envmap.exr", ("2 pixels are nan",)),
    "envmap inf": (_envmap(_env_with({(1, 1): np.inf})), "envmap.exr", ("1 pixels are infinite",)),
    "envmap negative": (
        _envmap(_env_with({(1, 1): -0.5, (3, 4): -0.01, (5, 5): -1e-7})),
        "envmap.exr",
        ("2 pixels have negative", "-0.5"),
    ),
    "envmap black": (_envmap(np.zeros((16, 32, 3))), "envmap.exr", ("black everywhere",)),
    "envmap_to_world": (
        _top("envmap_to_world", [[1, 0, 0], [0, 1, 0], [0, 0, 2]]),
        "transforms.json",
        ("envmap_to_world", "orthonormal"),
    ),
    "envmap_to_world mirror": (
        _top("envmap_to_world", [[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
        "transforms.json",
        ("envmap_to_world", "determinant"),
    ),
    "no frames": (_top("frames", []), "transforms.json", ("no frames",)),
    "duplicate image": (
        lambda r: edit(r, lambda d: d["frames"][3].__setitem__("file_path", "./images/000.png")),
        "images/000.png",
        ("frames[0] and frames[3]",),
    ),
    "path escapes": (
        lambda r: edit(r, lambda d: d["frames"][0].__setitem__("file_path", "../outside.png")),
        "transforms.json",
        ("frames[0]", "leaves the capture folder"),
    ),
    "intrinsics missing": (
        lambda r: edit(r, lambda d: d.pop("fl_x")),
        "transforms.json",
        ("frames[0]", "fl_x missing"),
    ),
    "bad exposure": (
        _top("tonemap", {"exposure": -1}),
        "transforms.json",
        ("tonemap.exposure", "greater than 0"),
    ),
    "bad transfer": (_top("tonemap", {"transfer": "gamma"}), "transforms.json", ("tonemap.transfer",)),
    "distortion k4": (_top("k4", 0.1), "transforms.json", ("distortion", "k4")),  # k1 k2 k3 p1 p2: undistorted
    "fisheye": (_top("camera_model", "OPENCV_FISHEYE"), "transforms.json", ("camera_model", "OPENCV_FISHEYE")),
    "transforms missing": (lambda r: (r / "transforms.json").unlink(), "transforms.json", ("not found",)),
    "transforms not json": (
        lambda r: (r / "transforms.json").write_text('{"frames": [,]}'),
        "transforms.json",
        ("not valid json", "line 1"),
    ),
    "transforms wrong type": (
        lambda r: (r / "transforms.json").write_text('{"frames": [{"file_path": 3}]}'),
        "transforms.json",
        ("frames[0].file_path", "string"),
    ),
}


@pytest.mark.parametrize("name", list(DEFECTS))
def test_each_defect_is_reported_with_its_file(tmp_path: Path, name: str) -> None:
    root = write_capture(tmp_path / "cap")
    change, file, words = DEFECTS[name]
    change(root)
    problems = validate_capture(root)
    find(problems, file, *words)


def test_schema_errors_do_not_hide_other_problems(cap: Path) -> None:
    (cap / "images/001.png").unlink()

    def change(d: dict[str, Any]) -> None:
        d["tonemap"] = {"exposure": "bright"}
        d["frames"][2]["transform_matrix"] = "identity"
        d["frames"][3]["transform_matrix"] = SCALED

    edit(cap, change)
    problems = validate_capture(cap)
    find(problems, "transforms.json", "tonemap.exposure", "number")
    find(problems, "transforms.json", "frames[2].transform_matrix", "list")
    find(problems, "transforms.json", "frames[3]", "orthonormal")
    find(problems, "images/001.png", "not found")
    assert len(problems) == 4


def test_mask_defects(tmp_path: Path) -> None:
    root = write_capture(tmp_path / "cap", masks=True)
    assert validate_capture(root) == []
    write_image(root / "masks/001.png", np.ones((16, 16, 1), np.float32))
    _garbage(root / "masks/002.png")
    (root / "masks/003.png").unlink()
    problems = validate_capture(root)
    find(problems, "masks/001.png", "16x16", "32x32")
    find(problems, "masks/002.png", "cannot be read")
    find(problems, "masks/003.png", "not found")
    assert len(problems) == 3


def test_float_noise_negatives_in_envmap_are_harmless(tmp_path: Path) -> None:
    root = write_capture(tmp_path / "cap")
    if STUDIO.is_file():  # the shared CC0 map has negatives down to -6.6e-7
        shutil.copy(STUDIO, root / "envmap.exr")
    else:
        _envmap(_env_with({(1, 1): -1e-7}))(root)
    assert validate_capture(root) == []
    with load_capture(root) as capture:
        assert capture.load_envmap().min() >= 0.0


def test_five_defects_through_the_cli_entry(tmp_path: Path) -> None:
    root = write_capture(tmp_path / "cap")
    _garbage(root / "images/000.png")
    write_image(root / "images/001.png", np.zeros((32, 30, 3), np.float32))
    _set_pose(2, SCALED)(root)
    (root / "mesh.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    _envmap(_env_with({(1, 1): np.nan, (2, 3): -0.5}))(root)
    code = (
        "from neumatex_core.capture.report import run_validate; import sys;"
        " sys.exit(run_validate(sys.argv[1]))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(root)], capture_output=True, text=True, timeout=60,
        cwd=Path(__file__).resolve().parents[1],
    )  # fmt: skip
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "Traceback" not in out
    lines = proc.stdout.splitlines()
    assert lines[0].endswith(f"problems in {root}:")

    def line_with(*words: str) -> str:
        hits = [ln for ln in lines if all(w in ln for w in words)]
        assert hits, f"no line with {words} in:\n{proc.stdout}"
        return hits[0]

    line_with("images/000.png", "cannot be read")
    line_with("images/001.png", "30x32")
    line_with("transforms.json", "frames[2]", "orthonormal")
    line_with("mesh.obj", "non-finite")
    line_with("envmap.exr", "NaN")
    line_with("envmap.exr", "negative")


def test_cli_entry_on_missing_and_non_capture_paths(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run_validate(str(tmp_path / "nope")) == 1
    assert "capture not found" in capsys.readouterr().out
    junk = tmp_path / "junk.zip"
    junk.write_bytes(b"not a zip")
    assert run_validate(str(junk)) == 1
    out = capsys.readouterr().out
    assert "1 problems in" in out and "junk.zip" in out


def test_zip_without_transforms(tmp_path: Path) -> None:
    z = tmp_path / "empty.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("a/readme.txt", "hi")
        zf.writestr("b/readme.txt", "hi")
    with pytest.raises(CaptureError) as info:
        load_capture(z)
    find(info.value.problems, "transforms.json", "not found", "empty.zip")


# ---------------------------------------------------------------------------------------- safe extraction


def _listing(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")) if folder.exists() else []


def _rejects(z: Path, tmp_path: Path, *words: str, **limits: Any) -> list[Problem]:
    before = _listing(tmp_path)
    dest = tmp_path / "dest"
    with pytest.raises(CaptureError) as info:
        extract_zip(z, dest, **limits)
    assert _listing(tmp_path) == before, "extraction left files behind"
    problems = info.value.problems
    find(problems, z.name, *words)
    return problems


def test_zip_slip_members_are_rejected(tmp_path: Path) -> None:
    z = tmp_path / "slip.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("ok.txt", "fine")
        zf.writestr("../evil.txt", "escape")
        zf.writestr("sub/../../evil2.txt", "escape")
        zf.writestr("/abs.txt", "absolute")
    problems = _rejects(z, tmp_path, "'../evil.txt'", "zip-slip")
    find(problems, "slip.zip", "sub/../../evil2.txt")
    find(problems, "slip.zip", "/abs.txt")
    assert not (tmp_path / "evil.txt").exists() and not (tmp_path / "evil2.txt").exists()


def test_symlink_member_is_rejected(tmp_path: Path) -> None:
    z = tmp_path / "link.zip"
    info = zipfile.ZipInfo("images/000.png")
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr(info, "/etc/passwd")
    _rejects(z, tmp_path, "'images/000.png'", "symbolic link")


def test_zip_bomb_is_rejected(tmp_path: Path) -> None:
    z = tmp_path / "bomb.zip"
    with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("big.bin", b"\0" * (8 * 1024**2))
    _rejects(z, tmp_path, "'big.bin'", "zip bomb")


def test_too_many_files_and_too_many_bytes(tmp_path: Path) -> None:
    z = tmp_path / "many.zip"
    with zipfile.ZipFile(z, "w") as zf:
        for i in range(10):
            zf.writestr(f"f{i}.txt", "x" * 100)
    _rejects(z, tmp_path, "10 files", "at most 5", max_files=5)
    _rejects(z, tmp_path, "1000 bytes", "at most 999", max_total_bytes=999)
    dest = extract_zip(z, tmp_path / "dest", max_files=10, max_total_bytes=1000)
    assert len(_listing(dest)) == 10


def test_lying_sizes_are_caught_while_streaming(tmp_path: Path) -> None:
    z = tmp_path / "liar.zip"
    with zipfile.ZipFile(z, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("a_first.bin", b"a" * 1000)
        zf.writestr("b_liar.bin", np.random.default_rng(0).bytes(100_000))
    data = bytearray(z.read_bytes())
    # declare 1000 bytes for the second member in the central directory (uncompressed size at +24)
    second = data.find(b"PK\x01\x02", data.find(b"PK\x01\x02") + 1)
    data[second + 24 : second + 28] = (1000).to_bytes(4, "little")
    z.write_bytes(bytes(data))
    _rejects(z, tmp_path, "'b_liar.bin'", "cannot be extracted")  # a_first.bin was written, then removed
    import io

    from neumatex_core.capture import archive

    with pytest.raises(archive._LimitExceeded):
        copy_limited(io.BytesIO(b"x" * 5000), io.BytesIO(), 4999)


def test_extraction_never_overwrites_or_removes_existing_files(cap: Path, tmp_path: Path) -> None:
    z = zip_capture(cap, tmp_path / "cap.zip")
    dest = tmp_path / "dest"
    dest.mkdir()
    (dest / "keep.txt").write_text("mine")
    (dest / "mesh.obj").write_text("mine too")
    with pytest.raises(CaptureError) as info:
        extract_zip(z, dest)
    find(info.value.problems, "cap.zip", "'mesh.obj'", "overwrite")
    assert _listing(dest) == ["keep.txt", "mesh.obj"] and (dest / "mesh.obj").read_text() == "mine too"


def test_unsafe_zip_is_reported_by_validate(cap: Path, tmp_path: Path) -> None:
    z = zip_capture(cap, tmp_path / "cap.zip")
    with zipfile.ZipFile(z, "a") as zf:
        zf.writestr("../../evil.txt", "x")
    find(validate_capture(z), "cap.zip", "zip-slip")
    with pytest.raises(CaptureError):
        load_capture(z)


# ------------------------------------------------------------------------------------------------ tonemap


def _srgb_reference(x: float) -> float:
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def test_srgb_oetf_matches_the_standard() -> None:
    xs = [0.0, 0.001, 0.0031308, 0.01, 0.18, 0.5, 1.0]
    got = Tonemap().apply(torch.tensor(xs, dtype=torch.float64))
    np.testing.assert_allclose(got.numpy(), [_srgb_reference(x) for x in xs], rtol=1e-9, atol=1e-12)
    assert math.isclose(float(got[4]), 0.461356, abs_tol=1e-6) and float(got[-1]) == pytest.approx(1.0)
    np.testing.assert_allclose(Tonemap().apply_numpy(np.array(xs)), got.numpy(), rtol=1e-9)


def test_exposure_and_clipping() -> None:
    x = torch.tensor([[0.1, 0.25, 0.6]])
    np.testing.assert_allclose(Tonemap(2.0, "linear").apply(x).numpy(), [[0.2, 0.5, 1.0]], rtol=1e-6)
    np.testing.assert_allclose(Tonemap(-1e-3 + 1.0, "linear").apply(-x).numpy(), 0.0)
    hdr = torch.tensor([[0.05, 1.0, 30.0]])
    np.testing.assert_allclose(Tonemap(4.0).apply(hdr).numpy(), Tonemap(1.0).apply(hdr * 4.0).numpy())
    with pytest.raises(ValueError):
        Tonemap(0.0)


@pytest.mark.parametrize("tonemap", [Tonemap(1.0, "srgb"), Tonemap(2.0, "srgb"), Tonemap(0.5, "linear")])
def test_display_to_linear_inverts_apply(tonemap: Tonemap) -> None:
    y = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)
    np.testing.assert_allclose(tonemap.apply(tonemap.display_to_linear(y)).numpy(), y.numpy(), atol=1e-9)
    yn = y.numpy()
    np.testing.assert_allclose(tonemap.apply_numpy(tonemap.display_to_linear(yn)), yn, atol=1e-9)
    x = torch.linspace(0.0, 1.0 / tonemap.exposure, 50, dtype=torch.float64)
    np.testing.assert_allclose(tonemap.display_to_linear(tonemap.apply(x)).numpy(), x.numpy(), atol=1e-9)


def test_tonemap_gradients_are_finite_at_zero() -> None:
    x = torch.tensor([0.0, 1e-9, 1e-3, 0.5, 2.0], requires_grad=True)
    Tonemap().apply(x).sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert float(x.grad[2]) == pytest.approx(12.92) and float(x.grad[4]) == 0.0
