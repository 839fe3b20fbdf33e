"""The `neumatex` command line: render writes images, bad input gives a clear error and no traceback."""

from __future__ import annotations

import subprocess
import sys

from capture_fixtures import write_capture
from conftest import ENVMAPS, MESHES

from neumatex_core.imageio import read_image


def neumatex(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "neumatex_core.cli", *args], capture_output=True, text=True, timeout=300
    )


def test_render_preset_views(tmp_path):
    out = tmp_path / "render"
    res = neumatex(
        "render",
        "--mesh",
        str(MESHES / "suzanne.obj"),
        "--envmap",
        str(ENVMAPS / "studio.exr"),
        "--out",
        str(out),
        "--views",
        "0,17",
        "--resolution",
        "24",
        "--spp",
        "4",
    )
    assert res.returncode == 0, res.stderr
    for i in (0, 1):
        exr = read_image(out / f"view_{i:02d}.exr")
        png = read_image(out / f"view_{i:02d}.png")
        assert exr.shape == png.shape == (24, 24, 3)
        assert exr.min() >= 0 and exr.max() > 0
    assert (out / "views.png").is_file()


def test_render_capture_cameras(tmp_path):
    capture = write_capture(tmp_path / "cap", n_frames=2, resolution=16)
    res = neumatex("render", "--capture", str(capture), "--out", str(tmp_path / "out"), "--spp", "2")
    assert res.returncode == 0, res.stderr
    assert read_image(tmp_path / "out" / "view_01.png").shape == (16, 16, 3)


def test_render_bad_input_is_a_clear_error(tmp_path):
    bad = tmp_path / "broken.obj"
    bad.write_text("this is not a mesh\n")
    res = neumatex("render", "--mesh", str(bad), "--envmap", str(ENVMAPS / "studio.exr"), "--out", str(tmp_path))
    assert res.returncode == 2
    assert "broken.obj" in res.stderr and "Traceback" not in res.stderr + res.stdout
    res = neumatex("render", "--mesh", str(MESHES / "suzanne.obj"), "--envmap", str(tmp_path / "none.exr"))
    assert res.returncode == 2 and "none.exr" in res.stderr and "Traceback" not in res.stderr
    res = neumatex(
        "render", "--mesh", str(MESHES / "suzanne.obj"), "--envmap", str(ENVMAPS / "studio.exr"), "--views", "99"
    )
    assert res.returncode == 2 and "--views" in res.stderr


def test_command_line_rebuilds_the_config_it_describes():
    import argparse
    import shlex

    from neumatex_core.config import add_config_arguments, command_line, config_from_args
    from neumatex_core.eval.suite import EvalConfig

    cfg = EvalConfig(data="data/my split", out="runs/x", objects="every:5", relight_views="0,8", workers=2,
                     progress=False, allow_incomplete=True)
    line = command_line("neumatex eval", cfg)
    assert line.startswith("neumatex eval 'data/my split' ") and "--workers 2" in line and "--no-progress" in line
    assert "--preset" not in line  # defaults are left out
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, EvalConfig)
    assert config_from_args(EvalConfig, parser.parse_args(shlex.split(line)[2:])) == cfg
