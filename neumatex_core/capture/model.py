"""The typed Capture model: frames (photo + camera + optional mask), mesh, environment map and tonemap.

A `Capture` is what `load_capture` returns once transforms.json parsed and every referenced file exists;
`validate_capture` goes further and reads every file. All paths held here are absolute.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from neumatex_core.capture.distortion import Distortion, undistort
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.mesh import Mesh, load_mesh
from neumatex_core.imageio import ImageError, read_image
from neumatex_core.lighting.envmap import load_envmap_radiance


@dataclass(frozen=True)
class Problem:
    """One reason a capture cannot be used: the file concerned (relative to the capture root, or the
    archive's name) and the reason in plain words."""

    file: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}: {self.message}"


class CaptureError(ValueError):
    """A capture that cannot be loaded; `problems` lists every reason found, not only the first."""

    def __init__(self, problems: list[Problem]):
        self.problems = list(problems)
        lines = "\n".join(f"  {p}" for p in self.problems)
        super().__init__(f"{len(self.problems)} problem(s) with the capture:\n{lines}")


@dataclass(frozen=True)
class Frame:
    """One photograph.

    image_path: absolute path of the photo (display-encoded LDR, or linear EXR when the tonemap says so).
    camera: its pinhole camera (nerfstudio/OpenGL convention, intrinsics in pixels of this image).
    mask_path: absolute path of a foreground mask of the same size (white = object), or None.
    distortion: the lens distortion of the photo file (transforms.json's k1 k2 k3 p1 p2), or None; the loaders
    undistort the photo and its mask into `camera` (a pinhole with the same intrinsics; capture/distortion.py).
    exposure: the photo's own exposure, a unitless linear multiplier (> 0) on top of the capture's tonemap exposure
    (hand-held photos each have their own; `Capture.tonemap_of`, docs/capture-format.md).
    """

    image_path: Path
    camera: Camera
    mask_path: Path | None = None
    distortion: Distortion | None = None
    exposure: float = 1.0


@dataclass(frozen=True, eq=False)  # eq=False: numpy fields make == ambiguous; captures compare by identity
class Capture:
    """A multi-view capture of one object under a known environment.

    root: absolute capture folder (the folder holding transforms.json).
    frames: the photos with their cameras, in transforms.json order.
    mesh_path: absolute path of the object's mesh (OBJ/PLY/GLB, world units, +Y up).
    envmap_path: absolute path of the equirectangular linear HDR environment map (EXR/HDR, width = 2 height).
    envmap_to_world: [3, 3] float64 rotation from envmap space to world space (Mitsuba 3 `to_world`).
    envmap_scale: unitless multiplier on the map's radiance (> 0).
    tonemap: the display transform T that turns rendered radiance into the photos' pixel values (a frame with its
    own exposure uses `tonemap_of(i)`).
    """

    root: Path
    frames: list[Frame]
    mesh_path: Path
    envmap_path: Path
    envmap_to_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    envmap_scale: float = 1.0
    tonemap: Tonemap = field(default_factory=Tonemap)
    # A zip capture extracted to a temporary folder keeps it alive here; `close()` removes it.
    workdir: tempfile.TemporaryDirectory[str] | None = field(default=None, repr=False, compare=False)

    @property
    def cameras(self) -> list[Camera]:
        return [f.camera for f in self.frames]

    def tonemap_of(self, i: int) -> Tonemap:
        """The tonemap of frame i: the capture's, its exposure multiplied by the frame's own `exposure`."""
        exposure = self.frames[i].exposure
        return self.tonemap if exposure == 1.0 else replace(self.tonemap, exposure=self.tonemap.exposure * exposure)

    @property
    def exposures(self) -> list[float]:
        """Each frame's own exposure multiplier (on top of `tonemap.exposure`), in frame order."""
        return [f.exposure for f in self.frames]

    def relative(self, path: Path) -> str:
        """`path` relative to the capture root, in POSIX form (for messages)."""
        try:
            return Path(path).relative_to(self.root).as_posix()
        except ValueError:
            return str(path)

    def load_image(self, i: int) -> np.ndarray:
        """Photo of frame i as float32 [H, W, 3] in the file's encoding (grey replicated, alpha dropped).

        A photo with lens distortion comes back undistorted into the frame's pinhole camera (pixels with no source
        are 0; `load_mask` leaves them out). Raises ImageError naming the file when it cannot be read or has 2 or
        more than 4 channels.
        """
        frame = self.frames[i]
        rgb = to_rgb(read_image(frame.image_path), frame.image_path)
        if frame.distortion is not None:
            rgb = undistort(rgb, frame.camera, frame.distortion)[0]
        return rgb

    def load_mask(self, i: int) -> np.ndarray | None:
        """Foreground mask of frame i as bool [H, W] (first channel > 0.5); None without a mask. For a photo with
        lens distortion: the undistorted mask, without the pixels that undistortion could not fill (a mask of those
        alone when the frame has no mask file and some pixels lack a source)."""
        frame = self.frames[i]
        mask = None if frame.mask_path is None else np.asarray(read_image(frame.mask_path)[:, :, 0] > 0.5)
        if frame.distortion is None:
            return mask
        if mask is None:
            valid = undistort(np.ones((frame.camera.height, frame.camera.width, 1), np.float32), frame.camera,
                              frame.distortion, nearest=True)[1]  # fmt: skip
            return None if valid.all() else valid
        moved, valid = undistort(mask[:, :, None].astype(np.float32), frame.camera, frame.distortion, nearest=True)
        return np.asarray((moved[:, :, 0] > 0.5) & valid)

    def load_envmap(self) -> np.ndarray:
        """The environment map as float32 [H, W, 3] linear radiance, multiplied by `envmap_scale`.

        Raises EnvmapError naming the file when the map is not usable (not HDR, not 2:1, NaN, negatives beyond
        float noise: `neumatex_core.lighting.envmap.read_envmap`, the checks of `validate_capture`); float-noise
        negatives are clamped to 0. Rows run from +Y (top) to -Y, in envmap space (apply `envmap_to_world`).
        """
        rgb = load_envmap_radiance(self.envmap_path)
        return (rgb * np.float32(self.envmap_scale)).astype(np.float32)

    def load_mesh(self, smooth: bool = True) -> Mesh:
        """The object's mesh (raises MeshError naming the file)."""
        return load_mesh(self.mesh_path, smooth=smooth)

    def close(self) -> None:
        """Remove the temporary folder a zip capture was extracted to (no-op for folders)."""
        if self.workdir is not None:
            self.workdir.cleanup()

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def to_rgb(pixels: np.ndarray, path: Path | str) -> np.ndarray:
    """[H, W, C] float32 with C in {1, 3, 4} -> [H, W, 3] (grey replicated, alpha dropped)."""
    c = pixels.shape[2]
    if c == 1:
        return np.repeat(pixels, 3, axis=2)
    if c in (3, 4):
        return np.ascontiguousarray(pixels[:, :, :3])
    raise ImageError(f"{path}: has {c} channels; expected 1 (grey), 3 (RGB) or 4 (RGBA)")
