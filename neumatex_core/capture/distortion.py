"""Lens distortion (OpenCV's Brown-Conrady model: k1, k2, p1, p2, k3) and undistortion to the same pinhole.

A photo taken through a lens with distortion coefficients `d` and pinhole intrinsics K is resampled into the image
an ideal pinhole camera with the *same* K would have taken (`cv2.initUndistortRectifyMap(K, d, None, K)`), so the
capture's `Camera` (a pinhole) describes the undistorted photo exactly. Pixels of the undistorted image whose source
position falls outside the distorted photo (pincushion corners) are invalid: `undistort` returns them in a mask, and
the capture treats them as not observed (`Capture.load_mask`).

Pixel convention: ours (and COLMAP's) puts pixel (i, j)'s centre at (i + 0.5, j + 0.5); OpenCV puts it at (i, j),
so the principal point handed to OpenCV is (cx - 0.5, cy - 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neumatex_core.geometry.camera import Camera


@dataclass(frozen=True)
class Distortion:
    """OpenCV radial (k1, k2, k3) and tangential (p1, p2) coefficients of normalised image coordinates."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @property
    def is_zero(self) -> bool:
        return not any((self.k1, self.k2, self.p1, self.p2, self.k3))

    def opencv(self) -> np.ndarray:
        """The coefficients in OpenCV's order (k1, k2, p1, p2, k3), float64."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=np.float64)


def opencv_matrix(camera: Camera) -> np.ndarray:
    """[3, 3] camera matrix in OpenCV's pixel convention (pixel centres at integers)."""
    return np.array([[camera.fl_x, 0.0, camera.cx - 0.5], [0.0, camera.fl_y, camera.cy - 0.5], [0.0, 0.0, 1.0]])


def undistort_maps(camera: Camera, distortion: Distortion) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every pixel of the undistorted image: where to sample the distorted photo (map_x, map_y [H, W] float32,
    OpenCV pixel coordinates) and whether that position lies inside the photo (valid [H, W] bool)."""
    import cv2

    k = opencv_matrix(camera)
    size = (camera.width, camera.height)
    map_x, map_y = cv2.initUndistortRectifyMap(k, distortion.opencv(), None, k, size, cv2.CV_32FC1)
    valid = (map_x >= -0.5) & (map_x <= camera.width - 0.5) & (map_y >= -0.5) & (map_y <= camera.height - 0.5)
    return map_x, map_y, np.asarray(valid)


def undistort(image: np.ndarray, camera: Camera, distortion: Distortion,
              nearest: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The photo [H, W, C] (float32) as the pinhole `camera` would have taken it, and its valid mask [H, W] bool.

    Bicubic resampling (clipped to the photo's own value range, so an LDR photo stays in [0, 1]); `nearest` for masks.
    Invalid pixels are 0."""
    import cv2

    if image.shape[0] != camera.height or image.shape[1] != camera.width:
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} pixels but the camera is "
                         f"{camera.width}x{camera.height}")  # fmt: skip
    map_x, map_y, valid = undistort_maps(camera, distortion)
    src = np.ascontiguousarray(image, dtype=np.float32)
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_CUBIC
    channels = [cv2.remap(np.ascontiguousarray(src[:, :, c]), map_x, map_y, interp, borderMode=cv2.BORDER_REPLICATE)
                for c in range(src.shape[2])]  # fmt: skip
    out = np.stack(channels, axis=2)
    out = np.clip(out, float(src.min()), float(src.max())) if src.size else out
    out[~valid] = 0.0
    return out.astype(np.float32), valid
