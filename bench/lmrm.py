"""LMRM alone on the benchmark test split: material G-buffer PSNR against two trivial baselines, uncertainty
calibration and inference time.

For every finished object of `--data` (default data/benchmark-test, `neumatex synth --split test`), the shipped
LMRM (`load_lmrm`) predicts a triplane from the 23 tonemapped preset views, their cameras, the mesh and the
environment map; its decoders are read at the surface points of every covered pixel of the 23 views' ground-truth
G-buffers (positions at pixel centres). Measured in the same run:

- PSNR_BaseColor on rho_d and PSNR_Latents on (l+1)/2 (eval/metrics.py: masked, over the covered pixels of all 23
  views of an object), averaged over objects, for (a) the LMRM, (b) the training-set mean material (mean rho_d and
  latent over the training objects' covered pixels, recorded in the checkpoint as metrics.training_mean), (c) the
  per-pixel image colour as base colour (the view's pixel, sRGB-decoded; its latent is the training mean, so its
  PSNR_Latents equals (b)), (d) how much of the base colour the inputs carry in their plainest form: a linear map
  from the shading-normalised colour (the linear pixel over the diffuse lighting cue, the LMRM's "ratio" input, and
  its mean over the object) to rho_d, least-squares fitted on the other test objects (leave one object out), and
  (e) each object's own mean base colour (an oracle: what knowing only an object's average colour would give);
- uncertainty calibration on the raw G-buffer (rho_d, l), per pixel and channel: Spearman correlation of the
  predicted variance exp(log_var) with the squared error (pooled over objects, and per channel), and the fraction
  of errors inside the predicted 1-sigma and 2-sigma bands (a calibrated Gaussian gives 0.683 and 0.954);
- inference seconds per object (`LMRM.predict`, G-buffer ray queries included), median over objects;
- the base colour by material family (each pixel's region, `gbuffers/NNN_region.exr`, and its family in
  material.json; pixels pooled over objects): the LMRM's PSNR and the mean material's, and the mean colour each
  predicts against the truth's, which shows where the LMRM gives the layers' colour to the base (docs/lmrm.md).

`--figure PNG` also draws, for the first `--figure-objects` objects, view 0: the input, base colour, latents
(channels 0-2 and 3-5 as RGB of (l+1)/2) and the predicted standard deviation next to the absolute error.

    .venv/bin/python bench/lmrm.py                       # the whole test split (about 2-4 s per object)
    .venv/bin/python bench/lmrm.py --limit 4 --no-save   # smoke run
    .venv/bin/python bench/lmrm.py --weights out/lmrm-gpu/lmrm.safetensors   # a candidate (its .json beside it)
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, write_result  # noqa: E402

from neumatex_core.capture.tonemap import srgb_eotf  # noqa: E402
from neumatex_core.eval.metrics import psnr, psnr_of_mse  # noqa: E402
from neumatex_core.geometry.mesh import load_mesh  # noqa: E402
from neumatex_core.lmrm import load_lmrm  # noqa: E402
from neumatex_core.lmrm.data import (  # noqa: E402
    finished_objects,
    lighting_cues,
    load_synth_object,
    prefiltered,
    to_camera_directions,
)
from neumatex_core.lmrm.inference import load_lmrm_from  # noqa: E402
from neumatex_core.lmrm.model import RATIO_MAX  # noqa: E402
from neumatex_core.materials.prior import FAMILIES  # noqa: E402

RATIO_PIXELS = 40_000  # covered pixels per object kept for baseline (d)
CHANNELS = ["rho_r", "rho_g", "rho_b", "l0", "l1", "l2", "l3", "l4", "l5"]


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(a, b).statistic)


class FamilyErrors:
    """Base-colour squared errors [3] of the LMRM and of the mean material, pooled per family over objects."""

    def __init__(self) -> None:
        self.rows: dict[str, dict[str, torch.Tensor]] = {}
        self.pixels: dict[str, int] = {}

    def add(self, family: str, pred: torch.Tensor, mean: torch.Tensor, truth: torch.Tensor) -> None:
        """pred, truth [N, 3] rho_d of one family's pixels; mean [3] the mean material's."""
        row = self.rows.setdefault(family, {k: torch.zeros(3, dtype=torch.float64) for k in
                                            ("lmrm", "mean", "pred_sum", "truth_sum")})  # fmt: skip
        row["lmrm"] += ((pred - truth) ** 2).sum(0).double()
        row["mean"] += ((mean - truth) ** 2).sum(0).double()
        row["pred_sum"] += pred.sum(0).double()
        row["truth_sum"] += truth.sum(0).double()
        self.pixels[family] = self.pixels.get(family, 0) + truth.shape[0]

    def table(self) -> dict[str, dict[str, Any]]:
        total = sum(self.pixels.values())
        out = {}
        for fam, r in sorted(self.rows.items()):
            n = self.pixels[fam]
            out[fam] = {"share": n / total, "lmrm_basecolor": psnr_of_mse(float(r["lmrm"].sum()) / (3 * n)),
                        "mean_basecolor": psnr_of_mse(float(r["mean"].sum()) / (3 * n)),
                        "lmrm_mean_colour": (r["pred_sum"] / n).round(decimals=3).tolist(),
                        "truth_mean_colour": (r["truth_sum"] / n).round(decimals=3).tolist()}  # fmt: skip
        return out


def _heat(x: np.ndarray, vmax: float) -> np.ndarray:
    """[H, W] -> [H, W, 3] a black-red-yellow-white ramp of x / vmax."""
    t = np.clip(x / max(vmax, 1e-12), 0, 1)[..., None]
    return np.clip(np.concatenate([3 * t, 3 * t - 1, 3 * t - 2], axis=-1), 0, 1)


def figure(rows: list[dict[str, np.ndarray]], path: Path) -> None:
    """Columns: input | base colour truth / LMRM | latent 0-2 truth / LMRM | latent 3-5 truth / LMRM |
    predicted sigma (mean over 9 channels) | |error| (mean over 9 channels), same colour scale."""
    from PIL import Image, ImageDraw

    from neumatex_core.capture.tonemap import srgb_oetf_numpy

    titles = ["input view", "rho_d truth", "rho_d LMRM", "l0-2 truth", "l0-2 LMRM", "l3-5 truth", "l3-5 LMRM",
              "pred. sigma", "|error|"]  # fmt: skip
    tiles = []
    for r in rows:
        m = r["mask"][..., None]

        def enc(x: np.ndarray, m: np.ndarray = m) -> np.ndarray:
            return np.asarray(srgb_oetf_numpy(np.clip(x, 0, 1)) * m + (1 - m))

        def lat(x: np.ndarray, m: np.ndarray = m) -> np.ndarray:
            return (x + 1) / 2 * m + (1 - m)

        vmax = float(np.percentile(r["sigma"][r["mask"] > 0], 99)) if r["mask"].any() else 1.0
        tiles.append([r["input"], enc(r["rho_true"]), enc(r["rho_pred"]), lat(r["lat_true"][..., :3]),
                      lat(r["lat_pred"][..., :3]), lat(r["lat_true"][..., 3:]), lat(r["lat_pred"][..., 3:]),
                      _heat(r["sigma"], vmax) * m + (1 - m), _heat(r["error"], vmax) * m + (1 - m)])  # fmt: skip
    h, w = rows[0]["mask"].shape
    pad, top = 4, 16
    sheet = np.ones((top + len(rows) * (h + pad), len(titles) * (w + pad), 3), dtype=np.float32)
    for i, row in enumerate(tiles):
        for j, tile in enumerate(row):
            y, x = top + i * (h + pad), j * (w + pad)
            sheet[y:y + h, x:x + w] = tile
    img = Image.fromarray((sheet * 255).round().astype(np.uint8))
    draw = ImageDraw.Draw(img)
    for j, t in enumerate(titles):
        draw.text((j * (w + pad) + 2, 2), t, fill=(0, 0, 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)


def main() -> int:
    ap = argument_parser(__doc__)
    ap.add_argument("--data", default="data/benchmark-test", help="test split folder (neumatex synth --split test)")
    ap.add_argument("--limit", type=int, default=0, help="at most this many test objects (0: all)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--figure", default="", help="write the prediction figure to this PNG")
    ap.add_argument("--figure-objects", type=int, default=4)
    ap.add_argument("--max-pairs", type=int, default=400_000, help="(pixel, channel) pairs kept for Spearman")
    ap.add_argument("--weights", default="", help="an LMRM .safetensors (its .json beside it), not the shipped one")
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    weights = Path(args.weights) if args.weights else None
    lmrm = load_lmrm_from(weights, weights.with_suffix(".json")) if weights else load_lmrm("cpu")
    folders = finished_objects(Path(args.data))
    if args.limit:
        folders = folders[:args.limit]
    if not folders:
        print(f"error: {args.data}: no finished test objects", file=sys.stderr)
        return 2
    try:
        mean = torch.tensor(lmrm.record["metrics"]["training_mean"], dtype=torch.float32)[:9]
    except (KeyError, TypeError):
        print("error: the LMRM record has no metrics.training_mean (retrain with `neumatex train-lmrm`)",
              file=sys.stderr)
        return 2
    rng = np.random.default_rng(0)
    per_object: list[dict[str, Any]] = []
    pairs_var, pairs_err2 = [], []
    ratio_rows: list[tuple[torch.Tensor, torch.Tensor]] = []  # per object: [P, 7] features, [P, 3] rho_d (d)
    ratio_rng = np.random.default_rng(1)
    inside1 = np.zeros(9)
    inside2 = np.zeros(9)
    total = 0
    fig_rows = []
    families = FamilyErrors()
    print(f"LMRM {lmrm.record.get('sha256', '')[:12]} on {len(folders)} objects of {args.data}")
    for folder in folders:
        obj = load_synth_object(folder)
        mesh = load_mesh(folder / "mesh.obj")
        t0 = time.perf_counter()
        pred = lmrm.predict(obj.rgb, obj.cameras, mesh, obj.envmap)
        m = obj.mask
        with torch.no_grad():
            rho, lat, log_var = pred.gbuffers(obj.position[m])
        seconds = time.perf_counter() - t0
        t = obj.targets[m]
        mean_t = mean.expand(t.shape[0], 9)
        image_rho = srgb_eotf(obj.rgb[m])
        with torch.no_grad():
            to_cam = to_camera_directions(obj.position, obj.cameras)[m]
            cues = lighting_cues(prefiltered(obj.envmap), obj.normal[m], to_cam)
        ratio = (image_rho / cues[:, :3].clamp_min(1e-3)).clamp(0, RATIO_MAX)
        features = torch.cat([ratio, ratio.mean(0, keepdim=True).expand_as(ratio), torch.ones_like(ratio[:, :1])], -1)
        pick = torch.from_numpy(ratio_rng.permutation(t.shape[0])[:RATIO_PIXELS])
        ratio_rows.append((features[pick].double(), t[pick, :3].double()))
        row = {
            "id": obj.id, "pixels": int(m.sum()), "seconds": round(seconds, 3),
            "lmrm_basecolor": psnr(rho[None], t[None, :, :3]),
            "lmrm_latents": psnr((lat[None] + 1) / 2, (t[None, :, 3:9] + 1) / 2),
            "mean_basecolor": psnr(mean_t[None, :, :3], t[None, :, :3]),
            "mean_latents": psnr((mean_t[None, :, 3:9] + 1) / 2, (t[None, :, 3:9] + 1) / 2),
            "image_basecolor": psnr(image_rho[None], t[None, :, :3]),
            "own_mean_basecolor": psnr(t[None, :, :3].mean(1, keepdim=True).expand(1, t.shape[0], 3), t[None, :, :3]),
        }  # fmt: skip
        per_object.append(row)
        covered_family = obj.family[m]
        for k, fam in enumerate(FAMILIES):
            inside = covered_family == k
            if inside.any():
                families.add(fam, rho[inside], mean[:3], t[inside, :3])
        err = torch.cat([rho, lat], -1) - t[:, :9]
        var = torch.exp(log_var)
        sd = var.sqrt()
        inside1 += (err.abs() <= sd).double().sum(0).numpy()
        inside2 += (err.abs() <= 2 * sd).double().sum(0).numpy()
        total += err.shape[0]
        keep = rng.random(err.shape[0]) < min(1.0, args.max_pairs / 9 / max(len(folders), 1) / err.shape[0])
        pairs_var.append(var[torch.from_numpy(keep)].numpy())
        pairs_err2.append((err[torch.from_numpy(keep)] ** 2).numpy())
        print(f"  {obj.id}: base colour {row['lmrm_basecolor']:.2f} dB (mean {row['mean_basecolor']:.2f}, image "
              f"{row['image_basecolor']:.2f}), latents {row['lmrm_latents']:.2f} dB (mean {row['mean_latents']:.2f}), "
              f"{seconds:.2f} s")  # fmt: skip
        if args.figure and len(fig_rows) < args.figure_objects:
            v = 0
            mv = m[v]

            def full(x: torch.Tensor, v: int = v, mv: torch.Tensor = mv) -> np.ndarray:
                out = torch.zeros(*mv.shape, x.shape[-1])
                out[mv] = x
                return out.numpy()

            with torch.no_grad():
                r0, l0, lv0 = pred.gbuffers(obj.position[v][mv])
            e0 = (torch.cat([r0, l0], -1) - obj.targets[v][mv][:, :9]).abs().mean(-1, keepdim=True)
            fig_rows.append({"mask": mv.numpy().astype(np.float32), "input": obj.rgb[v].numpy(),
                             "rho_true": obj.targets[v, :, :, :3].numpy(), "rho_pred": full(r0),
                             "lat_true": obj.targets[v, :, :, 3:9].numpy(), "lat_pred": full(l0),
                             "sigma": full(torch.exp(0.5 * lv0).mean(-1, keepdim=True))[..., 0],
                             "error": full(e0)[..., 0]})  # fmt: skip
    # (d): least squares on the shading-normalised colour, leaving each object out of its own fit (normal equations:
    # every object's X^T X and X^T y are summed once and its own taken away; with one object, it is fitted on itself)
    gram = [(x.T @ x, x.T @ y) for x, y in ratio_rows]
    gram_all = (sum(g[0] for g in gram), sum(g[1] for g in gram))
    for row, (xk, yk), (xx, xy) in zip(per_object, ratio_rows, gram, strict=True):
        others = (gram_all[0] - xx, gram_all[1] - xy) if len(gram) > 1 else (xx, xy)
        w = torch.linalg.solve(*others)
        row["ratio_basecolor"] = psnr((xk @ w).clamp(0, 1).float()[None], yk.float()[None])
    var_all, err2_all = np.concatenate(pairs_var), np.concatenate(pairs_err2)
    calib = {
        "spearman_all": _spearman(var_all.ravel(), err2_all.ravel()),
        "spearman_per_channel": {c: _spearman(var_all[:, k], err2_all[:, k]) for k, c in enumerate(CHANNELS)},
        "within_1sigma": float(inside1.sum() / (9 * total)), "within_2sigma": float(inside2.sum() / (9 * total)),
        "within_1sigma_per_channel": dict(zip(CHANNELS, (inside1 / total).round(4).tolist(), strict=True)),
        "pairs": int(var_all.size),
    }  # fmt: skip
    avg = {k: statistics.fmean(r[k] for r in per_object) for k in per_object[0] if k not in ("id", "pixels")}
    sec = statistics.median(r["seconds"] for r in per_object)
    print()
    print(f"{len(per_object)} test objects | PSNR_BaseColor (dB) | PSNR_Latents (dB)")
    print(f"LMRM                 | {avg['lmrm_basecolor']:6.2f} | {avg['lmrm_latents']:6.2f}")
    print(f"training-set mean    | {avg['mean_basecolor']:6.2f} | {avg['mean_latents']:6.2f}")
    print(f"image colour as rho_d| {avg['image_basecolor']:6.2f} | {avg['mean_latents']:6.2f} (mean latent)")
    print(f"linear map of the shading-normalised colour (other objects) | {avg['ratio_basecolor']:6.2f} |")
    print(f"each object's own mean base colour (oracle) | {avg['own_mean_basecolor']:6.2f} |")
    print(f"LMRM - mean material: {avg['lmrm_basecolor'] - avg['mean_basecolor']:+.2f} / "
          f"{avg['lmrm_latents'] - avg['mean_latents']:+.2f} dB; LMRM - image colour: "
          f"{avg['lmrm_basecolor'] - avg['image_basecolor']:+.2f} dB (base colour)")
    print(f"uncertainty: Spearman(var, err^2) {calib['spearman_all']:.3f} over {calib['pairs']} (pixel, channel) "
          f"pairs; within 1 sigma {calib['within_1sigma']:.3f} (Gaussian 0.683), within 2 sigma "
          f"{calib['within_2sigma']:.3f} (0.954)")
    print("Spearman per channel: " + ", ".join(f"{c} {v:.2f}" for c, v in calib["spearman_per_channel"].items()))
    print(f"inference: median {sec:.2f} s per object ({torch.get_num_threads()} threads)")
    by_family = families.table()
    print("base colour by family (pixels pooled) | share | LMRM dB | mean material dB | LMRM mean colour -> truth's")
    for fam, f in by_family.items():
        print(f"  {fam:10s} | {f['share']:.2f} | {f['lmrm_basecolor']:6.2f} | {f['mean_basecolor']:6.2f} | "
              f"{f['lmrm_mean_colour']} -> {f['truth_mean_colour']}")
    if args.figure:
        figure(fig_rows, Path(args.figure))
        print(f"wrote {args.figure}")
    if not args.no_save:
        rec = {"data": args.data, "objects": len(per_object), "checkpoint_sha256": lmrm.record.get("sha256"),
               "basis_id": lmrm.basis_id, "psnr": avg, "calibration": calib, "seconds_per_object_median": sec,
               "by_family": by_family, "per_object": per_object}  # fmt: skip
        print(f"appended to {write_result('lmrm', rec)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
