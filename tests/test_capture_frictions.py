"""Frictions of issue 18, one test each: EXIF-rotated JPEGs load upright; tonemap keys the format does not know;
small negative noise in an HDR map; photos in the preset directions at another distance; a capture naming
../mesh.obj (local CLI yes, uploads and zips no); the asset's tensors file mode; load_mesh's normals."""

from __future__ import annotations

import json
import logging
import os
import stat
from pathlib import Path

import numpy as np
import pytest
import torch
from capture_fixtures import read_transforms, write_capture, write_transforms, zip_capture
from PIL import Image, ImageOps

from neumatex_core.capture import load_capture, validate_capture
from neumatex_core.capture.loader import allow_outside_paths
from neumatex_core.capture.validate import inspect_capture
from neumatex_core.cli import main
from neumatex_core.geometry.camera import PRESET_DISTANCE, preset_views
from neumatex_core.geometry.mesh import load_mesh
from neumatex_core.imageio import image_size, read_image, write_image
from neumatex_core.lighting.envmap import NEGATIVE_NOISE_FRACTION, EnvironmentMap, EnvmapError
from neumatex_core.novel_view.presets import match_preset_views
from neumatex_core.pipeline import ExtractConfig, run_stage

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


# ------------------------------------------------------------------------------------------ EXIF orientation


def upright_image(w: int = 48, h: int = 32) -> Image.Image:
    """A smooth, asymmetric RGB picture (JPEG keeps it well), wider than tall so that a wrong turn shows."""
    ys, xs = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    rgb = np.stack([xs, ys, 0.5 + 0.4 * np.sin(3 * xs + 2 * ys)], axis=2)
    rgb[: h // 3, : w // 4] = [1.0, 0.1, 0.1]  # a red block in the top-left corner
    return Image.fromarray((rgb * 255).round().astype(np.uint8))


@pytest.mark.parametrize(("orientation", "stored_turn"), [(6, Image.Transpose.ROTATE_90),
                                                          (8, Image.Transpose.ROTATE_270)])  # fmt: skip
def test_exif_rotated_jpeg_loads_upright(tmp_path: Path, orientation: int, stored_turn: Image.Transpose) -> None:
    upright = upright_image()
    upright.save(tmp_path / "upright.jpg", quality=95)
    stored = upright.transpose(stored_turn)  # what a camera held sideways writes; the tag says how to turn it back
    exif = Image.Exif()
    exif[0x0112] = orientation
    stored.save(tmp_path / "rotated.jpg", quality=95, exif=exif.tobytes())
    with Image.open(tmp_path / "rotated.jpg") as im:
        assert im.size == (32, 48) and im.getexif()[0x0112] == orientation
        reference = np.asarray(ImageOps.exif_transpose(im).convert("RGB"), dtype=np.float32) / 255
    loaded = read_image(tmp_path / "rotated.jpg")
    expected = read_image(tmp_path / "upright.jpg")
    assert loaded.shape == (32, 48, 3) and image_size(tmp_path / "rotated.jpg") == (48, 32)
    assert read_image(tmp_path / "rotated.jpg", orient_upright=False).shape == (48, 32, 3)  # as stored
    # JPEG tolerance: both files went through the codec once (quality 95), in two orientations.
    assert float(np.abs(loaded - expected).mean()) < 0.01 and float(np.abs(loaded - expected).max()) < 0.12
    assert float(np.abs(loaded - reference).max()) <= 2 / 255  # what PIL's exif_transpose gives
    assert loaded[2, 2, 0] > 0.9 and loaded[2, 2, 1] < 0.2  # the red corner is top-left again


# ------------------------------------------------------------------------------------------------- tonemap


def test_unknown_tonemap_keys_are_ignored_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    root = write_capture(tmp_path / "cap", extra={"tonemap": {"exposure": 1.5, "gamma": 2.2, "white_point": 0.9}})
    assert validate_capture(root) == []
    with caplog.at_level(logging.WARNING, logger="neumatex.capture"), load_capture(root) as cap:
        assert cap.tonemap.exposure == 1.5 and cap.tonemap.transfer == "srgb"
    assert "tonemap keys gamma, white_point are not part of the format" in caplog.text
    assert main(["validate", str(root)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("OK:") and "warning: transforms.json: tonemap keys gamma, white_point" in out
    # clip and oetf say what the tonemap does: taken when they agree with it, refused when they contradict it.
    data = read_transforms(root)
    data["tonemap"] = {"clip": True, "oetf": "linear"}
    write_transforms(root, data)
    with load_capture(root) as cap:
        assert cap.tonemap.transfer == "linear"
    for bad, words in (({"clip": False}, "always clips"), ({"oetf": "pq"}, "'pq' is not a transfer"),
                       ({"oetf": "srgb", "transfer": "linear"}, "contradicts")):  # fmt: skip
        data["tonemap"] = bad
        write_transforms(root, data)
        problems = validate_capture(root)
        assert len(problems) == 1 and words in problems[0].message and problems[0].file == "transforms.json"


# ---------------------------------------------------------------------------------------- envmap negatives


def test_small_negative_envmap_noise_passes_everywhere_larger_and_nan_do_not(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = write_capture(tmp_path / "cap", envmap_value=0.8)  # the mean of forest.exr, which has such texels
    pixels = np.full((16, 32, 3), 0.8, np.float32)
    pixels[3, 4], pixels[5, 6, 1], pixels[7, 8] = -0.0017, -0.0017, -0.0009
    write_image(root / "envmap.exr", pixels)
    assert 0.0017 < NEGATIVE_NOISE_FRACTION * 0.8  # the one threshold (lighting/envmap.py) covers it
    assert validate_capture(root) == []
    with load_capture(root) as cap:
        assert cap.load_envmap().min() == 0.0  # clamped on load
    assert float(EnvironmentMap.from_file(root / "envmap.exr").texels.min()) == 0.0
    render = ["render", "--mesh", str(root / "mesh.obj"), "--envmap", str(root / "envmap.exr"), "--out",
              str(tmp_path / "render"), "--views", "0", "--resolution", "8", "--spp", "1", "--device", "cpu"]
    assert main(render) == 0, capsys.readouterr().err
    for value, words in ((-0.5, "negative values"), (np.nan, "NaN")):
        pixels[3, 4] = value
        write_image(root / "envmap.exr", pixels)
        problems = validate_capture(root)
        assert [p.file for p in problems] == ["envmap.exr"] and words in problems[0].message
        with pytest.raises(EnvmapError, match=words):
            EnvironmentMap.from_file(root / "envmap.exr")
        assert main(render) == 2
        err = capsys.readouterr().err
        assert "envmap.exr" in err and words in err and "Traceback" not in err


# ---------------------------------------------------------------------------------------------- preset views


def preset_capture(root: Path, distance: float) -> Path:
    write_capture(root, n_frames=23, resolution=32)
    data = read_transforms(root)
    for frame, cam in zip(data["frames"], preset_views(32, distance=distance), strict=True):
        frame["transform_matrix"] = cam.c2w.tolist()
    write_transforms(root, data)
    return root


def test_preset_directions_at_another_distance_are_blended_and_say_why(tmp_path: Path) -> None:
    exact = preset_capture(tmp_path / "exact", PRESET_DISTANCE)
    with load_capture(exact) as cap:
        assert match_preset_views(cap.cameras).frames == list(range(23))
    near = preset_capture(tmp_path / "near", 3.0)
    with load_capture(near) as cap:
        match = match_preset_views(cap.cameras)
    assert match.frames is None and match.aimed == 23
    assert "in the directions of 23 preset view(s) but not at their poses" in match.reason
    assert "at distance 3 from the origin instead of 3.2 (off by 0.2)" in match.reason
    assert "the preset views are at distance 3.2" in match.reason
    config = ExtractConfig.preset("tiny", init="random", device="cpu")
    messages: list[str] = []
    for stage in ("validate", "prepare_views"):
        run_stage(stage, near, tmp_path / "work", config, lambda p: messages.append(p.message))
    source = json.loads((tmp_path / "work" / "prepare_views" / "views.json").read_text())["source"]
    assert source.startswith("blended from 23 photos") and "instead of 3.2" in source
    assert match.reason in messages
    run_stage("validate", exact, tmp_path / "work2", config)
    run_stage("prepare_views", exact, tmp_path / "work2", config)
    assert json.loads((tmp_path / "work2" / "prepare_views" / "views.json").read_text())["source"] == \
        "the capture's preset views"


# ----------------------------------------------------------------------------------------- paths outside


def test_a_shared_mesh_outside_the_capture_is_for_local_use_only(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    root = write_capture(tmp_path / "relight" / "0")
    os.replace(root / "mesh.obj", tmp_path / "relight" / "mesh.obj")  # one mesh shared by the relit captures
    data = read_transforms(root)
    data["mesh"] = "../mesh.obj"
    write_transforms(root, data)
    # Uploads (the service validates with inspect_capture, services/uploads.py) and plain loads refuse it.
    problems = inspect_capture(root).problems
    assert len(problems) == 1 and "mesh path '../mesh.obj' leaves the capture folder" in problems[0].message
    assert main(["validate", str(root)]) == 1
    # Local use, asked for explicitly: the CLI option and the context manager.
    assert main(["validate", str(root), "--allow-outside-paths"]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("OK: 4 frames")
    with allow_outside_paths(), load_capture(root) as cap:
        assert cap.mesh_path == tmp_path / "relight" / "mesh.obj" and cap.load_mesh().num_faces > 0
        assert validate_capture(root) == []
    assert validate_capture(root) != []  # the permission ends with the block
    # A zip is self-contained: never, even when asked.
    archive = zip_capture(root, tmp_path / "upload.zip")
    with allow_outside_paths():
        assert any("leaves the capture folder" in p.message for p in validate_capture(archive))
    assert main(["validate", str(archive), "--allow-outside-paths"]) == 1
    # render --capture takes the option too.
    assert main(["render", "--capture", str(root), "--out", str(tmp_path / "r"), "--spp", "1", "--device", "cpu",
                 "--allow-outside-paths"]) == 0  # fmt: skip
    assert main(["render", "--capture", str(root), "--out", str(tmp_path / "r2"), "--spp", "1", "--device",
                 "cpu"]) == 2  # fmt: skip


# --------------------------------------------------------------------------------------------- asset files


def test_every_asset_file_has_the_same_mode(tmp_path: Path) -> None:
    from neumatex_core.assets import asset_from_triplane, write_asset
    from neumatex_core.fields.neural_field import TriplaneMaterialField
    from neumatex_core.fields.triplane import Triplane
    from neumatex_core.geometry.mesh import icosphere
    from neumatex_core.materials.neural_basis import load_basis

    torch.manual_seed(0)
    from neumatex_core.fields.decoders import MaterialDecoder

    triplane = Triplane(4, 8, init_std=0.1)
    basis = load_basis()
    field = TriplaneMaterialField(triplane, MaterialDecoder(triplane.feature_dim), basis)
    asset = asset_from_triplane("modes", icosphere(2), field, resolution=16)
    folder = write_asset(asset, tmp_path / "asset")
    modes = {p.relative_to(folder).as_posix(): stat.S_IMODE(p.stat().st_mode) for p in folder.rglob("*")
             if p.is_file()}  # fmt: skip
    assert "tensors.safetensors" in modes and modes["tensors.safetensors"] == modes["mesh.obj"]
    assert set(modes.values()) == {modes["mesh.obj"]}, modes
    assert modes["mesh.obj"] & 0o044  # readable by others (0644 under the usual umask 022)


# -------------------------------------------------------------------------------------------------- meshes


def test_load_mesh_recomputes_normals_as_its_docstring_says(tmp_path: Path) -> None:
    path = tmp_path / "tri.obj"  # a triangle in the z = 0 plane whose file normals point along +X
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 1 0 0\nvn 1 0 0\nvn 1 0 0\nf 1//1 2//2 3//3\n")
    mesh = load_mesh(path)
    assert mesh.vertex_normals is not None
    np.testing.assert_allclose(mesh.vertex_normals, np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-6)  # from the face
    assert load_mesh(path, smooth=False).vertex_normals is None
    doc = load_mesh.__doc__ or ""
    assert "recomputed from the faces" in doc and "not\n    used" in doc


# ------------------------------------------------------------------------------------------- --compare-pbr


def test_extract_compare_pbr_writes_the_baseline_beside_the_neural_scores(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    capture = Path(__file__).resolve().parents[1] / "examples" / "teapot" / "photos"
    out = tmp_path / "asset"
    args = ["extract", str(capture), "--out", str(out), "--preset", "tiny", "--init", "random", "--device", "cpu",
            "--no-progress", "--compare-pbr"]  # fmt: skip
    assert main(args) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    metrics = json.loads((out / "manifest.json").read_text())["metrics"]
    stored = json.loads((tmp_path / ".asset.work" / "compare_pbr" / "done.json").read_text())
    assert metrics["psnr_photos_pbr_baseline"] == stored["psnr_photos_pbr_baseline"]
    assert 5 < metrics["psnr_photos_pbr_baseline"] < 60 and np.isfinite(metrics["psnr_photos"])
    assert metrics["psnr_gain_vs_pbr_baseline_db"] == pytest.approx(
        metrics["psnr_photos"] - metrics["psnr_photos_pbr_baseline"])
    config = ExtractConfig.preset("tiny", init="random")
    assert metrics["pbr_baseline_steps"] == config.tto_config().total_steps()  # equal steps
    assert f"photo PSNR {metrics['psnr_photos_pbr_baseline']:.2f} dB" in printed
    page = (out / "report" / "index.html").read_text()
    assert "Against the PBR baseline" in page and "PBR baseline TTO (--compare-pbr)" in page
    from neumatex_core.assets import read_asset

    assert read_asset(out).metrics["psnr_photos_pbr_baseline"] == metrics["psnr_photos_pbr_baseline"]
    assert main([*args[:3], str(tmp_path / "a.zip"), *args[4:]]) == 2  # a zip asset has no room for it
    assert "--compare-pbr" in capsys.readouterr().err
