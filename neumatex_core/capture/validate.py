"""Full validation of a capture: every problem at once, each naming its file and the reason in plain words.

On top of `parse_capture`'s structural checks (schema, intrinsics, rigid poses, paths, missing files,
duplicates, envmap_to_world) this reads every file: images and masks (corrupt, size vs intrinsics, mask vs
image), the mesh (faces, finite vertices), the environment map (2:1 equirectangular, NaN/inf/negative
values) and checks that every camera sees some of the mesh.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TypeVar

import numpy as np

from neumatex_core.capture.loader import (
    TRANSFORMS,
    ParsedCapture,
    ParsedFrame,
    allow_outside_paths,
    is_zip,
    open_capture_folder,
    outside_paths_allowed,
    parse_capture,
)
from neumatex_core.capture.model import CaptureError, Problem
from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.mesh import Mesh, MeshError, load_mesh
from neumatex_core.imageio import ImageError, read_image
from neumatex_core.lighting.envmap import read_envmap

MAX_VISIBILITY_VERTICES = 5000
MIN_MESH_SPAN_PX = 4  # the mesh must span at least this many pixels in some photo
T = TypeVar("T")


@dataclass
class ValidationReport:
    """Problems found plus, for the OK line, what was read: frame count, mesh faces, envmap (w, h)."""

    problems: list[Problem] = field(default_factory=list)
    warnings: list[Problem] = field(default_factory=list)
    n_frames: int = 0
    mesh_faces: int | None = None
    envmap_size: tuple[int, int] | None = None

    @property
    def ok(self) -> bool:
        return not self.problems


def _reason(exc: Exception, path: Path) -> str:
    """The exception text on one line, without the absolute path (the Problem names the file already)."""
    return _reason_text(str(exc), path)


def _reason_text(text: str, path: Path) -> str:
    text = text.replace(f"{path}: ", "").replace(str(path), "the file")
    return "; ".join(line.strip() for line in text.splitlines() if line.strip())


def _guard(problems: list[Problem], file: str, check: Callable[[], T]) -> T | None:
    """Run one file's check; an unexpected exception becomes a Problem for that file instead of a crash."""
    try:
        return check()
    except Exception as exc:  # reported, never raised: the other checks must still run
        text = re.sub(r"(?<![\w.])/\S*/", "", str(exc))  # no server paths in the message
        problems.append(Problem(file, f"could not be checked ({type(exc).__name__}: {text})"))
        return None


def _visible_pixels(camera: Camera, vertices: np.ndarray) -> np.ndarray:
    """Image positions [M, 2] of the world points [N, 3] that lie in front of the camera and inside its image."""
    px, front = camera.project(np.asarray(vertices, dtype=np.float64))
    inside = (px[:, 0] >= 0) & (px[:, 0] <= camera.width) & (px[:, 1] >= 0) & (px[:, 1] <= camera.height)
    return np.asarray(px[front & inside])


def sees_mesh(camera: Camera, vertices: np.ndarray) -> bool:
    """Whether any of the world points [N, 3] lies in front of the camera and inside its image."""
    return len(_visible_pixels(camera, vertices)) > 0


def mesh_span(camera: Camera, vertices: np.ndarray) -> float:
    """How many pixels across the visible part of the points [N, 3] spans in the camera's image (0 if none)."""
    px = _visible_pixels(camera, vertices)
    return float((px.max(axis=0) - px.min(axis=0)).max()) if len(px) else 0.0


def _subsample(vertices: np.ndarray, n: int = MAX_VISIBILITY_VERTICES) -> np.ndarray:
    if len(vertices) <= n:
        return vertices
    return vertices[np.linspace(0, len(vertices) - 1, n).astype(np.int64)]


def _check_frame(parsed: ParsedCapture, f: ParsedFrame, problems: list[Problem]) -> None:
    image_hw: tuple[int, int] | None = None
    if f.image_path is not None:
        path, name = f.image_path, parsed.rel(f.image_path)
        try:
            img = read_image(path)
        except ImageError as exc:
            problems.append(Problem(name, _reason(exc, path)))
        else:
            image_hw = (img.shape[0], img.shape[1])
            if img.shape[2] not in (1, 3, 4):
                problems.append(Problem(name, f"image has {img.shape[2]} channels; expected 1, 3 or 4"))
            if not np.isfinite(img).all():
                problems.append(Problem(name, "image has NaN or infinite pixel values"))
            if f.size is not None and (img.shape[1], img.shape[0]) != f.size:
                problems.append(
                    Problem(
                        name,
                        f"image is {img.shape[1]}x{img.shape[0]} pixels but the intrinsics of"
                        f" {f.label} say w x h = {f.size[0]}x{f.size[1]}",
                    )
                )
    if f.mask_path is not None:
        path, name = f.mask_path, parsed.rel(f.mask_path)
        try:
            mask = read_image(path)
        except ImageError as exc:
            problems.append(Problem(name, _reason(exc, path)))
            return
        expected = image_hw or (None if f.size is None else (f.size[1], f.size[0]))
        if expected is not None and mask.shape[:2] != expected:
            problems.append(
                Problem(
                    name,
                    f"mask is {mask.shape[1]}x{mask.shape[0]} pixels but its image"
                    f" {f.name} is {expected[1]}x{expected[0]}",
                )
            )


def _check_mesh(parsed: ParsedCapture, report: ValidationReport) -> Mesh | None:
    if parsed.mesh_path is None:
        return None
    path = parsed.mesh_path
    try:
        mesh = load_mesh(path, smooth=False)
    except MeshError as exc:
        report.problems.append(Problem(parsed.rel(path), _reason(exc, path)))
        return None
    report.mesh_faces = mesh.num_faces
    return mesh


def _check_envmap(parsed: ParsedCapture, report: ValidationReport) -> None:
    if parsed.envmap_path is None:
        return
    path, name = parsed.envmap_path, parsed.rel(parsed.envmap_path)
    pixels, problems = read_envmap(path)
    if pixels is not None:
        report.envmap_size = (pixels.shape[1], pixels.shape[0])
    report.problems.extend(Problem(name, _reason_text(msg, path)) for msg in problems)


def _check_visibility(parsed: ParsedCapture, mesh: Mesh, problems: list[Problem]) -> None:
    points = _subsample(mesh.vertices)
    spans = [mesh_span(f.camera, points) for f in parsed.frames if f.camera is not None]
    if spans and 0 < max(spans) < MIN_MESH_SPAN_PX and parsed.mesh_path is not None:
        problems.append(
            Problem(
                parsed.rel(parsed.mesh_path),
                f"the mesh spans at most {max(spans):.2g} pixels in the photos (at least {MIN_MESH_SPAN_PX} are"
                " needed): its surface is too small for the views; check its units and the camera positions",
            )
        )
    for f in parsed.frames:
        if f.camera is not None and not sees_mesh(f.camera, points):
            problems.append(
                Problem(
                    parsed.rel(f.image_path) if f.image_path else f.name,
                    f"the camera of {f.label} does not see the mesh (no mesh vertex is in front of it and"
                    " inside its image): check transform_matrix and the OpenGL convention (-Z forward)",
                )
            )


def check_capture_folder(root: Path) -> ValidationReport:
    """Every problem of the capture whose transforms.json is in `root` (see module doc)."""
    parsed = parse_capture(root)
    report = ValidationReport(problems=parsed.problems, warnings=parsed.warnings, n_frames=len(parsed.frames))
    if not parsed.schema_ok:
        return report
    problems = report.problems
    for f in parsed.frames:
        _guard(problems, f.name, partial(_check_frame, parsed, f, problems))
    mesh_name = parsed.rel(parsed.mesh_path) if parsed.mesh_path else "mesh"
    mesh = _guard(problems, mesh_name, partial(_check_mesh, parsed, report))
    envmap_name = parsed.rel(parsed.envmap_path) if parsed.envmap_path else "envmap"
    _guard(problems, envmap_name, partial(_check_envmap, parsed, report))
    if mesh is not None:
        _guard(problems, TRANSFORMS, partial(_check_visibility, parsed, mesh, problems))
    return report


def inspect_capture(path: str | Path) -> ValidationReport:
    """Validate a capture folder or zip (a zip is extracted safely to a temporary folder, then removed)."""
    try:
        opened = open_capture_folder(path)
    except CaptureError as exc:
        return ValidationReport(problems=exc.problems)
    try:
        with allow_outside_paths(outside_paths_allowed() and not is_zip(Path(path))):  # a zip is self-contained
            return check_capture_folder(opened.root)
    finally:
        if opened.workdir is not None:
            opened.workdir.cleanup()


def validate_capture(path: str | Path) -> list[Problem]:
    """Every problem with the capture folder or zip at `path` (empty when it is valid)."""
    return inspect_capture(path).problems
