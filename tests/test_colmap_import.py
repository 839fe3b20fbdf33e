"""`neumatex import colmap`: a COLMAP model (text and binary, written here by a small writer that follows COLMAP's
documented layout) of the bundled example's random-pose photos, the photos distorted through OPENCV / SIMPLE_RADIAL
lenses, imported back: the cameras equal the originals, the undistorted photos match the originals, mesh points
project where COLMAP's own formula puts them, and an extraction runs end to end from the imported capture. Also a
nerfstudio transforms.json with distortion coefficients, undistorted at load."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from neumatex_core.capture import load_capture, validate_capture
from neumatex_core.capture.colmap import ColmapError, import_colmap, read_model
from neumatex_core.cli import main
from neumatex_core.geometry.camera import Camera
from neumatex_core.imageio import read_image, write_image

SOURCE = Path(__file__).resolve().parents[1] / "examples" / "coat-teapot" / "photos"  # 6 photos, 256 px, clean
# One camera per supported family: OPENCV (barrel + tangential), SIMPLE_RADIAL (pincushion: corners without source),
# PINHOLE. Frame i uses camera LENSES[i % 3].
LENSES = [("OPENCV", (-0.12, 0.03, 0.002, -0.001)), ("SIMPLE_RADIAL", (0.08,)), ("PINHOLE", ())]
MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "OPENCV_FISHEYE": 5}
# Measured (2026-11-25) PSNR of the undistorted photo against the original over the valid pixels: 43.6 dB at worst
# (frame 3, OPENCV; the others 48.6 dB), against 21.1-30.8 dB for the photos through the lens, not undistorted. What
# is lost: bicubic resampling twice (the lens simulated here, then the import) and the 8-bit PNG in between. The bound
# sits 3.6 dB under the worst measured value; a wrong axis, principal point or coefficient order falls below 31 dB.
MIN_PSNR_DB = 40.0


# ------------------------------------------------------------------------------------------- COLMAP writer


def rotation_to_qvec(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method), w >= 0."""
    tr = np.trace(r)
    if tr > 0:
        s = 2 * np.sqrt(tr + 1)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    qv = np.asarray(q)
    return qv if qv[0] >= 0 else -qv


def world_to_camera(c2w_opengl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's (R, t): x_cam = R x_world + t in OpenCV axes, from our OpenGL camera-to-world."""
    c2w_cv = np.asarray(c2w_opengl) @ np.diag([1.0, -1.0, -1.0, 1.0])
    r = c2w_cv[:3, :3].T
    return r, -r @ c2w_cv[:3, 3]


def lens_params(model: str, cam: Camera, coeffs: tuple[float, ...]) -> list[float]:
    if model == "PINHOLE":
        return [cam.fl_x, cam.fl_y, cam.cx, cam.cy]
    if model == "SIMPLE_RADIAL":
        return [cam.fl_x, cam.cx, cam.cy, *coeffs]
    return [cam.fl_x, cam.fl_y, cam.cx, cam.cy, *coeffs]


def opencv_coeffs(model: str, coeffs: tuple[float, ...]) -> np.ndarray:
    full = {"PINHOLE": (0, 0, 0, 0), "SIMPLE_RADIAL": (coeffs[0] if coeffs else 0, 0, 0, 0), "OPENCV": coeffs}[model]
    return np.array([*full, 0.0], dtype=np.float64)


def write_colmap(folder: Path, cameras: list[tuple[int, str, int, int, list[float]]],
                 images: list[tuple[int, np.ndarray, np.ndarray, int, str]], binary: bool) -> None:
    """cameras: (id, model, w, h, params); images: (id, qvec, tvec, camera id, name). Each image gets two 2-D
    points so the readers must skip them."""
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        with open(folder / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", len(cameras)))
            for cid, model, w, h, params in cameras:
                f.write(struct.pack("<iiQQ", cid, MODEL_IDS[model], w, h))
                f.write(struct.pack(f"<{len(params)}d", *params))
        with open(folder / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", len(images)))
            for iid, q, t, cid, name in images:
                f.write(struct.pack("<i4d3di", iid, *q, *t, cid))
                f.write(name.encode() + b"\0")
                f.write(struct.pack("<Q", 2))
                f.write(struct.pack("<ddq", 10.5, 20.5, 7) + struct.pack("<ddq", 1.0, 2.0, -1))
        return
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    lines += [f"{cid} {model} {w} {h} " + " ".join(repr(float(p)) for p in params)
              for cid, model, w, h, params in cameras]  # fmt: skip
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, "
             "NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]  # fmt: skip
    for n, (iid, q, t, cid, name) in enumerate(images):
        lines.append(" ".join([str(iid), *(repr(float(v)) for v in (*q, *t)), str(cid), name]))
        lines.append("" if n % 2 else "10.5 20.5 7 1.0 2.0 -1")  # empty points lines happen too
    (folder / "images.txt").write_text("\n".join(lines) + "\n")


def distort_photo(image: np.ndarray, cam: Camera, dist: np.ndarray) -> np.ndarray:
    """The photo a lens with OpenCV coefficients `dist` would have taken: each distorted pixel samples the ideal
    (pinhole) image where cv2.undistortPoints sends it (the inverse of the map the importer uses)."""
    k = np.array([[cam.fl_x, 0, cam.cx - 0.5], [0, cam.fl_y, cam.cy - 0.5], [0, 0, 1]], dtype=np.float64)
    ys, xs = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)[:, None, :]
    ideal = cv2.undistortPoints(pts, k, dist, P=k).reshape(cam.height, cam.width, 2).astype(np.float32)
    channels = [cv2.remap(np.ascontiguousarray(image[:, :, c]), ideal[..., 0], ideal[..., 1], cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REPLICATE) for c in range(image.shape[2])]  # fmt: skip
    return np.clip(np.stack(channels, axis=2), 0, 1)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    mse = float(((a - b) ** 2)[mask].mean())
    return 10 * np.log10(1.0 / max(mse, 1e-12))


@pytest.fixture(scope="module")
def colmap_scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The example's photos through the lenses, and its cameras as a COLMAP model in both forms."""
    root = tmp_path_factory.mktemp("colmap")
    original = load_capture(SOURCE)
    photos = root / "photos"
    cameras, images, truth = [], [], []
    for i, frame in enumerate(original.frames):  # one COLMAP camera per photo: their focal lengths differ
        cam = frame.camera
        model, coeffs = LENSES[i % 3]
        cameras.append((i + 1, model, cam.width, cam.height, lens_params(model, cam, coeffs)))
        name = f"sub/IMG_{i:04d}.png" if i == 1 else f"IMG_{i:04d}.png"  # names may hold folders
        photo = original.load_image(i)
        write_image(photos / name, distort_photo(photo, cam, opencv_coeffs(model, coeffs)))
        r, t = world_to_camera(cam.c2w)
        images.append((10 + i, rotation_to_qvec(r), t, i + 1, name))
        truth.append((name, cam, photo))
    write_colmap(root / "sparse_txt", cameras, images, binary=False)
    write_colmap(root / "sparse_bin", cameras, images, binary=True)
    return {"root": root, "original": original, "photos": photos, "truth": truth}


def import_args(scene: dict, sparse: str, out: Path) -> list[str]:
    orig = scene["original"]
    return ["import", "colmap", str(scene["root"] / sparse), str(scene["photos"]), "--mesh", str(orig.mesh_path),
            "--envmap", str(orig.envmap_path), "--out", str(out), "--envmap-scale", repr(orig.envmap_scale),
            "--envmap-to-world=" + ",".join(repr(float(v)) for v in orig.envmap_to_world.ravel())]  # fmt: skip


@pytest.mark.parametrize("sparse", ["sparse_txt", "sparse_bin"])
def test_import_gives_the_original_cameras_and_undistorted_photos(colmap_scene: dict, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str],
                                                                   sparse: str) -> None:
    scene = colmap_scene
    out = tmp_path / "capture"
    assert main(import_args(scene, sparse, out)) == 0, capsys.readouterr().err
    form = "binary" if sparse == "sparse_bin" else "text"
    assert f"6 frames from the {form} COLMAP model, 4 photos undistorted" in capsys.readouterr().out
    assert validate_capture(out) == []
    with load_capture(out) as cap:
        assert cap.envmap_scale == pytest.approx(scene["original"].envmap_scale)
        np.testing.assert_allclose(cap.envmap_to_world, scene["original"].envmap_to_world, atol=1e-12)
        names = [f.image_path.relative_to(out).as_posix() for f in cap.frames]
        assert names == ["images/IMG_0000.png", "images/IMG_0002.png", "images/IMG_0003.png",
                         "images/IMG_0004.png", "images/IMG_0005.png", "images/sub/IMG_0001.png"]  # sorted by name
        by_name = {Path(n).stem: i for i, n in enumerate(names)}
        mesh_points = cap.load_mesh().vertices.astype(np.float64)[::7]
        worst = 99.0
        for name, cam, photo in scene["truth"]:
            i = by_name[Path(name).stem]
            got = cap.frames[i].camera
            assert cap.frames[i].distortion is None  # undistorted on import: a plain pinhole capture
            np.testing.assert_allclose(got.c2w, cam.c2w, atol=1e-5)
            np.testing.assert_allclose([got.fl_x, got.fl_y, got.cx, got.cy], [cam.fl_x, cam.fl_y, cam.cx, cam.cy],
                                       atol=1e-5)  # fmt: skip
            assert (got.width, got.height) == (cam.width, cam.height)
            # COLMAP's own projection (x_cam = R X + t, OpenCV axes, pixel = f x/z + c) lands where ours does.
            r, t = world_to_camera(cam.c2w)
            p = mesh_points @ r.T + t
            colmap_px = np.stack([cam.fl_x * p[:, 0] / p[:, 2] + cam.cx, cam.fl_y * p[:, 1] / p[:, 2] + cam.cy], 1)
            ours, front = got.project(mesh_points)
            assert front.all() and (p[:, 2] > 0).all()
            np.testing.assert_allclose(ours, colmap_px, atol=1e-6)
            # The undistorted photo is the original, over the pixels the lens saw.
            loaded, mask = cap.load_image(i), cap.load_mask(i)
            valid = np.ones(loaded.shape[:2], bool) if mask is None else mask
            lens = LENSES[int(Path(name).stem[-1]) % 3][0]
            assert (mask is not None) == (lens == "SIMPLE_RADIAL")  # pincushion: corners without a source
            if mask is not None:
                assert 0.9 < valid.mean() < 1.0
            score = psnr(loaded, photo, valid)
            if lens != "PINHOLE":
                raw = read_image(scene["photos"] / name)[:, :, :3]
                assert psnr(raw, photo, valid) < score - 10  # undistortion is what makes them match
                worst = min(worst, score)
            else:
                assert score > 60  # no lens: the 8-bit photo is copied as it is (measured: identical)
        assert worst > MIN_PSNR_DB, worst


def test_unsupported_camera_models_and_broken_files_are_refused_by_name(colmap_scene: dict, tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    sparse = tmp_path / "fisheye"
    shutil.copytree(colmap_scene["root"] / "sparse_txt", sparse)
    lines = (sparse / "cameras.txt").read_text().splitlines()
    cid, _, w, h, f, cx, cy, k = lines[3].split()  # camera 2 (SIMPLE_RADIAL) -> a fisheye with its 8 parameters
    lines[3] = " ".join([cid, "OPENCV_FISHEYE", w, h, f, f, cx, cy, k, "0", "0", "0"])
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    orig = colmap_scene["original"]
    with pytest.raises(ColmapError, match=r"cameras\.txt: camera 2 uses the COLMAP camera model OPENCV_FISHEYE"):
        import_colmap(sparse, colmap_scene["photos"], orig.mesh_path, orig.envmap_path, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    args = import_args(colmap_scene, "sparse_txt", tmp_path / "out2")
    args[2] = str(sparse)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "OPENCV_FISHEYE" in err and "cameras.txt" in err and "Traceback" not in err
    truncated = tmp_path / "truncated"
    shutil.copytree(colmap_scene["root"] / "sparse_bin", truncated)
    data = (truncated / "images.bin").read_bytes()
    (truncated / "images.bin").write_bytes(data[: len(data) // 2])
    with pytest.raises(ColmapError, match=r"images\.bin: file ends"):
        read_model(truncated)


def test_nerfstudio_distortion_is_undistorted_at_load(colmap_scene: dict, tmp_path: Path) -> None:
    """transforms.json frames with k1 k2 p1 p2 (nerfstudio's OPENCV camera) load undistorted, as the import does."""
    root = tmp_path / "ns"
    shutil.copytree(SOURCE, root)
    data = json.loads((root / "transforms.json").read_text())
    by_stem = {Path(n).stem: (n, c) for n, c, _ in colmap_scene["truth"]}
    for i, frame in enumerate(data["frames"]):
        name, _ = by_stem[f"IMG_{i:04d}"]
        model, coeffs = LENSES[i % 3]
        k1, k2, p1, p2, _ = opencv_coeffs(model, coeffs)
        frame.update(k1=k1, k2=k2, p1=p1, p2=p2, camera_model="OPENCV")
        shutil.copyfile(colmap_scene["photos"] / name, root / frame["file_path"])
    (root / "transforms.json").write_text(json.dumps(data))
    assert validate_capture(root) == []
    with load_capture(root) as cap:
        for i in range(len(cap.frames)):
            photo = colmap_scene["truth"][i][2]
            mask = cap.load_mask(i)
            assert mask is not None  # the example's own masks, undistorted
            assert psnr(cap.load_image(i), photo, mask) > MIN_PSNR_DB
    data["frames"][0]["camera_model"] = "OPENCV_FISHEYE"
    data["frames"][1]["k4"] = 0.01
    (root / "transforms.json").write_text(json.dumps(data))
    text = "\n".join(str(p) for p in validate_capture(root))
    assert "frames[0]" in text and "OPENCV_FISHEYE" in text and "frames[1]" in text and "k4" in text


def test_extraction_runs_end_to_end_from_the_imported_capture(colmap_scene: dict, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    capture = tmp_path / "capture"
    assert main(import_args(colmap_scene, "sparse_bin", capture)) == 0
    out = tmp_path / "asset"
    code = main(["extract", str(capture), "--out", str(out), "--preset", "tiny", "--init", "random", "--device", "cpu",
                 "--no-progress"])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0, captured.err
    metrics = json.loads((out / "manifest.json").read_text())["metrics"]
    assert np.isfinite(metrics["psnr_photos"]) and metrics["psnr_photos"] > 10
    views = json.loads((tmp_path / ".asset.work" / "prepare_views" / "views.json").read_text())
    assert views["source"].startswith("blended from 6 photos")
