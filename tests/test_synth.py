"""Synthetic data engine: determinism, resume, manifest, valid captures, unit sphere, G-buffer consistency, splits.

Objects here are tiny (24 px, 4 spp, 1 photo, 1 held-out lighting at 2 spp, test-split meshes teapot and beetle);
the consistency test writes one convex object at 16 spp. The file takes 70 CPU seconds (user + system, worker and
CLI processes included), so about a minute on an idle 2-core machine (3-10 min on the shared one under load).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ENVMAPS, MESHES

from neumatex_core.capture import load_capture, validate_capture
from neumatex_core.geometry.camera import preset_views
from neumatex_core.geometry.mesh import load_mesh
from neumatex_core.imageio import read_image
from neumatex_core.materials.layered import PARAMETER_NAMES
from neumatex_core.materials.neural_basis import load_basis
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.synth import HELD_OUT_MESHES, SynthConfig, generate, object_spec
from neumatex_core.synth.dataset import MANIFEST, TIMINGS
from neumatex_core.synth.rerender import consistency_z, load_view, render_mean_variance
from neumatex_core.synth.shapes import ShapeSpec
from neumatex_core.synth.sheets import CAPTION, contact_sheets
from neumatex_core.synth.spec import ENVMAP_SUFFIXES, MESH_SUFFIXES, shared_names
from neumatex_core.synth.writer import ObjectWriter

TINY = dict(n=2, split="test", resolution=24, spp=4, photos=1, relight_maps=1, relight_spp=2, layered=True,
            workers=1, progress=False, meshes=str(MESHES), envmaps=str(ENVMAPS))  # fmt: skip


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def file_hashes(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != TIMINGS}  # fmt: skip


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "a"
    result = generate(SynthConfig(out=str(out), **TINY))  # type: ignore[arg-type]
    assert result.made == ["test-000000", "test-000001"] and result.complete
    return out


def test_same_seed_gives_identical_files_in_any_number_of_processes(dataset, tmp_path):
    other = tmp_path / "b"
    result = generate(SynthConfig(out=str(other), **{**TINY, "workers": 2}))  # type: ignore[arg-type]
    assert sorted(result.made) == ["test-000000", "test-000001"]
    a, b = file_hashes(dataset), file_hashes(other)
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []  # every file, manifest included, bit for bit
    # A different seed gives a different object.
    assert object_spec("test", 0, 1, [], []).material != object_spec("test", 0, 0, [], []).material


def test_resume_skips_finished_objects_and_shards_split_the_work(dataset, tmp_path):
    out = tmp_path / "resume"
    shutil.copytree(dataset, out)
    before = file_hashes(out)
    again = generate(SynthConfig(out=str(out), **TINY))  # type: ignore[arg-type]
    assert again.made == [] and again.skipped == 2 and again.complete
    # A crashed run: object 1 missing, its half-written temporary folder left behind.
    shutil.rmtree(out / "test-000001")
    (out / ".tmp-test-000001-99999" / "images").mkdir(parents=True)
    partial = generate(SynthConfig(out=str(out), **TINY))  # type: ignore[arg-type]
    assert partial.made == ["test-000001"] and partial.skipped == 1 and partial.complete
    assert not list(out.glob(".tmp-*"))
    assert file_hashes(out) == before
    # Sharding: with object 0 gone, shard 1/2 (odd indices) has nothing to do and leaves the manifest incomplete;
    # shard 0/2 makes object 0 only, and the two shards' folder is the single run's, manifest included.
    shutil.rmtree(out / "test-000000")
    odd = generate(SynthConfig(out=str(out), **{**TINY, "shard": "1/2"}))  # type: ignore[arg-type]
    assert odd.made == [] and odd.skipped == 1 and not odd.complete
    manifest = json.loads((out / MANIFEST).read_text())
    assert not manifest["complete"] and [o["id"] for o in manifest["objects"]] == ["test-000001"]
    even = generate(SynthConfig(out=str(out), **{**TINY, "shard": "0/2"}))  # type: ignore[arg-type]
    assert even.made == ["test-000000"] and even.skipped == 0 and even.complete
    assert file_hashes(out) == before
    # Other content options in the same folder are refused, naming the option.
    with pytest.raises(ValueError, match="spp"):
        generate(SynthConfig(out=str(out), **{**TINY, "spp": 8}))  # type: ignore[arg-type]


def test_manifest_lists_every_object_with_metadata(dataset):
    manifest = json.loads((dataset / MANIFEST).read_text())
    assert manifest["complete"] and manifest["n"] == 2 and manifest["split"] == "test"
    assert manifest["content"]["resolution"] == 24 and manifest["content"]["spp"] == 4
    assert manifest["basis"]["id"] == load_basis().basis_id
    assert manifest["held_out_meshes"] == list(HELD_OUT_MESHES)
    assert [o["id"] for o in manifest["objects"]] == ["test-000000", "test-000001"]
    for entry in manifest["objects"]:
        meta = json.loads((dataset / entry["id"] / "meta.json").read_text())
        assert entry["tree_sha256"] == meta["tree_sha256"] and entry["shape"] == "mesh"
        assert entry["mesh"] in HELD_OUT_MESHES and 1 <= entry["regions"] == len(entry["families"])
        assert entry["lighting"]["envmap_scale"] > 0 and 0 < entry["coverage"] < 1
        listed = {p.relative_to(dataset / entry["id"]).as_posix() for p in (dataset / entry["id"]).rglob("*")
                  if p.is_file() and p.name != "meta.json"}  # fmt: skip
        assert set(meta["files"]) == listed
    assert len((dataset / TIMINGS).read_text().splitlines()) == 2
    timing = json.loads((dataset / TIMINGS).read_text().splitlines()[0])
    assert {"rays", "field", "material", "write"} <= set(timing["stages"])


def test_every_object_is_a_valid_capture_with_ground_truth(dataset):
    views = preset_views(24)
    for obj in ("test-000000", "test-000001"):
        root = dataset / obj
        for capture, frames in ((root, 23), (root / "photos", 1), (root / "relight" / "0", 17)):
            assert validate_capture(capture) == [], capture
            with load_capture(capture) as cap:
                assert len(cap.frames) == frames and cap.envmap_scale > 0
                assert cap.load_image(0).shape == (24, 24, 3) and cap.load_mesh().num_faces > 0
                if capture == root:  # the preset views, in order
                    for frame, cam in zip(cap.frames, views, strict=True):
                        np.testing.assert_allclose(frame.camera.c2w, cam.c2w, atol=1e-6)
                        assert (frame.camera.fl_x, frame.camera.width) == (cam.fl_x, cam.width)
        frames = json.loads((root / "transforms.json").read_text())["frames"]
        assert len(frames) == 23 and [f["view"] for f in frames[16:18]] == ["orbit_16", "canonical_+x"]
        mask = read_image(root / frames[0]["mask_path"])[:, :, 0] > 0.5
        shapes = {"position": 3, "normal": 3, "basecolor": 3, "latent": 6, "pbr": 5, "region": 1}
        for key, channels in shapes.items():
            buf = read_image(root / frames[0]["gbuffers"][key])
            assert buf.shape == (24, 24, channels), key
            assert np.all(buf[~mask] == 0), key
        # The latent G-buffer holds each pixel's region's latent (the basis encoder of its parameters), exactly.
        material = json.loads((root / "material.json").read_text())
        region = read_image(root / frames[0]["gbuffers"]["region"])[mask][:, 0].astype(np.int64)
        latent = read_image(root / frames[0]["gbuffers"]["latent"])[mask]
        table = np.asarray([r["latent"] for r in material["regions"]], dtype=np.float32)
        np.testing.assert_array_equal(latent, table[region])
        params = torch.tensor([[r["params"][k] for k in PARAMETER_NAMES] for r in material["regions"]])
        with torch.no_grad():
            np.testing.assert_allclose(load_basis().encode(params).numpy(), table, atol=1e-6)
        assert np.abs(latent).max() <= 1
        normal = read_image(root / frames[0]["gbuffers"]["normal"])[mask]
        np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=1e-4)
        position = read_image(root / frames[0]["gbuffers"]["position"])[mask]
        assert np.linalg.norm(position, axis=-1).max() <= 1.0
        base = read_image(root / frames[0]["gbuffers"]["basecolor"])[mask]
        pbr = read_image(root / frames[0]["gbuffers"]["pbr"])[mask]
        assert 0 <= base.min() and base.max() <= 1 and pbr.min() >= 0 and pbr.max() <= 1
        linear = read_image(root / frames[0]["linear_path"])
        assert linear.shape == (24, 24, 3) and np.isfinite(linear).all() and linear[mask].mean() > 0
        assert read_image(root / frames[0]["layered_path"]).shape == (24, 24, 3)


def test_contact_sheets_show_each_object_view_base_colour_and_latents(dataset, tmp_path):
    paths = contact_sheets(dataset, tmp_path, "tiny", view=0, columns=2)
    assert [p.name for p in paths] == ["tiny-contact.png", "tiny-basecolor.png", "tiny-latents.png"]
    tile_h, tile_w = 24 + CAPTION, 24
    contact, base, latents = (read_image(p) for p in paths)
    assert contact.shape == base.shape == (3 + tile_h + 3, 3 + 2 * (tile_w + 3), 3)
    assert latents.shape == (3 + tile_h + 3, 3 + 4 * (tile_w + 3), 3)  # two tiles per object
    # Tiles are the stored view and G-buffers (8-bit), under a caption strip; uncovered pixels white.
    root = dataset / "test-000001"
    frame = json.loads((root / "transforms.json").read_text())["frames"][0]
    x0, y0 = 3 + tile_w + 3, 3 + CAPTION
    np.testing.assert_array_equal(contact[y0:y0 + 24, x0:x0 + 24], read_image(root / frame["file_path"])[:, :, :3])
    mask = read_image(root / frame["mask_path"])[:, :, 0] > 0.5
    assert np.all(base[y0:y0 + 24, x0:x0 + 24][~mask] == 1.0)
    latent = (read_image(root / frame["gbuffers"]["latent"])[:, :, 3:6] + 1) / 2
    x1 = 3 + 3 * (tile_w + 3)
    np.testing.assert_allclose(latents[y0:y0 + 24, x1:x1 + 24][mask], latent[mask], atol=0.5 / 255 + 1e-6)
    with pytest.raises(ValueError, match="manifest.json: not found"):
        contact_sheets(tmp_path, tmp_path)
    # A dataset still being made (no manifest yet, one object finished) is drawn only when asked.
    partial = tmp_path / "partial"
    shutil.copytree(dataset, partial, ignore=shutil.ignore_patterns("test-000000", MANIFEST))
    with pytest.raises(ValueError, match="--allow-incomplete"):
        contact_sheets(partial, tmp_path / "p")
    contact = read_image(contact_sheets(partial, tmp_path / "p", columns=2, allow_incomplete=True)[0])
    np.testing.assert_array_equal(contact[y0:y0 + 24, 3:27], read_image(root / frame["file_path"])[:, :, :3])


def test_meshes_lie_inside_the_unit_sphere(dataset):
    for obj in ("test-000000", "test-000001"):
        mesh = load_mesh(dataset / obj / "mesh.obj")
        assert np.linalg.norm(mesh.vertices, axis=1).max() <= 1.0
        assert np.linalg.norm(mesh.vertices, axis=1).max() > 0.9  # normalised, not shrunk


def test_held_out_meshes_never_appear_in_train():
    meshes, envmaps = shared_names(MESHES, MESH_SUFFIXES), shared_names(ENVMAPS, ENVMAP_SUFFIXES)
    train = [object_spec("train", i, 0, meshes, envmaps).shape for i in range(300)]
    used = {s.mesh for s in train if s.kind == "mesh"}
    assert used and not used & set(HELD_OUT_MESHES)
    assert len({s.kind for s in train}) == 6  # every procedural kind and shared meshes
    test = [object_spec("test", i, 0, meshes, envmaps).shape for i in range(40)]
    test_meshes = [s.mesh for s in test if s.kind == "mesh"]
    assert sorted(set(test_meshes)) == sorted(HELD_OUT_MESHES) and len(test_meshes) == 16
    assert not {s.seed for s in test} & {s.seed for s in train}


def test_rerender_from_stored_gbuffers_matches_the_stored_image(tmp_path):
    """Ground truth is consistent: view 0 of a written object, re-rendered from nothing but its stored files (mesh,
    map, rotation, scale, camera, base-colour and latent G-buffers), equals the stored image up to Monte Carlo noise.

    The object is convex (a sphere: no path reaches another surface point, so the view's G-buffers hold every
    material the render needs) with one region and a colour pattern of low frequency: G-buffers are point samples
    at pixel centres while the images average over the pixel (box filter), which only agree where the material
    is smooth at the pixel scale (docs/design-notes.md). Tolerances from the per-pixel standard error:
    z = (stored - re-render) / sqrt(var/16 + var/64) per pixel and channel, var the per-sample variance from a
    third, independent render (a variance from the re-render's own samples correlates with its mean and biases z
    for the skewed radiance of a sun). With n covered pixels (channels of a pixel are correlated, so n and not 3n
    independent values), no bias: |mean z| < 5 / sqrt(n); N(0, 1) spread: the median |z| of a standard normal is
    0.674 with standard error 0.5 / (2 phi(0.674) sqrt(n)) = 0.786 / sqrt(n), allowed 5 of them."""
    meshes, envmaps = shared_names(MESHES, MESH_SUFFIXES), shared_names(ENVMAPS, ENVMAP_SUFFIXES)
    spec = object_spec("train", 7, 0, meshes, envmaps)
    material = dataclasses.replace(spec.material, regions=spec.material.regions[:1], color_frequency=1.0)
    spec = dataclasses.replace(spec, shape=ShapeSpec("sphere", 11), material=material)
    assert spec.lighting.kind == "sky"  # a sun: the hardest lighting for the noise model
    cfg = SynthConfig(resolution=24, spp=16, photos=0, relight_maps=0, meshes=str(MESHES), envmaps=str(ENVMAPS))
    basis = load_basis()
    ObjectWriter(spec, cfg, basis).write(tmp_path / "obj")
    stored = load_view(tmp_path / "obj", 0)
    tracer = PathTracer(PathTracerConfig(max_bounces=cfg.max_bounces))
    scene = Scene(stored.mesh, stored.envmap, stored.field(basis))
    spp, n = 64, int(stored.mask.sum())

    def z_scores() -> np.ndarray:
        mean, _ = render_mean_variance(tracer, scene, stored.camera, spp, seed=stored.seed + 12345)
        _, var = render_mean_variance(tracer, scene, stored.camera, spp, seed=stored.seed + 54321)
        return consistency_z(stored.image, cfg.spp, mean, var, spp)[stored.mask]

    def problems(z: np.ndarray) -> list[str]:
        """Why z does not look like N(0, 1) noise (empty when it does)."""
        out = []
        if not np.isfinite(z).all():
            out.append("non-finite z")
        if abs(z.mean()) >= 5 / np.sqrt(n):
            out.append(f"bias: mean z = {z.mean() * np.sqrt(n):.2f} / sqrt(n)")
        if abs(np.median(np.abs(z)) - 0.674) >= 5 * 0.786 / np.sqrt(n):
            out.append(f"spread: median |z| = {np.median(np.abs(z)):.3f}")
        return out

    assert n > 200
    assert problems(z_scores()) == []  # measured: mean z 0.0-1.1 / sqrt(n), median |z| 0.64-0.74 over 8 seeds
    # The check has power: a base-colour G-buffer 10% too dark (measured: mean z = 11.7 / sqrt(n)) or latents
    # moved by 0.3 (median |z| 1.29) are caught.
    scene.material = dataclasses.replace(stored, base_color=stored.base_color * 0.9).field(basis)
    assert any(p.startswith("bias") for p in problems(z_scores()))
    scene.material = dataclasses.replace(stored, latent=np.clip(stored.latent + np.float32(0.3), -1, 1)).field(basis)
    assert problems(z_scores()) != []


def test_cli_synth_bad_options_are_clear_errors(tmp_path):
    res = subprocess.run([sys.executable, "-m", "neumatex_core.cli", "synth", "--out", str(tmp_path / "x"),
                          "--shard", "3/2"], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 2 and "error: --shard" in res.stderr and "Traceback" not in res.stderr
    res = subprocess.run([sys.executable, "-m", "neumatex_core.cli", "synth", "--out", str(tmp_path / "x"),
                          "--meshes", str(tmp_path / "none")], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 2 and "none" in res.stderr and "Traceback" not in res.stderr
