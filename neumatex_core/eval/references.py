"""Noise-free scoring of renders: the exact ground-truth material of a synthetic object, high-sample reference
renders of it in two independent halves, and the noise-corrected PSNR that compares a variant against them.

    field = truth_field("data/benchmark-test/test-000000")          # the material the photos were made with
    render_references("data/benchmark-test/test-000000", spp_half=128)
    score = clean_psnr(a1, a2, r1, r2, mask, cap.tonemap)            # score.psnr, score.raw_psnr
    clean_metrics(object_dir, field, mesh, range(17), (0, 8, 16), spp_half=32, seed=0)  # what the harness reports

Files (under the object folder; resumable, every image written atomically):

```
references/meta.json                 {"settings": ..., "seeds": {"capture/000_a": seed, ...}, "complete": bool}
references/capture/000_a.exr, 000_b.exr, ... 016_b.exr    the 17 orbital views under the capture's lighting
references/relight/<j>/000_a.exr ...                      the same cameras under held-out lighting j
```

Each image is the ground-truth material (`truth_field`) rendered with `spp_half` samples per pixel (linear HDR
float32 [H, W, 3]); halves a and b use independent seeds (`half_seed` of the object's render seed), so their
difference measures the Monte Carlo noise. `settings` holds what decides the pixels (spp, bounces, the tracer's
Russian roulette depth and strategy, views, lightings, the basis and the object's tree hash): a run with other
settings is refused rather than mixed in. One process per object at a time (a run removes temporary files it
finds there).

Measured on benchmark object test-000000 (128 px, references of 128 + 128 spp, made in 749 s on one thread of the
shared 2-core machine, 15 MB): its ground-truth material scored at 32 + 32 spp reads 49.7 dB clean against a raw
30.1 dB (17 orbital views; clean MSE 1.1e-5 +- 1.0e-5, i.e. consistent with 0), 45.4 dB against 30.1 under the
held-out lightings (views 0, 4, 8, 12, 16), where its photo-based PSNR PathTrace / Relight read 25.2 / 24.0 dB.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from neumatex_core.atomic import is_temporary, replaced_atomically, write_json_atomic
from neumatex_core.capture import load_capture
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.geometry.camera import PRESET_ORBIT_VIEWS
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh, load_mesh
from neumatex_core.imageio import read_image, write_image
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.layered import PARAMETER_NAMES
from neumatex_core.materials.neural_basis import NeuralBasis, check_basis_id
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.synth.lighting import LightingSpec
from neumatex_core.synth.materials import MaterialSpec, ProceduralMaterialField, RegionMaterial, face_regions
from neumatex_core.synth.shapes import ShapeSpec, build_shape
from neumatex_core.synth.spec import ObjectSpec

FOLDER = "references"
FORMAT = "neumatex-references-1"
REFERENCE_TAG = 0x5EF  # seed stream of the reference halves (of the object's render seed)
CLEAN_TAG = 0xC1EA  # seed stream of a variant's halves in the clean scoring (of the evaluation seed)
MSE_FLOOR = 1e-10  # the clean MSE is floored here (100 dB) when noise makes the estimate <= 0
HALVES = ("a", "b")


# -- the exact ground truth ------------------------------------------------------------------------------------
def object_spec_from_json(data: dict[str, Any]) -> ObjectSpec:
    """The ObjectSpec of a meta.json "spec" (`ObjectSpec.to_json`): JSON floats round-trip exactly, so this is the
    spec the object was written from."""
    m = data["material"]
    regions = tuple(RegionMaterial(str(r["family"]), tuple(float(r["params"][n]) for n in PARAMETER_NAMES),
                                   tuple(float(x) for x in r["color0"]),  # type: ignore[arg-type]
                                   tuple(float(x) for x in r["color1"]))  # type: ignore[arg-type]
                    for r in m["regions"])  # fmt: skip
    material = MaterialSpec(str(m["mode"]), regions, int(m["region_seed"]), float(m["region_frequency"]),
                            int(m["color_seed"]), float(m["color_frequency"]), str(m["pattern"]),
                            float(m["contrast"]))  # fmt: skip
    return ObjectSpec(
        id=str(data["id"]), split=str(data["split"]), index=int(data["index"]), seed=int(data["seed"]),
        shape=ShapeSpec(str(data["shape"]["kind"]), int(data["shape"]["seed"]), str(data["shape"].get("mesh", ""))),
        material=material, lighting=LightingSpec(**data["lighting"]),
        relight=tuple(LightingSpec(**r) for r in data["relight"]),
        render_seed=int(data["render_seed"]), photo_seed=int(data["photo_seed"]),
    )  # fmt: skip


def _meta(object_dir: Path) -> dict[str, Any]:
    path = object_dir / "meta.json"
    if not path.is_file():
        raise ValueError(f"{object_dir}: not a finished synthetic object (no meta.json)")
    return dict(json.loads(path.read_text()))


def _face_parts(meta: dict[str, Any], spec: ObjectSpec, mesh: Mesh) -> np.ndarray:
    """[F] part label per face as `build_shape` gives it. A shared-mesh shape has one part (zeros, as build_shape
    makes them; its mesh file is then not needed); a procedural shape is rebuilt from its seed, checked against the
    stored shape parameters and face count."""
    if spec.shape.kind == "mesh":
        return np.zeros(mesh.num_faces, np.int64)
    shape = build_shape(spec.shape)
    if shape.parts.shape[0] != mesh.num_faces or json.loads(json.dumps(shape.params)) != meta["shape"]:
        raise ValueError(f"{spec.id}: the rebuilt shape differs from the stored one (another synth version?)")
    return shape.parts


def truth_field(object_dir: str | Path, basis: NeuralBasis | None = None) -> ProceduralMaterialField:
    """The exact ground-truth material field of a synthetic benchmark object, rebuilt as `ObjectWriter.write` built
    it: the spec from meta.json, the mesh from mesh.obj, `face_regions` and `ProceduralMaterialField`. Its
    G-buffers equal the stored ones and a render with a stored photo's seed reproduces the photo
    (tests/test_clean_scoring.py). Raises ValueError (BasisError) when the installed basis is not the one the
    object was made with (its latents would differ)."""
    object_dir = Path(object_dir)
    meta = _meta(object_dir)
    spec = object_spec_from_json(meta["spec"])
    basis = check_basis_id(meta["basis"]["id"], meta["basis"]["sha256"], basis)
    mesh = load_mesh(object_dir / "mesh.obj")
    needs_parts = spec.material.mode == "parts" and len(spec.material.regions) > 1
    parts = _face_parts(meta, spec, mesh) if needs_parts else np.zeros(mesh.num_faces, np.int64)
    return ProceduralMaterialField(spec.material, basis, face_regions(spec.material, mesh, parts))


# -- seeds, lightings, files -----------------------------------------------------------------------------------
def half_seed(base: int, tag: int, lighting: int, view: int, half: int) -> int:
    """A torch seed (32 bits) for one half-render: SeedSequence([base, tag, lighting, view, half]). lighting: 0
    for the capture's own map, j + 1 for relight/j; half: 0 (a) or 1 (b). Distinct tags give independent
    streams, so a variant's halves (CLEAN_TAG) are independent of the references' (REFERENCE_TAG)."""
    entropy = [int(base) % 2**64, tag, lighting, view, half]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def lightings(object_dir: str | Path) -> list[tuple[str, Path]]:
    """[(name, capture folder)]: ("capture", the object) then ("relight/j", its held-out lighting j) by j."""
    object_dir = Path(object_dir)
    relit = [p for p in (object_dir / "relight").glob("*") if (p / "transforms.json").is_file()]
    relit.sort(key=lambda p: (len(p.name), p.name))
    return [("capture", object_dir)] + [(f"relight/{p.name}", p) for p in relit]


def harness_envmap(cap: Any) -> EnvironmentMap:
    """The map as the eval harness and the capture loader make it (envmap_scale folded into the texels)."""
    return EnvironmentMap(cap.load_envmap(), cap.envmap_to_world, 1.0)


def reference_settings(object_dir: Path, spp_half: int, max_bounces: int) -> dict[str, Any]:
    """What decides the reference pixels (compared on resume): no times, paths or commit."""
    meta = _meta(object_dir)
    tracer = PathTracerConfig(spp=spp_half, max_bounces=max_bounces)
    return {"format": FORMAT, "object": meta["id"], "object_tree_sha256": meta.get("tree_sha256", ""),
            "basis_sha256": meta["basis"]["sha256"], "spp_half": spp_half, "max_bounces": max_bounces,
            "rr_depth": tracer.rr_depth, "strategy": tracer.strategy, "views": PRESET_ORBIT_VIEWS,
            "lightings": [name for name, _ in lightings(object_dir)],
            "seed_rule": "half_seed(spec.render_seed, REFERENCE_TAG=0x5EF, lighting, view, half)"}  # fmt: skip


def _check_settings(meta_path: Path, settings: dict[str, Any]) -> dict[str, Any] | None:
    """The stored meta.json (None when absent); ValueError naming what differs when its settings are others."""
    if not meta_path.is_file():
        return None
    stored = dict(json.loads(meta_path.read_text()))
    old = stored.get("settings", {})
    if old != settings:
        differ = sorted(k for k in {*old, *settings} if old.get(k) != settings.get(k))
        detail = ", ".join(f"{k}: stored {old.get(k)!r}, asked {settings.get(k)!r}" for k in differ)
        raise ValueError(f"{meta_path.parent}: references made with other settings ({detail}); use the same "
                         f"options or delete {meta_path.parent} to remake them")
    return stored


def render_references(object_dir: str | Path, spp_half: int = 128, max_bounces: int = 3,
                      basis: NeuralBasis | None = None, progress: Callable[[int, int], None] | None = None
                      ) -> dict[str, Any]:
    """Render (or finish) the references of a synthetic object (module docstring); returns references/meta.json.

    For each lighting (`lightings`) and orbital view 0..16: the ground-truth material, spp_half samples per pixel,
    twice with independent seeds, linear float32, with the capture's own camera and the harness's map. Files
    already there are skipped (resume); a folder made with other settings raises ValueError.
    progress(done, total) after each image (done counts images present)."""
    object_dir = Path(object_dir)
    if spp_half < 1 or max_bounces < 1:
        raise ValueError(f"spp_half and max_bounces must be >= 1, got {spp_half}, {max_bounces}")
    folder = object_dir / FOLDER
    settings = reference_settings(object_dir, spp_half, max_bounces)
    stored = _check_settings(folder / "meta.json", settings)
    render_seed = int(_meta(object_dir)["spec"]["render_seed"])
    names = lightings(object_dir)
    seeds = {f"{name}/{v:03d}_{h}": half_seed(render_seed, REFERENCE_TAG, li, v, hi)
             for li, (name, _) in enumerate(names) for v in range(PRESET_ORBIT_VIEWS)
             for hi, h in enumerate(HALVES)}  # fmt: skip
    record = {"settings": settings, "seeds": seeds, "complete": False, "seconds": 0.0, **(stored or {})}
    folder.mkdir(parents=True, exist_ok=True)
    for stale in [p for p in folder.rglob(".*") if is_temporary(p.name)]:  # a stopped run's half-written file
        stale.unlink(missing_ok=True)
    write_json_atomic(folder / "meta.json", record)
    todo = [k for k in seeds if not (folder / f"{k}.exr").is_file()]
    total = len(seeds)
    if progress is not None:
        progress(total - len(todo), total)
    start = time.perf_counter()
    field = truth_field(object_dir, basis) if todo else None
    tracer = PathTracer(PathTracerConfig(spp=spp_half, max_bounces=max_bounces))
    mesh = load_mesh(object_dir / "mesh.obj")
    done = total - len(todo)
    for name, cap_dir in names:
        mine = [k for k in todo if k.rsplit("/", 1)[0] == name]
        if not mine:
            continue
        assert field is not None
        cap = load_capture(cap_dir)
        scene = Scene(mesh, harness_envmap(cap), field)
        for key in mine:
            view = int(key.rsplit("/", 1)[1][:3])
            with torch.no_grad():
                image = tracer.render(scene, cap.frames[view].camera, seed=seeds[key]).cpu().numpy()
            path = folder / f"{key}.exr"
            path.parent.mkdir(parents=True, exist_ok=True)
            with replaced_atomically(path) as tmp:
                write_image(tmp, image.astype(np.float32))
            done += 1
            if progress is not None:
                progress(done, total)
    record.update(complete=all((folder / f"{k}.exr").is_file() for k in seeds),
                  seconds=round(float(record["seconds"]) + time.perf_counter() - start, 3))  # fmt: skip
    write_json_atomic(folder / "meta.json", record)
    return record


@dataclass
class References:
    """A finished references folder: settings (references/meta.json) and its images."""

    folder: Path
    settings: dict[str, Any]

    @property
    def spp_half(self) -> int:
        return int(self.settings["spp_half"])

    @property
    def max_bounces(self) -> int:
        return int(self.settings["max_bounces"])

    def halves(self, lighting: str, view: int) -> tuple[np.ndarray, np.ndarray]:
        """(a, b): linear float32 [H, W, 3] of orbital view `view` under `lighting` ("capture", "relight/j")."""
        a, b = (read_image(self.folder / lighting / f"{view:03d}_{h}.exr")[:, :, :3] for h in HALVES)
        return a, b


def has_references(object_dir: str | Path) -> bool:
    """Whether the object has a complete references folder (finished, and every image of it still there)."""
    folder = Path(object_dir) / FOLDER
    if not (folder / "meta.json").is_file():
        return False
    record = json.loads((folder / "meta.json").read_text())
    return bool(record.get("complete")) and all((folder / f"{k}.exr").is_file() for k in record.get("seeds", {}))


def load_references(object_dir: str | Path) -> References:
    """The object's references; ValueError when they are missing or unfinished."""
    folder = Path(object_dir) / FOLDER
    if not has_references(object_dir):
        raise ValueError(f"{folder}: no complete references (run `neumatex references` on the dataset)")
    return References(folder, dict(json.loads((folder / "meta.json").read_text())["settings"]))


# -- the noise-corrected PSNR ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CleanScore:
    """psnr: -10 log10(max(mse, MSE_FLOOR)) (dB), the noise-corrected PSNR; raw_psnr: of T(A) vs T(R) as they are;
    mse: the clean MSE estimate (display units^2, may be <= 0 from noise); mse_raw; noise_variant / noise_reference:
    the estimated variance of T(A) / T(R) (means of (T(X1) - T(X2))^2 / 4); standard_error: of `mse` over pixels
    (std of the per-pixel terms / sqrt(pixels); exact noise-only spread when the images agree, conservative when
    they differ); floored: mse was <= MSE_FLOOR; pixels: covered pixels scored."""

    psnr: float
    raw_psnr: float
    mse: float
    mse_raw: float
    noise_variant: float
    noise_reference: float
    standard_error: float
    floored: bool
    pixels: int


def _array(x: Any) -> np.ndarray:
    return (x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)).astype(np.float64)


def clean_psnr(halves_a: Any, halves_b: Any, ref_a: Any, ref_b: Any, mask: Any, tonemap: Tonemap,
               average: Literal["radiance", "display"] = "radiance") -> CleanScore:
    """Noise-corrected PSNR of a render A against a reference R, each given as two independent half-renders.

    halves_a, halves_b (A1, A2), ref_a, ref_b (R1, R2): linear radiance [..., H, W, 3] (numpy or torch; several
    views may be stacked in front); mask: [..., H, W] bool, the covered pixels scored (pooled over views);
    tonemap: the capture's T (display values in [0, 1]).

    With A = (A1 + A2) / 2 and R = (R1 + R2) / 2 in radiance (average="radiance", the default),
        MSE_clean = mean over masked pixels and channels of
                    (T(A) - T(R))^2 - (T(A1) - T(A2))^2 / 4 - (T(R1) - T(R2))^2 / 4,
        PSNR = -10 log10(max(MSE_clean, MSE_FLOOR)).
    Why: if the noise of the four half-renders is independent and T is locally linear at the noise scale,
    T(A) = a + e_A with Var(e_A) = E[(T(A1) - T(A2))^2] / 4, likewise for R, so E[(T(A) - T(R))^2] =
    (a - r)^2 + Var(e_A) + Var(e_R), and subtracting the two half-difference terms leaves an unbiased estimate of
    (a - r)^2, the squared difference of the noise-free tonemapped images. T is not linear (the sRGB curve, the
    clip at 1) and path-tracing noise is skewed, so two biases remain, both shrinking as the sample counts grow:
    Var(T(A)) is not quite Var(T(A1)) / 2 (the correction overshoots: -2.4e-4 at 8 + 8 spp on both sides,
    -0.9e-4 at 16 + 16, on a 24 px sphere whose raw MSE there is ~7e-3 and ~3.5e-3), and E[T(A)] lags T(a) by
    ~T'' Var(A) / 2 (Jensen), differently for A and R when their sample counts differ (partly cancelling the
    first: +0.8e-4 +- 0.5e-4 at 8 spp against references of 32, +0.2e-4 +- 0.3e-4 at 32 against 128, on an MSE of
    1.04e-3 between the ground truth and its base colour x 0.8).

    average="display" averages the halves after T instead: A' = (T(A1) + T(A2)) / 2 has variance exactly
    E[(T(A1) - T(A2))^2] / 4 whatever T does, so E[MSE_clean] = (E[T(A1)] - E[T(R1)])^2, no linearity assumed:
    exactly 0 for the same material at the same spp (measured -0.05e-4 +- 0.5e-4 at 8 + 8) and within noise of
    the truth for the two materials above (-0.6e-4 +- 0.6e-4 at 8 + 8). With fewer samples on A than on R the
    Jensen lags no longer cancel: on that smooth sphere display is the worse of the two (+4.5e-4 at 8 against 32,
    +0.8e-4 +- 0.3e-4 at 32 against 128). But radiance's variance term assumes T linear at the noise scale, which
    heavy-tailed path noise (a metal's highlights, fireflies) and the clip break: the ground truth of benchmark
    object 1 (metal and scattering) against its own references at 32 against 128 spp, 5 views, MSE 4.9e-4 (33.1
    dB) in radiance, 0.9e-4 (40.3 dB) in display (4.4e-6 at 128 against 128); four other objects' 0.4e-6 to
    2.4e-5, display never the worse (docs/design-notes.md item 48). Hence `clean_score` averages in display.

    raw_psnr: the uncorrected PSNR of T(A) against T(R). The estimate can come out <= 0 when A and R agree to
    within the noise; it is then floored (`floored`) and the PSNR reads 100 dB."""
    a1, a2, r1, r2 = (_array(x) for x in (halves_a, halves_b, ref_a, ref_b))
    m = _array(mask).astype(bool)
    if not (a1.shape == a2.shape == r1.shape == r2.shape) or a1.shape[:-1] != m.shape:
        raise ValueError(f"shapes differ: halves {a1.shape} {a2.shape}, references {r1.shape} {r2.shape}, "
                         f"mask {m.shape}")
    if not m.any():
        raise ValueError("mask covers no pixel")
    if average not in ("display", "radiance"):
        raise ValueError(f"average must be 'display' or 'radiance', got {average!r}")
    t = tonemap.apply_numpy
    ta1, ta2, tr1, tr2 = t(a1)[m], t(a2)[m], t(r1)[m], t(r2)[m]  # [P, 3] display values
    full_a, full_r = t((a1 + a2) / 2)[m], t((r1 + r2) / 2)[m]
    mean_a, mean_r = ((ta1 + ta2) / 2, (tr1 + tr2) / 2) if average == "display" else (full_a, full_r)
    noise_a, noise_r = (ta1 - ta2) ** 2 / 4, (tr1 - tr2) ** 2 / 4
    per_pixel = ((mean_a - mean_r) ** 2 - noise_a - noise_r).mean(-1)  # [P]: a pixel's channels share paths
    n = int(per_pixel.shape[0])
    mse, mse_raw = float(per_pixel.mean()), float(((full_a - full_r) ** 2).mean())
    se = float(per_pixel.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return CleanScore(psnr=-10 * math.log10(max(mse, MSE_FLOOR)),
                      raw_psnr=math.inf if mse_raw == 0 else -10 * math.log10(mse_raw), mse=mse, mse_raw=mse_raw,
                      noise_variant=float(noise_a.mean()), noise_reference=float(noise_r.mean()),
                      standard_error=se, floored=mse <= MSE_FLOOR, pixels=n)  # fmt: skip


# -- a variant against the references ------------------------------------------------------------------------
def coverage_mask(cap: Any, mesh: Mesh, view: int) -> np.ndarray:
    """[H, W] bool: pixels of frame `view` the mesh covers (and the capture's mask, when it has one)."""
    mask = render_gbuffer(mesh, cap.frames[view].camera).mask.cpu().numpy()
    user = cap.load_mask(view)
    return mask & np.asarray(user) if user is not None else mask


def clean_score(object_dir: str | Path, field: MaterialField, mesh: Mesh, lighting_names: Sequence[str],
                views: Sequence[int], spp_half: int, seed: int, refs: References | None = None,
                average: Literal["radiance", "display"] = "display") -> CleanScore:
    """`clean_psnr` of `field` (on `mesh`, e.g. a UV-unwrapped copy of the object's) against the object's
    references, pooled over the covered pixels of `views` under every lighting of `lighting_names`. The field is
    rendered twice per view with `spp_half` samples and seeds half_seed(seed, CLEAN_TAG, lighting, view, half), at
    the references' bounce count; the mask comes from the object's own mesh. average: see `clean_psnr` ("display":
    exact at the references' spp_half, and with fewer samples the more robust of the two)."""
    object_dir = Path(object_dir)
    refs = refs or load_references(object_dir)
    names = dict(lightings(object_dir))
    index = {name: i for i, name in enumerate(names)}
    object_mesh = load_mesh(object_dir / "mesh.obj")
    tracer = PathTracer(PathTracerConfig(spp=spp_half, max_bounces=refs.max_bounces))
    parts: dict[str, list[np.ndarray]] = {"a1": [], "a2": [], "r1": [], "r2": [], "m": []}
    tonemap: Tonemap | None = None
    for name in lighting_names:
        cap = load_capture(names[name])
        if tonemap is not None and cap.tonemap != tonemap:
            raise ValueError(f"{object_dir}: lightings with different tonemaps cannot be pooled")
        tonemap = cap.tonemap
        scene = Scene(mesh, harness_envmap(cap), field)
        for v in views:
            cam = cap.frames[v].camera
            with torch.no_grad():
                for h in (0, 1):
                    image = tracer.render(scene, cam, seed=half_seed(seed, CLEAN_TAG, index[name], v, h))
                    parts[f"a{h + 1}"].append(image.cpu().numpy())
            r1, r2 = refs.halves(name, v)
            parts["r1"].append(r1)
            parts["r2"].append(r2)
            parts["m"].append(coverage_mask(cap, object_mesh, v))
    if tonemap is None:
        raise ValueError("clean_score: no lighting to score")
    s = {k: np.stack(v) for k, v in parts.items()}
    return clean_psnr(s["a1"], s["a2"], s["r1"], s["r2"], s["m"], tonemap, average)


def clean_metrics(object_dir: str | Path, field: MaterialField, mesh: Mesh, render_views: Sequence[int],
                  relight_views: Sequence[int], spp_half: int, seed: int) -> dict[str, float]:
    """The harness's clean numbers (empty when the object has no complete references):

    psnr_pathtrace_clean (`render_views` under the capture's lighting), psnr_relight_clean (`relight_views` under
    every held-out lighting, pooled; only when both exist), each with `_raw` (the same renders without the
    noise correction), `_mse` (the clean MSE before the floor) and `_se` (its standard error)."""
    if spp_half < 1 or not has_references(object_dir):
        return {}
    refs = load_references(object_dir)
    out: dict[str, float] = {}
    relit = [name for name in refs.settings["lightings"] if name != "capture"]
    for key, names, views in (("psnr_pathtrace_clean", ["capture"], render_views),
                              ("psnr_relight_clean", relit, relight_views)):  # fmt: skip
        if not names or not views:
            continue
        score = clean_score(object_dir, field, mesh, names, views, spp_half, seed, refs)
        out.update({key: score.psnr, f"{key}_raw": score.raw_psnr, f"{key}_mse": score.mse,
                    f"{key}_se": score.standard_error})  # fmt: skip
    return out
