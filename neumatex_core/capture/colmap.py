"""`neumatex import colmap`: a COLMAP sparse model (cameras + images, binary or text) -> a capture folder.

COLMAP stores, per image, the world-to-camera rotation as a unit quaternion qvec = (w, x, y, z) and the translation
tvec, in OpenCV camera axes (+X right, +Y down, +Z forward): x_cam = R(qvec) x_world + tvec. Our capture format wants
camera-to-world in OpenGL axes (+X right, +Y up, -Z forward), so

    c2w = [[R^T, -R^T tvec], [0, 1]] @ diag(1, -1, -1, 1)

(the second and third camera axes flip). Pixel coordinates agree: COLMAP, like us, puts the centre of the top-left
pixel at (0.5, 0.5), so cx, cy carry over unchanged. Camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL
and OPENCV (their parameters are a pinhole plus OpenCV's k1 k2 p1 p2); the photos are undistorted on import into a
pinhole camera with the same intrinsics (capture/distortion.py), so the capture has no distortion left. Others
(fisheye, FULL_OPENCV, FOV, ...) are refused naming the file and the model.

File layouts (COLMAP's documentation, "Output format"): cameras.bin = uint64 count, then per camera int32 id, int32
model id, uint64 width, uint64 height, float64 params[n(model)]; images.bin = uint64 count, then per image int32 id,
float64 qvec[4], float64 tvec[3], int32 camera id, NUL-terminated name, uint64 n_points, (float64 x, float64 y,
int64 point3D id) x n_points; all little-endian. cameras.txt: `ID MODEL WIDTH HEIGHT PARAMS...`; images.txt: two
lines per image, `ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and its 2-D points; `#` starts a comment.

The mesh must be in the COLMAP model's world frame (e.g. reconstructed from the same model); `neumatex validate` then
checks that every camera sees it.
"""

from __future__ import annotations

import json
import shutil
import struct
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from neumatex_core.capture.distortion import Distortion, undistort
from neumatex_core.config import option
from neumatex_core.geometry.camera import Camera

# COLMAP's camera model ids and parameter counts (src/colmap/sensor/models.h).
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}  # fmt: skip
MODEL_PARAMS = {name: n for name, n in CAMERA_MODELS.values()}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


class ColmapError(ValueError):
    """A COLMAP model that cannot be imported; the message names the file and the reason."""


@dataclass(frozen=True)
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class ColmapImage:
    id: int
    qvec: tuple[float, float, float, float]  # (w, x, y, z), world-to-camera rotation
    tvec: tuple[float, float, float]
    camera_id: int
    name: str


# ----------------------------------------------------------------------------------------------- reading


class _Reader:
    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def take(self, fmt: str) -> tuple[int | float, ...]:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: file ends early (truncated at byte {len(self.data)})")
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def name(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise ColmapError(f"{self.path}: file ends inside an image name (truncated)")
        raw = self.data[self.pos:end]
        self.pos = end + 1
        return raw.decode("utf-8", errors="replace")


def _check_camera(path: Path, cam: ColmapCamera) -> ColmapCamera:
    if cam.model not in MODEL_PARAMS:
        raise ColmapError(f"{path}: camera {cam.id} has an unknown camera model {cam.model!r}")
    if len(cam.params) != MODEL_PARAMS[cam.model]:
        raise ColmapError(f"{path}: camera {cam.id} ({cam.model}) has {len(cam.params)} parameters; the model has "
                          f"{MODEL_PARAMS[cam.model]}")  # fmt: skip
    if cam.width <= 0 or cam.height <= 0 or not np.isfinite(cam.params).all():
        raise ColmapError(f"{path}: camera {cam.id} has a size of {cam.width}x{cam.height} or non-finite parameters")
    return cam


def read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    r, out = _Reader(path), {}
    (count,) = r.take("<Q")
    for _ in range(int(count)):
        cam_id, model_id, width, height = (int(v) for v in r.take("<iiQQ"))
        if model_id not in CAMERA_MODELS:
            raise ColmapError(f"{path}: camera {cam_id} has an unknown camera model id {model_id}")
        model, n = CAMERA_MODELS[model_id]
        params = tuple(float(v) for v in r.take(f"<{n}d"))
        out[cam_id] = _check_camera(path, ColmapCamera(cam_id, model, width, height, params))
    return out


def read_images_binary(path: Path) -> dict[int, ColmapImage]:
    r, out = _Reader(path), {}
    (count,) = r.take("<Q")
    for _ in range(int(count)):
        (image_id,) = r.take("<i")
        q = tuple(float(v) for v in r.take("<4d"))
        t = tuple(float(v) for v in r.take("<3d"))
        (camera_id,) = r.take("<i")
        name = r.name()
        (n_points,) = r.take("<Q")
        r.take(f"<{3 * int(n_points)}d")  # x, y (float64) and point3D id (int64): 24 bytes each, unused
        out[int(image_id)] = ColmapImage(int(image_id), q, t, int(camera_id), name)  # type: ignore[arg-type]
    return out


def _lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ColmapError(f"{path}: is not UTF-8 text") from None
    return [(n, line) for n, line in enumerate(text.splitlines(), 1)]


def read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    out = {}
    for n, line in _lines(path):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        try:
            cam = ColmapCamera(int(parts[0]), parts[1], int(parts[2]), int(parts[3]),
                               tuple(float(p) for p in parts[4:]))  # fmt: skip
        except (ValueError, IndexError):
            raise ColmapError(f"{path}: line {n} is not `CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`") from None
        out[cam.id] = _check_camera(path, cam)
    return out


def read_images_text(path: Path) -> dict[int, ColmapImage]:
    out: dict[int, ColmapImage] = {}
    expect_points = False
    for n, line in _lines(path):
        if line.lstrip().startswith("#"):
            continue
        if expect_points:  # the second line of an image (its 2-D points; may be empty)
            expect_points = False
            continue
        if not line.strip():
            continue
        parts = line.split(maxsplit=9)
        try:
            image = ColmapImage(int(parts[0]), tuple(float(p) for p in parts[1:5]),  # type: ignore[arg-type]
                                tuple(float(p) for p in parts[5:8]), int(parts[8]), parts[9].strip())  # type: ignore[arg-type]
        except (ValueError, IndexError):
            raise ColmapError(f"{path}: line {n} is not `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`") from None
        out[image.id] = image
        expect_points = True
    return out


def read_model(sparse_dir: str | Path) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage], str]:
    """Cameras and images of the COLMAP model in `sparse_dir` (binary files when present, else text), and which
    form was read ("binary" or "text")."""
    folder = Path(sparse_dir)
    if (folder / "cameras.bin").is_file() and (folder / "images.bin").is_file():
        return read_cameras_binary(folder / "cameras.bin"), read_images_binary(folder / "images.bin"), "binary"
    if (folder / "cameras.txt").is_file() and (folder / "images.txt").is_file():
        return read_cameras_text(folder / "cameras.txt"), read_images_text(folder / "images.txt"), "text"
    raise ColmapError(f"{folder}: no COLMAP model (expected cameras.bin + images.bin or cameras.txt + images.txt)")


# -------------------------------------------------------------------------------------------- conversion


def qvec_to_rotation(qvec: tuple[float, float, float, float] | np.ndarray) -> np.ndarray:
    """[3, 3] rotation of the quaternion (w, x, y, z) (normalised first)."""
    q = np.asarray(qvec, dtype=np.float64)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def camera_to_world(image: ColmapImage) -> np.ndarray:
    """[4, 4] camera-to-world in OpenGL axes (our capture format) of a COLMAP image's world-to-camera pose."""
    rot = qvec_to_rotation(image.qvec)
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T
    c2w[:3, 3] = -rot.T @ np.asarray(image.tvec, dtype=np.float64)
    return c2w @ OPENGL_FROM_OPENCV


def intrinsics(camera: ColmapCamera, path: str = "cameras") -> tuple[float, float, float, float, Distortion]:
    """(fl_x, fl_y, cx, cy, distortion) of a supported COLMAP camera; ColmapError naming `path` and the model
    otherwise."""
    p = camera.params
    if camera.model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2], Distortion()
    if camera.model == "PINHOLE":
        return p[0], p[1], p[2], p[3], Distortion()
    if camera.model == "SIMPLE_RADIAL":
        return p[0], p[0], p[1], p[2], Distortion(k1=p[3])
    if camera.model == "RADIAL":
        return p[0], p[0], p[1], p[2], Distortion(k1=p[3], k2=p[4])
    if camera.model == "OPENCV":
        return p[0], p[1], p[2], p[3], Distortion(k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    raise ColmapError(f"{path}: camera {camera.id} uses the COLMAP camera model {camera.model}, which cannot be "
                      f"imported (supported: {', '.join(SUPPORTED_MODELS)}); re-run COLMAP with one of those or "
                      "undistort with `colmap image_undistorter` first")  # fmt: skip


def pinhole(camera: ColmapCamera, image: ColmapImage, path: str = "cameras") -> tuple[Camera, Distortion]:
    """Our pinhole Camera of a COLMAP image and the lens distortion its photo has."""
    fx, fy, cx, cy, dist = intrinsics(camera, path)
    return Camera(camera_to_world(image), fx, fy, cx, cy, camera.width, camera.height), dist


# ------------------------------------------------------------------------------------------------ import


@dataclass
class ImportResult:
    out: Path
    frames: int
    form: str  # "binary" or "text"
    undistorted: int  # photos that had lens distortion
    masked: int  # photos with pixels undistortion could not fill (masks written)


def _photo_kind(path: Path) -> Literal["float", "uint16", "uint8"]:
    import OpenImageIO as oiio

    from neumatex_core.imageio import ImageError

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot be read as an image ({oiio.geterror() or 'unknown format'})")
    base = inp.spec().format.basetype
    inp.close()
    if base in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE):
        return "float"
    return "uint16" if base in (oiio.UINT16, oiio.INT16) else "uint8"


def import_colmap(sparse_dir: str | Path, images_dir: str | Path, mesh: str | Path, envmap: str | Path,
                  out: str | Path, envmap_scale: float = 1.0, envmap_to_world: np.ndarray | None = None,
                  exposure: float = 1.0, transfer: Literal["srgb", "linear"] = "srgb",
                  progress: Callable[[int, int], None] | None = None) -> ImportResult:
    """Write a capture folder `out` (created; must not exist) from a COLMAP model: transforms.json with each image's
    pinhole camera (sorted by image name), the photos undistorted into images/ (PNG, 16-bit PNG for 16-bit photos,
    EXR for float ones; masks/ where undistortion leaves pixels without a source), and copies of the mesh and the
    environment map. Raises ColmapError (bad model), ImageError (unreadable photo) or ValueError."""
    from neumatex_core.imageio import read_image, write_image

    sparse_dir, images_dir, out = Path(sparse_dir), Path(images_dir), Path(out)
    mesh, envmap = Path(mesh), Path(envmap)
    for what, p in (("mesh", mesh), ("environment map", envmap)):
        if not p.is_file():
            raise ValueError(f"{p}: {what} file not found")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: already exists; give a new folder for the capture")
    cameras, images, form = read_model(sparse_dir)
    cam_file = str(sparse_dir / ("cameras.bin" if form == "binary" else "cameras.txt"))
    img_file = str(sparse_dir / ("images.bin" if form == "binary" else "images.txt"))
    if not images:
        raise ColmapError(f"{img_file}: has no images")
    for cam in cameras.values():
        intrinsics(cam, cam_file)  # refuse unsupported models before any work
    ordered = sorted(images.values(), key=lambda im: im.name)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    frames, names, undistorted, masked = [], set(), 0, 0
    try:
        for k, im in enumerate(ordered):
            if im.camera_id not in cameras:
                raise ColmapError(f"{img_file}: image {im.id} ({im.name}) names camera {im.camera_id}, which "
                                  f"{cam_file} does not have")  # fmt: skip
            camera, dist = pinhole(cameras[im.camera_id], im, cam_file)
            src = images_dir / im.name
            if not src.is_file():
                raise ValueError(f"{src}: photo of COLMAP image {im.id} not found in {images_dir}")
            kind = _photo_kind(src)
            pixels = read_image(src, orient_upright=False)  # COLMAP measured the pixels as stored (no EXIF turn)
            if pixels.shape[:2] != (camera.height, camera.width):
                raise ValueError(f"{src}: is {pixels.shape[1]}x{pixels.shape[0]} pixels but COLMAP camera "
                                 f"{im.camera_id} is {camera.width}x{camera.height}")  # fmt: skip
            valid = None
            if not dist.is_zero:
                pixels, valid = undistort(pixels, camera, dist)
                undistorted += 1
            rel = Path(im.name).with_suffix(".exr" if kind == "float" else ".png").as_posix()
            if rel in names:
                raise ValueError(f"{src}: two COLMAP images would both be written as images/{rel}")
            names.add(rel)
            write_image(tmp / "images" / rel,
                        np.round(np.clip(pixels, 0, 1) * 65535).astype(np.uint16) if kind == "uint16" else pixels)
            entry = {"file_path": f"images/{rel}", "transform_matrix": camera.c2w.tolist(), "fl_x": camera.fl_x,
                     "fl_y": camera.fl_y, "cx": camera.cx, "cy": camera.cy, "w": camera.width, "h": camera.height,
                     "colmap_image_id": im.id}  # fmt: skip
            if valid is not None and not valid.all():
                mask_rel = f"masks/{Path(rel).with_suffix('.png').as_posix()}"
                write_image(tmp / mask_rel, valid.astype(np.float32)[:, :, None])
                entry["mask_path"] = mask_rel
                masked += 1
            frames.append(entry)
            if progress is not None:
                progress(k + 1, len(ordered))
        mesh_name, env_name = "mesh" + mesh.suffix.lower(), "envmap" + envmap.suffix.lower()
        shutil.copyfile(mesh, tmp / mesh_name)
        shutil.copyfile(envmap, tmp / env_name)
        data: dict[str, object] = {"mesh": mesh_name, "envmap": env_name, "envmap_scale": float(envmap_scale),
                                   "tonemap": {"exposure": float(exposure), "transfer": transfer},
                                   "source": f"COLMAP model {sparse_dir} ({form}); photos undistorted on import",
                                   "frames": frames}  # fmt: skip
        if envmap_to_world is not None:
            data["envmap_to_world"] = np.asarray(envmap_to_world, dtype=np.float64).reshape(3, 3).tolist()
        (tmp / "transforms.json").write_text(json.dumps(data, indent=1) + "\n")
        for p in [tmp, *tmp.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)  # mkdtemp made the folder 0700
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ImportResult(out, len(frames), form, undistorted, masked)


# ---------------------------------------------------------------------------------------------------- CLI


@dataclass
class ImportColmapConfig:
    """`neumatex import colmap SPARSE_DIR IMAGES_DIR --mesh M --envmap E --out CAPTURE`: a COLMAP sparse model
    (cameras/images .bin or .txt; PINHOLE, SIMPLE_RADIAL, OPENCV, ...) -> a capture folder, the photos undistorted
    into pinhole cameras, the mesh and map copied in. The mesh must be in the COLMAP model's world frame."""

    sparse: str = option("", "COLMAP model folder (cameras.bin + images.bin, or cameras.txt + images.txt)",
                         positional=True)
    images: str = option("", "folder of the photos (COLMAP's image names are relative to it)", positional=True)
    mesh: str = option("", "the object's mesh, in the COLMAP model's world frame")
    envmap: str = option("", "equirectangular linear HDR environment map (EXR/HDR)")
    out: str = option("", "capture folder to write (must not exist)")
    envmap_scale: float = option(1.0, "multiplier on the map's radiance (transforms.json envmap_scale)")
    envmap_to_world: str = option("", "3x3 rotation from the map to the world, 9 comma-separated numbers row by "
                                  "row (--envmap-to-world=... when the first is negative)")
    exposure: float = option(1.0, "tonemap exposure of the photos")
    transfer: Literal["srgb", "linear"] = option("srgb", "tonemap transfer function of the photos")


def run_import_colmap(cfg: ImportColmapConfig) -> int:
    if not (cfg.sparse and cfg.images and cfg.mesh and cfg.envmap and cfg.out):
        raise ValueError("give SPARSE_DIR IMAGES_DIR --mesh M --envmap E --out CAPTURE")
    rot = None
    if cfg.envmap_to_world:
        try:
            rot = np.array([float(v) for v in cfg.envmap_to_world.split(",")]).reshape(3, 3)
        except ValueError:
            raise ValueError("--envmap-to-world: expected 9 comma-separated numbers, got "
                             f"{cfg.envmap_to_world!r}") from None
    result = import_colmap(cfg.sparse, cfg.images, cfg.mesh, cfg.envmap, cfg.out, cfg.envmap_scale, rot,
                           cfg.exposure, cfg.transfer)  # fmt: skip
    print(f"wrote {result.out}: {result.frames} frames from the {result.form} COLMAP model, {result.undistorted} "
          f"photos undistorted ({result.masked} with masks of the pixels undistortion could not fill); check it with "
          f"`neumatex validate {result.out}`")
    return 0
