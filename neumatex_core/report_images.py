"""Display images of the extraction report: colour-mapped scalar maps, their colour bar, difference images.

All images are float [H, W, 3] in [0, 1] (display-referred, as the report writes them to PNG).
"""

from __future__ import annotations

import numpy as np

# a perceptually ordered ramp (dark blue -> teal -> yellow, close to viridis), stops at 0, 0.25, 0.5, 0.75, 1
_RAMP = np.array([[0.267, 0.005, 0.329], [0.230, 0.322, 0.546], [0.128, 0.567, 0.551],
                  [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]], dtype=np.float32)  # fmt: skip


def colour_mapped(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """values [...] -> [..., 3] on the ramp, lo mapped to its dark end and hi to its bright end (clipped)."""
    t = np.clip((np.asarray(values, np.float32) - lo) / max(hi - lo, 1e-12), 0.0, 1.0) * (len(_RAMP) - 1)
    i = np.minimum(t.astype(np.int64), len(_RAMP) - 2)
    f = (t - i)[..., None]
    return (_RAMP[i] * (1 - f) + _RAMP[i + 1] * f).astype(np.float32)


def colour_bar(height: int, width: int) -> np.ndarray:
    """The ramp as a vertical strip (a quarter of the width, centred) on white, [height, width, 3]; bright (high)
    at the top. Square like the map beside it so a grid shows both at one size; its range goes in the caption."""
    img = np.ones((height, width, 3), np.float32)
    strip = max(2, width // 4)
    left = (width - strip) // 2
    column = np.linspace(1.0, 0.0, height, dtype=np.float32)[:, None].repeat(strip, 1)
    img[:, left:left + strip] = colour_mapped(column, 0.0, 1.0)
    return img


def scalar_map(values: np.ndarray, mask: np.ndarray, background: float = 1.0) -> tuple[np.ndarray, float, float]:
    """values [H, W] over mask [H, W] (bool) -> (image [H, W, 3] normalised to the masked range, lo, hi).

    Normalised to the 1st-99th percentile of the masked values, so one outlier does not wash the map out."""
    inside = values[mask]
    lo, hi = (float(np.percentile(inside, 1)), float(np.percentile(inside, 99))) if inside.size else (0.0, 1.0)
    if hi <= lo:
        hi = lo + 1e-6
    img = np.full((*values.shape, 3), background, np.float32)
    img[mask] = colour_mapped(inside, lo, hi)
    return img, lo, hi


def difference_image(image: np.ndarray, reference: np.ndarray, gain: float = 4.0) -> np.ndarray:
    """|image - reference| x gain per channel, both [H, W, 3] in [0, 1]; black where they agree."""
    return np.clip(np.abs(image[..., :3] - reference[..., :3]) * gain, 0.0, 1.0).astype(np.float32)
