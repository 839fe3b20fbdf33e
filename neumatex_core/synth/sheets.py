"""Contact sheets of a synthetic dataset: one view per object, its base-colour and its latent G-buffers.

    neumatex synth-sheets data/benchmark-test --out docs --prefix benchmark --view 0
    python -m neumatex_core.synth.sheets data/benchmark-test --out docs --prefix benchmark   (the same)

writes `<prefix>-contact.png` (the tonemapped view as stored), `<prefix>-basecolor.png` (rho_d, sRGB-encoded) and
`<prefix>-latents.png` (per object two tiles side by side: latent channels 0-2 and 3-5 as RGB, mapped by
(l + 1) / 2, the quantity PSNR_Latents is taken on); uncovered pixels are white. Each tile is captioned with the
object's index and shape (mesh name for shared meshes). Objects are those of the dataset's manifest.json, in
index order; an incomplete dataset is refused unless `--allow-incomplete`, which also draws the finished objects
(folders with meta.json) of a dataset whose `neumatex synth` run is still going (it writes manifest.json at its end).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from neumatex_core.capture.tonemap import srgb_oetf_numpy
from neumatex_core.config import add_config_arguments, config_from_args, option
from neumatex_core.imageio import read_image, write_image

CAPTION = 12  # caption strip height (pixels)


@dataclass
class SheetsConfig:
    """`neumatex synth-sheets`: contact sheets of a synthetic dataset (one view per object, its base-colour and
    latent G-buffers) as three PNGs."""

    dataset: str = option("", "dataset folder (with manifest.json), e.g. data/benchmark-test", positional=True)
    out: str = option("docs", "output folder")
    prefix: str = option("benchmark", "file names: PREFIX-contact.png, PREFIX-basecolor.png, PREFIX-latents.png")
    view: int = option(0, "preset view index (0: orbit_00, 17: canonical_+x)")
    columns: int = option(8, "objects per row")
    tile: int = option(0, "tile size in pixels (0: the dataset's resolution; smaller tiles are box-filtered)")
    allow_incomplete: bool = option(False, "draw the finished objects of an incomplete or still running dataset")


def _tile(image: np.ndarray, caption: str, size: int) -> np.ndarray:
    """float [size + CAPTION, size, 3] in [0, 1]: image [H, W, >=3] (display-encoded, [0, 1]) under a caption."""
    from PIL import Image, ImageDraw

    img = Image.fromarray((np.clip(image[:, :, :3], 0, 1) * 255 + 0.5).astype(np.uint8))
    if img.size != (size, size):
        img = img.resize((size, size), Image.Resampling.BOX)
    canvas = Image.new("RGB", (size, size + CAPTION), (255, 255, 255))
    canvas.paste(img, (0, CAPTION))
    ImageDraw.Draw(canvas).text((2, 0), caption, fill=(0, 0, 0))
    return np.asarray(canvas, dtype=np.float32) / 255.0


def sheet(tiles: list[np.ndarray], columns: int, pad: int = 3) -> np.ndarray:
    """Tiles [H, W, 3] (same size) on a white grid, `columns` per row: float [rows (H + pad) + pad, ..., 3]."""
    h, w = tiles[0].shape[:2]
    rows = (len(tiles) + columns - 1) // columns
    out = np.ones((rows * (h + pad) + pad, columns * (w + pad) + pad, 3), dtype=np.float32)
    for k, t in enumerate(tiles):
        r, c = divmod(k, columns)
        out[pad + r * (h + pad):pad + r * (h + pad) + h, pad + c * (w + pad):pad + c * (w + pad) + w] = t
    return out


def _finished(dataset: Path) -> dict[str, Any]:
    """A manifest-like {"complete": False, "objects": [...]} of the finished objects (folders with meta.json) of a
    dataset whose run has not written manifest.json yet."""
    objects = []
    for meta_path in sorted(dataset.glob("*/meta.json")):
        meta = json.loads(meta_path.read_text())
        spec = meta["spec"]
        objects.append({"id": meta["id"], "index": spec["index"], "shape": meta["shape"]["kind"],
                        "mesh": spec["shape"]["mesh"]})  # fmt: skip
    return {"complete": False, "n": None, "objects": sorted(objects, key=lambda o: o["index"])}


def _manifest(dataset: Path, allow_incomplete: bool) -> dict[str, Any]:
    path = dataset / "manifest.json"
    if not path.is_file() and allow_incomplete and (dataset / "synth.json").is_file():
        return _finished(dataset)  # a run still going: manifest.json is written when it ends
    if not path.is_file():
        raise ValueError(f"{path}: not found (is {dataset} a dataset made by `neumatex synth`? while a run is "
                         "still making it, --allow-incomplete draws the objects finished so far)")
    try:
        manifest = json.loads(path.read_text())
        objects = manifest["objects"]
    except (ValueError, KeyError) as exc:
        raise ValueError(f"{path}: not a synth manifest ({exc})") from None
    if not objects:
        raise ValueError(f"{path}: lists no finished objects")
    if not manifest.get("complete") and not allow_incomplete:
        raise ValueError(f"{path}: the dataset is incomplete ({len(objects)} of {manifest.get('n')} objects); "
                         "finish it (rerun the same `neumatex synth`) or pass --allow-incomplete")
    return dict(manifest)


def contact_sheets(dataset: Path, out: Path, prefix: str = "benchmark", view: int = 0, columns: int = 8,
                   tile: int = 0, allow_incomplete: bool = False) -> list[Path]:
    """Write the three sheets of the objects in the dataset's manifest; returns their paths. ValueError naming
    the file for a missing or incomplete manifest, a missing view or G-buffer."""
    manifest = _manifest(dataset, allow_incomplete)
    views, colors, latents = [], [], []
    for entry in manifest["objects"]:
        root = dataset / entry["id"]
        frames = json.loads((root / "transforms.json").read_text())["frames"]
        if not 0 <= view < len(frames):
            raise ValueError(f"{root / 'transforms.json'}: no view {view} (it has {len(frames)})")
        frame = frames[view]
        image = read_image(root / frame["file_path"])
        size = tile or image.shape[1]
        caption = f"{entry['index']:02d} {entry['mesh'] or entry['shape']}"
        mask = read_image(root / frame["mask_path"])[:, :, :1] > 0.5
        views.append(_tile(image, caption, size))
        base = srgb_oetf_numpy(np.clip(read_image(root / frame["gbuffers"]["basecolor"]), 0, 1))
        colors.append(_tile(np.where(mask, base, 1.0), caption, size))
        latent = (read_image(root / frame["gbuffers"]["latent"]) + 1) / 2
        latents.append(_tile(np.where(mask, latent[:, :, 0:3], 1.0), caption + " l0-2", size))
        latents.append(_tile(np.where(mask, latent[:, :, 3:6], 1.0), "l3-5", size))
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{prefix}-{name}.png" for name in ("contact", "basecolor", "latents")]
    for path, tiles, cols in zip(paths, (views, colors, latents), (columns, columns, 2 * columns), strict=True):
        write_image(path, sheet(tiles, cols))
    return paths


def run_sheets(cfg: SheetsConfig) -> int:
    """The `neumatex synth-sheets` command: write the sheets, print their paths and sizes."""
    if not cfg.dataset:
        raise ValueError("give the dataset folder (neumatex synth-sheets DATASET)")
    if cfg.columns < 1 or cfg.tile < 0:
        raise ValueError(f"--columns must be >= 1 and --tile >= 0, got {cfg.columns} and {cfg.tile}")
    paths = contact_sheets(Path(cfg.dataset), Path(cfg.out), cfg.prefix, cfg.view, cfg.columns, cfg.tile,
                           cfg.allow_incomplete)  # fmt: skip
    for path in paths:
        print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m neumatex_core.synth.sheets", description=SheetsConfig.__doc__)
    add_config_arguments(parser, SheetsConfig)
    try:
        return run_sheets(config_from_args(SheetsConfig, parser.parse_args(argv)))
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
