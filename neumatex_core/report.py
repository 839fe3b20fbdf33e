"""The extraction report: one HTML page with PNGs beside it, written into the asset folder's report/.

Shows the preview renders (neural field and PBR fallback), the photos next to re-renders of the result, the
material G-buffers of preset views (base colour, latent channels 0-2 and 3-5 as (l + 1) / 2, the LMRM's
predicted standard deviation where an LMRM was used), the loss and PSNR curves of the TTO, the photos' fitted
exposures (TTOConfig.photo_exposure), metrics and timings.
"""

from __future__ import annotations

import html
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from neumatex_core.imageio import write_image
from neumatex_core.lmrm.plots import line_chart


@dataclass
class ReportContent:
    """title; sections: name -> captioned display images [H, W, 3] in [0, 1] (a grid per section); history: TTO
    rows; metrics, timings, settings: flat tables; notes: sentences shown at the top (the first: what was run)."""

    title: str
    sections: dict[str, list[tuple[str, np.ndarray]]] = field(default_factory=dict)
    history: list[dict[str, float]] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    settings: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    pbr_psnr: float | None = None  # dB, the PBR fallback's PSNR on the photos: a level marked on the PSNR curve
    columns: dict[str, int] = field(default_factory=dict)  # section -> grid columns (default: fill the width)
    # each photo's exposure multiplier fitted by the TTO (on top of its given one, geometric mean 1), or None
    exposures: list[float] | None = None


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text.lower()).strip("_")


def _table(rows: dict[str, Any]) -> str:
    def fmt(v: Any) -> str:
        return f"{v:.4g}" if isinstance(v, float) else html.escape(str(v))

    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{fmt(v)}</td></tr>" for k, v in rows.items())
    return f"<table>{body}</table>"


def write_report(content: ReportContent, folder: Path) -> Path:
    """Write folder/index.html, one captioned PNG per image, curves.png and history.json; returns the HTML path."""
    folder.mkdir(parents=True, exist_ok=True)
    parts = [f"<h1>{html.escape(content.title)}</h1>"]
    parts += [f"<p>{html.escape(n)}</p>" for n in content.notes]
    for name, items in content.sections.items():
        if not items:
            continue
        # one PNG per tile, each under its own caption, so a reader never has to count tiles in a sheet
        figures = []
        for i, (caption, img) in enumerate(items):
            png = f"{_slug(name)}-{i:02d}.png"
            write_image(folder / png, np.clip(img[:, :, :3], 0, 1).astype(np.float32))
            figures.append(f"<figure><img src='{png}' alt='{html.escape(caption)}'>"
                           f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        n_columns = content.columns.get(name)
        grid_style = f" style='grid-template-columns:repeat({n_columns},minmax(256px,1fr))'" if n_columns else ""
        parts.append(f"<h2>{html.escape(name)}</h2><div class='grid'{grid_style}>{''.join(figures)}</div>")
    if content.history:
        steps = [r["step"] for r in content.history]
        psnr_series: dict[str, tuple[Sequence[float], Sequence[float]]] = {
            "psnr": (steps, [r["psnr"] for r in content.history])}
        if content.pbr_psnr is not None:  # a flat line at the PBR fit's level
            psnr_series["PBR fallback (photos)"] = ([steps[0], steps[-1]], [content.pbr_psnr] * 2)
        line_chart([
            ("loss (total, photometric)", {"loss": (steps, [r["loss"] for r in content.history]),
                                           "photo": (steps, [r["photo"] for r in content.history])}, True),
            ("batch PSNR (dB, tonemapped)", psnr_series, False),
        ], folder / "curves.png")  # fmt: skip
        (folder / "history.json").write_text(json.dumps(content.history) + "\n")
        parts.append("<h2>TTO curves</h2><img src='curves.png'>"
                     "<p class='cap'>per step; history.json has the values; the flat line is the PBR fallback's "
                     "PSNR on the photos</p>")
    if content.exposures is not None:
        parts.append(f"<h2>Fitted photo exposures</h2>{_table(exposure_rows(content.exposures))}"
                     "<p class='cap'>each photo's exposure as the TTO fitted it, in stops (log2 of the multiplier) "
                     "relative to its given exposure; their mean is 0 by construction (the overall brightness "
                     "belongs to the material and the known lighting)</p>")  # fmt: skip
    for name, rows in (("Metrics", content.metrics), ("Timings (seconds)", content.timings),
                       ("Settings", content.settings)):  # fmt: skip
        if rows:
            parts.append(f"<h2>{name}</h2>{_table(rows)}")
    style = ("body{font-family:sans-serif;margin:2em;max-width:1500px}"
             " img{image-rendering:pixelated;max-width:100%;min-width:256px}"
             " .grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(256px,1fr));gap:8px}"
             " figure{margin:0} figure img{width:100%} figcaption{color:#555;font-size:80%}"
             " table{border-collapse:collapse} th,td{border:1px solid #ccc;padding:2px 8px;text-align:left}"
             " .cap{color:#555;font-size:90%}")  # fmt: skip
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(content.title)}</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")
    path = folder / "index.html"
    path.write_text(page)
    return path


def exposure_rows(exposures: Sequence[float]) -> dict[str, str]:
    """Table rows "photo i" -> "+0.98 stops (x1.973)" of the fitted exposure multipliers (photo order)."""
    return {f"photo {i}": f"{np.log2(e):+.2f} stops (x{e:.3f})" for i, e in enumerate(exposures)}


def append_table(page: Path, title: str, rows: dict[str, Any], note: str = "") -> None:
    """Add a titled table (and a note under it) at the end of an existing report page (e.g. scores computed after
    the export stage wrote the report: `neumatex extract --compare-pbr`)."""
    text = page.read_text()
    block = f"<h2>{html.escape(title)}</h2>{_table(rows)}" + (f"<p class='cap'>{html.escape(note)}</p>" if note else "")
    end = text.rfind("</body>")
    page.write_text(text[:end] + block + text[end:] if end >= 0 else text + block)
