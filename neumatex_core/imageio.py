"""Image files through OpenImageIO: PNG, JPEG, EXR, HDR, TIFF; 8/16-bit integer and float.

Pixels come back as float32 [H, W, C]: integer formats normalised to [0, 1] (still in the file's encoding,
e.g. sRGB for a photo), float formats as stored (linear HDR for EXR/HDR), turned upright by the file's EXIF
Orientation tag (a phone's JPEG stored sideways loads as it is displayed; what PIL's ImageOps.exif_transpose does).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np


class ImageError(ValueError):
    """An image file that cannot be used; the message names the file and the reason."""


def orient(pixels: np.ndarray, orientation: int) -> np.ndarray:
    """[H, W, C] pixels as stored -> as displayed, for an EXIF Orientation value (1-8; others: unchanged)."""
    transforms = {
        2: lambda a: a[:, ::-1],  # mirrored left-right
        3: lambda a: a[::-1, ::-1],  # rotated 180
        4: lambda a: a[::-1],  # mirrored top-bottom
        5: lambda a: a.transpose(1, 0, 2),  # transposed
        6: lambda a: np.rot90(a, -1),  # stored rotated 90 counter-clockwise: turn it 90 clockwise
        7: lambda a: a.transpose(1, 0, 2)[::-1, ::-1],  # transverse
        8: lambda a: np.rot90(a, 1),  # stored rotated 90 clockwise: turn it 90 counter-clockwise
    }
    fn = transforms.get(int(orientation))
    return pixels if fn is None else np.ascontiguousarray(fn(pixels))


def read_image(path: str | Path, orient_upright: bool = True) -> np.ndarray:
    """Read an image as float32 [H, W, C], upright by its EXIF Orientation unless `orient_upright` is false (the
    pixels as stored). Raises ImageError naming the file when it cannot be read."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: image file not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot be read as an image ({oiio.geterror() or 'unknown format'})")
    try:
        spec = inp.spec()
        orientation = int(spec.get_int_attribute("Orientation", 1))
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        err = inp.geterror()
    finally:
        inp.close()
    if pixels is None or err:
        raise ImageError(f"{path}: image data is corrupt or truncated ({err or 'no pixels'})")
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    return orient(arr, orientation) if orient_upright else arr


def is_float_image(path: str | Path) -> bool:
    """Whether the file stores floating-point pixels (EXR, HDR, float TIFF): linear HDR, not display-encoded."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot be read as an image ({oiio.geterror() or 'unknown format'})")
    basetype = inp.spec().format.basetype
    inp.close()
    return basetype in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE)


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) from the file header, without reading pixels; upright (EXIF Orientation), like read_image."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot be read as an image ({oiio.geterror() or 'unknown format'})")
    spec = inp.spec()
    inp.close()
    if int(spec.get_int_attribute("Orientation", 1)) in (5, 6, 7, 8):
        return int(spec.height), int(spec.width)
    return int(spec.width), int(spec.height)


def write_image(path: str | Path, pixels: np.ndarray, channel_names: Sequence[str] | None = None) -> None:
    """Write float [H, W, C] (or [H, W]) pixels. EXR/HDR keep float32 (half for .exr would lose the sun);
    PNG/JPEG get 8-bit (or 16-bit for .png when the array is uint16) after clipping to [0, 1].

    The file holds no time stamp (OpenImageIO would add EXR's DateTime), so the same pixels give the same bytes
    (synthetic data is checked bit for bit). `channel_names` names the channels (EXR), e.g. a 6-channel latent."""
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.asarray(pixels)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    h, w, c = arr.shape
    suffix = path.suffix.lower()
    if suffix in (".exr", ".hdr"):
        data, fmt = np.ascontiguousarray(arr, dtype=np.float32), oiio.FLOAT
    elif arr.dtype == np.uint16:
        data, fmt = np.ascontiguousarray(arr), oiio.UINT16
    else:
        data = np.ascontiguousarray(np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8))
        fmt = oiio.UINT8
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise ImageError(f"{path}: no writer for this file type ({oiio.geterror()})")
    spec = oiio.ImageSpec(w, h, c, fmt)
    spec.attribute("DateTime", "")
    if channel_names is not None:
        if len(channel_names) != c:
            raise ImageError(f"{path}: {len(channel_names)} channel names for {c} channels")
        spec.channelnames = tuple(channel_names)
    if not out.open(str(path), spec) or not out.write_image(data):
        msg = out.geterror()
        out.close()
        raise ImageError(f"{path}: cannot write image ({msg})")
    out.close()
