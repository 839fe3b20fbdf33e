"""A small line chart drawn with Pillow (no plotting library in the dependencies): training curves as PNG."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

from PIL import Image, ImageDraw

COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189), (23, 190, 207)]


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    return [lo + (hi - lo) * k / (n - 1) for k in range(n)]


def line_chart(
    panels: Sequence[tuple[str, dict[str, tuple[Sequence[float], Sequence[float]]], bool]],
    path: Path, panel_size: tuple[int, int] = (520, 300),
) -> None:
    """Write a PNG with one panel per (title, {label: (xs, ys)}, log_y) side by side."""
    pw, ph = panel_size
    img = Image.new("RGB", (pw * len(panels), ph), "white")
    draw = ImageDraw.Draw(img)
    for p, (title, series, log_y) in enumerate(panels):
        x0, y0, x1, y1 = p * pw + 60, 28, p * pw + pw - 15, ph - 35
        draw.text((p * pw + 60, 8), title, fill="black")
        draw.rectangle([x0, y0, x1, y1], outline="black")
        pts = [(x, y) for xs, ys in series.values() for x, y in zip(xs, ys, strict=True)
               if math.isfinite(y) and (y > 0 or not log_y)]  # fmt: skip
        if not pts:
            continue
        fy = (lambda v: math.log10(v)) if log_y else (lambda v: v)
        xmin, xmax = min(x for x, _ in pts), max(x for x, _ in pts)
        ymin, ymax = min(fy(y) for _, y in pts), max(fy(y) for _, y in pts)
        xmax, ymax = (xmax if xmax > xmin else xmin + 1), (ymax if ymax > ymin else ymin + 1)

        box, rng = (x0, y0, x1, y1), (xmin, xmax, ymin, ymax)

        def to_px(x: float, y: float, box: tuple[float, ...] = box, rng: tuple[float, ...] = rng,
                  log_y: bool = log_y) -> tuple[float, float]:
            v = math.log10(y) if log_y else y
            return (box[0] + (x - rng[0]) / (rng[1] - rng[0]) * (box[2] - box[0]),
                    box[3] - (v - rng[2]) / (rng[3] - rng[2]) * (box[3] - box[1]))

        for t in _ticks(ymin, ymax):
            yy = y1 - (t - ymin) / (ymax - ymin) * (y1 - y0)
            draw.line([x0 - 4, yy, x0, yy], fill="black")
            label = f"{10 ** t:.3g}" if log_y else f"{t:.3g}"
            draw.text((p * pw + 4, yy - 6), label, fill="black")
        for t in _ticks(xmin, xmax):
            xx = x0 + (t - xmin) / (xmax - xmin) * (x1 - x0)
            draw.line([xx, y1, xx, y1 + 4], fill="black")
            draw.text((xx - 12, y1 + 6), f"{t:.0f}", fill="black")
        for k, (label, (xs, ys)) in enumerate(series.items()):
            colour = COLOURS[k % len(COLOURS)]
            line = [to_px(x, y) for x, y in zip(xs, ys, strict=True) if math.isfinite(y) and (y > 0 or not log_y)]
            if len(line) > 1:
                draw.line(line, fill=colour, width=2)
            elif line:
                draw.ellipse([line[0][0] - 2, line[0][1] - 2, line[0][0] + 2, line[0][1] + 2], fill=colour)
            draw.text((x1 - 150, y0 + 6 + 14 * k), label, fill=colour)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)
