"""The paired-difference chart of the results page, drawn with Pillow (no plotting library in the dependencies).

One row per comparison: a grey dot per object (variant a minus variant b on one metric, dB), the mean as a black
tick with a bar of +- 2 standard errors (green: resolved above zero, red: resolved below, grey: not resolved), a
zero line and the claim's thresholds, where it has them, as orange ticks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

LABEL_WIDTH = 330  # px of text left of the axis (the default bitmap font is about 6 px per character)
ROW_HEIGHT = 26


@dataclass(frozen=True)
class DifferenceRow:
    """label; per-object differences [n] dB; thresholds: the claim's bars in dB (none, one, or both ends)."""

    label: str
    values: Sequence[float]
    thresholds: tuple[float, ...] = ()


def _nice_step(span: float) -> float:
    raw = span / 8
    mag = 10 ** math.floor(math.log10(raw))
    return next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)


def difference_chart(rows: Sequence[DifferenceRow], path: Path, width: int = 980) -> None:
    """Write the chart as a PNG; rows without values are drawn as empty strips."""
    finite = [v for r in rows for v in r.values if math.isfinite(v)]
    marks = finite + [t for r in rows for t in r.thresholds] + [0.0]
    lo, hi = min(marks), max(marks)
    pad = 0.05 * (hi - lo or 1.0)
    lo, hi = lo - pad, hi + pad
    x0, x1, top = LABEL_WIDTH, width - 20, 30
    height = top + ROW_HEIGHT * len(rows) + 40
    img = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(img)

    def px(v: float) -> float:
        return x0 + (v - lo) / (hi - lo) * (x1 - x0)

    draw.text((8, 8), "paired differences per object (dB): dots = objects, bar = mean +- 2 SE, "
              "orange = the claim's threshold", fill="black")  # fmt: skip
    step = _nice_step(hi - lo)
    bottom = top + ROW_HEIGHT * len(rows)
    for i in range(1, len(rows), 2):  # banded rows first, so the grid lies over them
        draw.rectangle([0, top + ROW_HEIGHT * i, width, top + ROW_HEIGHT * (i + 1) - 1], fill=(247, 247, 247))
    for k in range(math.ceil(lo / step), math.floor(hi / step) + 1):
        t = k * step
        draw.line([px(t), top, px(t), bottom], fill=(120, 120, 120) if k == 0 else (225, 225, 225),
                  width=2 if k == 0 else 1)  # fmt: skip
        draw.text((px(t) - 10, bottom + 6), f"{t:+.3g}" if t else "0", fill="black")
    for i, row in enumerate(rows):
        yc = top + ROW_HEIGHT * i + ROW_HEIGHT / 2
        draw.text((8, yc - 6), row.label, fill="black")
        vals = np.asarray([v for v in row.values if math.isfinite(v)], dtype=np.float64)
        for j, v in enumerate(vals):  # a small deterministic vertical jitter so equal values stay visible
            y = yc - 6 + 12 * ((j * 0.618) % 1.0)
            draw.ellipse([px(v) - 2, y - 2, px(v) + 2, y + 2], fill=(150, 150, 150))
        for t in row.thresholds:
            draw.line([px(t), yc - 11, px(t), yc + 11], fill=(255, 127, 14), width=3)
        if vals.size:
            mean = float(vals.mean())
            se = float(vals.std(ddof=1) / math.sqrt(vals.size)) if vals.size > 1 else 0.0
            colour = (44, 160, 44) if mean - 2 * se > 0 else (214, 39, 40) if mean + 2 * se < 0 else (110, 110, 110)
            draw.line([px(mean - 2 * se), yc, px(mean + 2 * se), yc], fill=colour, width=5)
            draw.line([px(mean), yc - 8, px(mean), yc + 8], fill="black", width=2)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
