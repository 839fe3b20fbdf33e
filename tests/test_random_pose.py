"""The random-pose variant of a synthetic object (neumatex_core/synth/random_pose.py, docs/benchmark.md): JPEG photos
with per-photo exposure and lens distortion, which the capture loader must bring back upright, undistorted and at
the truth's linear radiance.

One tiny object (test-000002, an ellipsoid with one region) written by the synth engine, 8 random-pose photos of
64 px at 16 spp with a strong lens (`lens=1.0`: k1 0.27, k2 0.27, so distortion moves the silhouette by pixels),
compared with 64 spp pinhole renders of its ground truth. Measured (2026-11-25): silhouettes of the undistorted
masks equal the truth's (0 pixels differ) where the raw distorted masks differ in 43-170 of 1770-2370; mean
radiance over the object / truth's 0.969-1.009 (the exposures are 0.72-1.37); the relative mean absolute error of
the blurred images (sigma 1.5 px, so that Monte Carlo noise does not dominate) has median 0.04 undistorted, 0.047
as stored, 0.20 with the exposure ignored, 0.40 upside down.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import ENVMAPS, MESHES
from scipy import ndimage

from neumatex_core.capture import load_capture
from neumatex_core.cli import main
from neumatex_core.eval.references import harness_envmap, truth_field
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import load_mesh
from neumatex_core.imageio import read_image
from neumatex_core.materials.neural_basis import load_basis
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.synth import SynthConfig, object_spec
from neumatex_core.synth.random_pose import RandomPoseConfig, write_random_pose
from neumatex_core.synth.spec import ENVMAP_SUFFIXES, MESH_SUFFIXES, shared_names
from neumatex_core.synth.writer import ObjectWriter

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

CFG = RandomPoseConfig(photos=8, resolution=64, spp=16, lens=1.0)


@pytest.fixture(scope="module")
def obj(tmp_path_factory) -> Path:
    meshes, envmaps = shared_names(MESHES, MESH_SUFFIXES), shared_names(ENVMAPS, ENVMAP_SUFFIXES)
    cfg = SynthConfig(resolution=16, spp=2, photos=0, relight_maps=0, relight_spp=1, meshes=str(MESHES),
                      envmaps=str(ENVMAPS))  # fmt: skip
    spec = object_spec("test", 2, 0, meshes, envmaps, 0)
    folder = tmp_path_factory.mktemp("random-pose") / spec.id
    ObjectWriter(spec, cfg, load_basis()).write(folder)
    assert write_random_pose(folder, CFG) is True
    return folder


def _rel(a: np.ndarray, truth: np.ndarray, sel: np.ndarray) -> float:
    blur = lambda x: ndimage.gaussian_filter(x, (1.5, 1.5, 0))  # noqa: E731
    return float(np.abs(blur(a)[sel] - blur(truth)[sel]).mean() / truth[sel].mean())


def test_random_pose_photos_load_upright_undistorted_and_at_their_exposure(obj):
    capture = obj / "random_pose"
    assert main(["validate", str(capture)]) == 0
    transforms = json.loads((capture / "transforms.json").read_text())
    assert transforms["camera_model"] == "OPENCV" and abs(transforms["k1"]) > 0.05
    assert all(f["file_path"].endswith(".jpg") for f in transforms["frames"])
    mesh = load_mesh(obj / "mesh.obj")
    with load_capture(obj) as own:
        scene = Scene(mesh, harness_envmap(own), truth_field(obj))
    tracer = PathTracer(PathTracerConfig(max_bounces=3, spp=64))
    rows = []
    with load_capture(capture) as cap:
        assert len(cap.frames) == CFG.photos and cap.frames[0].distortion is not None
        exposures = np.array(cap.exposures)
        assert np.abs(np.log2(exposures)).max() > 0.3  # the exposures differ enough for the check to mean anything
        for i, cam in enumerate(cap.cameras):
            truth = tracer.render(scene, cam, seed=7 + i).numpy()
            cover = render_gbuffer(mesh, cam).mask.numpy()
            mask = cap.load_mask(i)
            assert mask is not None
            raw_mask = read_image(capture / f"masks/{i:03d}.png")[:, :, 0] > 0.5
            lin = cap.tonemap_of(i).display_to_linear(cap.load_image(i))
            raw = cap.tonemap_of(i).display_to_linear(read_image(capture / cap.frames[i].image_path)[:, :, :3])
            ignored = cap.tonemap.display_to_linear(cap.load_image(i))
            sel = ndimage.binary_erosion(cover & mask & (lin.max(-1) < 0.98 / exposures[i]))
            rows.append({"xor": int((mask ^ cover).sum()), "raw_xor": int((raw_mask ^ cover).sum()),
                         "cover": int(cover.sum()), "ratio": float(lin[sel].mean() / truth[sel].mean()),
                         "rel": _rel(lin, truth, sel), "raw": _rel(raw, truth, sel),
                         "ignored": _rel(ignored, truth, sel), "flipped": _rel(lin[::-1], truth, sel)})  # fmt: skip
    xor, raw_xor, cover = (np.array([r[k] for r in rows]) for k in ("xor", "raw_xor", "cover"))
    # undistorted silhouettes match the truth's to within 1% of the object's pixels; the stored ones do not
    assert (xor <= 0.01 * cover).all(), rows
    assert raw_xor.sum() > 0.02 * cover.sum() and raw_xor.sum() > 10 * max(int(xor.sum()), 1), rows
    # per-photo exposure applied on load: radiance within 4% of the truth's for every photo
    ratio = np.array([r["ratio"] for r in rows])
    assert (np.abs(ratio - 1) < 0.04).all(), rows
    med = {k: float(np.median([r[k] for r in rows])) for k in ("rel", "raw", "ignored", "flipped")}
    assert med["rel"] < 0.07, med
    assert med["raw"] > med["rel"], med  # undistortion brings the pixels closer to the truth
    assert med["ignored"] > 2.5 * med["rel"] and med["flipped"] > 4 * med["rel"], med


def test_random_pose_is_deterministic_resumes_and_refuses_other_settings(obj, tmp_path):
    capture = obj / "random_pose"
    before = (capture / "transforms.json").read_bytes()
    assert write_random_pose(obj, CFG) is False  # kept
    assert (capture / "transforms.json").read_bytes() == before
    with pytest.raises(ValueError, match="other settings"):
        write_random_pose(obj, RandomPoseConfig(photos=9, resolution=64, spp=16, lens=1.0))
    # poses, exposures and lens depend only on the object's seeds: a fresh copy with other pixels (spp) agrees
    import shutil

    copy = tmp_path / obj.name
    shutil.copytree(obj, copy, ignore=shutil.ignore_patterns("random_pose"))
    write_random_pose(copy, RandomPoseConfig(photos=8, resolution=64, spp=1, lens=1.0))
    assert (copy / "random_pose" / "transforms.json").read_bytes() == before


def test_random_pose_resumes_an_interrupted_object_keeping_its_finished_photos(obj, tmp_path):
    """A run stopped after five of eight photos (no transforms.json yet) goes on from the sixth: the five are kept
    as they are (not rendered again) and the capture is byte for byte the one made in one go."""
    import shutil

    copy = tmp_path / obj.name
    shutil.copytree(obj, copy)
    capture = copy / "random_pose"
    made = {p.relative_to(capture).as_posix(): p.read_bytes() for p in capture.rglob("*") if p.is_file()}
    (capture / "transforms.json").unlink()
    for k in (5, 6, 7):
        (capture / f"images/{k:03d}.jpg").unlink()
    (capture / "masks/007.png").unlink()
    kept = {k: (capture / f"images/{k:03d}.jpg").stat().st_mtime_ns for k in range(5)}
    assert write_random_pose(copy, CFG) is True
    assert {k: (capture / f"images/{k:03d}.jpg").stat().st_mtime_ns for k in range(5)} == kept
    again = {p.relative_to(capture).as_posix(): p.read_bytes() for p in capture.rglob("*") if p.is_file()}
    assert again == made

