"""Loading a capture: a folder or a .zip of it (optionally with one top-level folder inside).

transforms.json is parsed with pydantic models, so schema errors come back as "field path: reason".
`parse_capture` collects every structural problem (schema, intrinsics, poses, paths, missing files) without
reading image or mesh data; `load_capture` turns a clean parse into a `Capture` and raises CaptureError
otherwise. Reading the files' contents is `validate_capture`'s job (validate.py).
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError

from neumatex_core.capture.archive import (
    DEFAULT_MAX_FILES,
    DEFAULT_MAX_RATIO,
    DEFAULT_MAX_TOTAL_BYTES,
    extract_zip,
)
from neumatex_core.capture.distortion import Distortion
from neumatex_core.capture.model import Capture, CaptureError, Frame, Problem
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.geometry.camera import Camera

TRANSFORMS = "transforms.json"
RIGID_TOLERANCE = 1e-3  # max |R^T R - I| and |det R - 1| for a rotation
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff")  # tried for extension-less file_path
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")  # nerfstudio's; k4 (an r^8 radial term) has no OpenCV twin
UNSUPPORTED_MODELS = ("FISHEYE", "EQUIRECT")  # nerfstudio camera_model values that are not a (distorted) pinhole
TONEMAP_KEYS = ("exposure", "transfer", "oetf", "clip")  # oetf: an alias of transfer; clip: T always clips to [0, 1]
K4_MESSAGE = ("lens distortion k4 (nerfstudio's r^8 radial term) is not supported (k1 k2 k3 p1 p2 are, as in "
              "OpenCV); undistort the photos and set it to 0")
MAX_FOLDER_CHAIN = 8  # single folders looked into for transforms.json
TOO_DEEP = "has lists or objects nested too deeply to read"
log = logging.getLogger("neumatex.capture")
# Whether transforms.json may name files outside the capture folder (`allow_outside_paths`): never for uploads
# or zips, only where a local user asks for it (`neumatex ... --allow-outside-paths`).
_ALLOW_OUTSIDE: ContextVar[bool] = ContextVar("neumatex_allow_outside_paths", default=False)


def outside_paths_allowed() -> bool:
    """Whether an `allow_outside_paths` block is in force."""
    return _ALLOW_OUTSIDE.get()


@contextmanager
def allow_outside_paths(allow: bool = True) -> Iterator[None]:
    """Inside this block, captures loaded from a folder may name files outside it (`../mesh.obj`, absolute paths):
    for local use, e.g. relit captures sharing one mesh. Zips and the job service's uploads never get this."""
    token = _ALLOW_OUTSIDE.set(allow)
    try:
        yield
    finally:
        _ALLOW_OUTSIDE.reset(token)


# ---------------------------------------------------------------------------------------------- schema


def _square(n: int) -> Any:
    def check(m: list[list[float]]) -> list[list[float]]:
        if len(m) != n or any(len(row) != n for row in m):
            raise ValueError(f"must be a {n}x{n} matrix (a list of {n} rows of {n} numbers)")
        return m

    return AfterValidator(check)


Matrix4 = Annotated[list[list[float]], _square(4)]
Matrix3 = Annotated[list[list[float]], _square(3)]
PositiveFinite = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


class IntrinsicsSchema(BaseModel):
    """Pinhole intrinsics in pixels; each may be given at the top level, per frame, or both."""

    model_config = ConfigDict(extra="allow")

    fl_x: PositiveFinite | None = None
    fl_y: PositiveFinite | None = None
    cx: Finite | None = None
    cy: Finite | None = None
    w: Annotated[int, Field(gt=0)] | None = None
    h: Annotated[int, Field(gt=0)] | None = None


class FrameSchema(IntrinsicsSchema):
    file_path: Annotated[str, Field(min_length=1)]
    transform_matrix: Matrix4
    mask_path: Annotated[str, Field(min_length=1)] | None = None
    exposure: PositiveFinite = 1.0  # the photo's own exposure: a multiplier on top of tonemap.exposure


class TonemapSchema(BaseModel):
    model_config = ConfigDict(extra="allow")  # unknown keys: `_tonemap` (warned about, or refused if they conflict)

    exposure: PositiveFinite = 1.0
    transfer: Literal["srgb", "linear"] = "srgb"


class TransformsSchema(IntrinsicsSchema):
    """transforms.json: nerfstudio fields plus our mesh / envmap / tonemap extensions."""

    frames: list[dict[str, Any]]  # each validated as a FrameSchema on its own
    mesh: Annotated[str, Field(min_length=1)] | None = None
    envmap: Annotated[str, Field(min_length=1)] | None = None
    envmap_to_world: Matrix3 | None = None
    envmap_scale: PositiveFinite = 1.0
    tonemap: TonemapSchema = Field(default_factory=TonemapSchema)


def _format_loc(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def schema_problems(
    exc: ValidationError, file: str = TRANSFORMS, prefix: tuple[int | str, ...] = ()
) -> list[Problem]:
    """One Problem per pydantic error: "field.path[index]: reason"."""
    out = []
    for err in exc.errors():
        msg = str(err["msg"]).removeprefix("Value error, ")
        out.append(Problem(file, f"{_format_loc(prefix + tuple(err['loc']))}: {msg}"))
    return out


# ----------------------------------------------------------------------------------------- geometry checks


def rotation_problems(r: np.ndarray, what: str, tol: float = RIGID_TOLERANCE) -> list[str]:
    """Reasons the [3, 3] matrix `r` is not a rotation (orthonormal within tol, determinant +1)."""
    if not np.isfinite(r).all():
        return [f"{what} has non-finite (NaN or infinite) values"]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > tol:
        return [
            f"{what} is not orthonormal (|R^T R - I| reaches {err:.3g}; allowed {tol:g}): no scale or shear"
        ]
    det = float(np.linalg.det(r))
    if abs(det - 1.0) > tol:
        return [f"{what} has determinant {det:.3g}, expected +1 (it mirrors the world)"]
    return []


def pose_problems(c2w: np.ndarray, tol: float = RIGID_TOLERANCE) -> list[str]:
    """Reasons the [4, 4] camera-to-world matrix is not a finite rigid pose."""
    if not np.isfinite(c2w).all():
        return ["camera-to-world matrix has non-finite (NaN or infinite) values"]
    out = []
    if np.abs(c2w[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        out.append(f"camera-to-world last row is {c2w[3].tolist()}, expected [0, 0, 0, 1]")
    out += rotation_problems(c2w[:3, :3], "camera rotation", tol)
    return out


# ------------------------------------------------------------------------------------------------- parse


@dataclass
class ParsedFrame:
    """One frame entry as far as it could be understood.

    name: file_path as written; image_path: the existing file (None when unsafe or missing);
    size: (w, h) from the intrinsics, or None; camera: None when intrinsics or pose are unusable.
    """

    index: int
    name: str
    image_path: Path | None
    size: tuple[int, int] | None
    camera: Camera | None
    mask_name: str | None = None
    mask_path: Path | None = None
    distortion: Distortion | None = None
    exposure: float = 1.0  # the frame's own exposure multiplier (on top of the capture's tonemap exposure)

    @property
    def label(self) -> str:
        return f"frames[{self.index}] ({self.name})"


@dataclass
class ParsedCapture:
    """Everything `parse_capture` understood, plus every problem found; `capture()` needs no problems."""

    root: Path
    problems: list[Problem] = field(default_factory=list)
    warnings: list[Problem] = field(default_factory=list)  # things ignored on purpose (logged by load_capture)
    schema_ok: bool = False
    frames: list[ParsedFrame] = field(default_factory=list)
    mesh_path: Path | None = None
    envmap_path: Path | None = None
    envmap_to_world: np.ndarray = field(default_factory=lambda: np.eye(3))
    envmap_scale: float = 1.0
    tonemap: Tonemap = field(default_factory=Tonemap)

    def rel(self, path: Path) -> str:
        try:
            return path.relative_to(self.root).as_posix()
        except ValueError:
            return str(path)

    def capture(self, workdir: tempfile.TemporaryDirectory[str] | None = None) -> Capture:
        if self.problems or self.mesh_path is None or self.envmap_path is None:
            raise CaptureError(self.problems or [Problem(TRANSFORMS, "capture is incomplete")])
        frames = []
        for f in self.frames:
            assert f.image_path is not None and f.camera is not None
            frames.append(Frame(f.image_path, f.camera, f.mask_path, f.distortion, f.exposure))
        return Capture(
            root=self.root,
            frames=frames,
            mesh_path=self.mesh_path,
            envmap_path=self.envmap_path,
            envmap_to_world=self.envmap_to_world,
            envmap_scale=self.envmap_scale,
            tonemap=self.tonemap,
            workdir=workdir,
        )


def _resolve(root: Path, rel: str) -> Path | None:
    """Absolute path of `rel` inside root, or None when it is absolute or escapes the capture folder (unless
    `allow_outside_paths` is in force)."""
    unified = rel.replace("\\", "/")
    if _ALLOW_OUTSIDE.get():
        return Path(os.path.normpath(root / unified))
    if unified.startswith("/") or (len(unified) >= 2 and unified[1] == ":"):
        return None
    norm = os.path.normpath(unified)
    if norm == ".." or norm.startswith("../"):
        return None
    path = root / norm
    if not path.resolve().is_relative_to(root.resolve()):
        return None  # a symlink inside the capture points outside it
    return path


def _existing_file(
    root: Path, rel: str, what: str, label: str, problems: list[Problem], image: bool
) -> Path | None:
    path = _resolve(root, rel)
    if path is None:
        problems.append(Problem(TRANSFORMS, f"{label}: {what} path {rel!r} leaves the capture folder"))
        return None
    if not path.is_file() and image and path.suffix == "":
        for suffix in IMAGE_SUFFIXES:  # nerfstudio/blender files often omit the extension
            if path.with_suffix(suffix).is_file():
                return path.with_suffix(suffix)
    if not path.is_file():
        shown = path.relative_to(root).as_posix() if path.is_relative_to(root) else str(path)
        problems.append(Problem(shown, f"{what} file not found (named by {label} in {TRANSFORMS})"))
        return None
    if not path.resolve().is_relative_to(root.resolve()):
        log.info("%s: %s %s is outside the capture folder (allowed: --allow-outside-paths)", TRANSFORMS, what, path)
    return path


def _distortion_values(entry: IntrinsicsSchema, where: str, problems: list[Problem]) -> dict[str, float]:
    """The distortion coefficients `entry` gives (numbers; anything else is a problem)."""
    extra = entry.model_extra or {}
    out = {}
    for k in DISTORTION_KEYS:
        if k not in extra or extra[k] is None:
            continue
        v = extra[k]
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            problems.append(Problem(TRANSFORMS, f"{where}{k}: must be a finite number, got {v!r}"))
            continue
        out[k] = float(v)
    return out


def _camera_model_problem(entry: IntrinsicsSchema) -> str | None:
    model = (entry.model_extra or {}).get("camera_model")
    if isinstance(model, str) and any(m in model.upper() for m in UNSUPPORTED_MODELS):
        return (f"camera_model {model!r} is not supported: only pinhole cameras with OpenCV lens distortion (k1 k2 k3 "
                "p1 p2; camera_model OPENCV, PINHOLE or none); convert the photos to a pinhole camera first")
    return None


def _frame_distortion(fr: FrameSchema, top: dict[str, float], label: str,
                      problems: list[Problem]) -> Distortion | None:
    """The frame's lens distortion (its own coefficients over the top level's), None when there is none."""
    own = _distortion_values(fr, f"{label}: ", problems)
    values = {**top, **own}
    model = _camera_model_problem(fr)
    if model:
        problems.append(Problem(TRANSFORMS, f"{label}: {model}"))
    if own.get("k4", 0.0) != 0.0:  # the top level's is reported once by parse_capture
        problems.append(Problem(TRANSFORMS, f"{label}: {K4_MESSAGE}"))
    dist = Distortion(*(values.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")))
    return None if dist.is_zero else dist


def _parse_frame(
    root: Path, i: int, fr: FrameSchema, top: TransformsSchema, problems: list[Problem],
    top_distortion: dict[str, float] | None = None,
) -> tuple[ParsedFrame, tuple[str, ...]]:
    """The frame as far as it is usable, and the intrinsics it lacks (reported grouped by the caller)."""
    parsed = ParsedFrame(i, fr.file_path, None, None, None, fr.mask_path, exposure=float(fr.exposure))
    label = parsed.label
    parsed.image_path = _existing_file(root, fr.file_path, "image", label, problems, image=True)
    if fr.mask_path is not None:
        parsed.mask_path = _existing_file(root, fr.mask_path, "mask", label, problems, image=True)
    values = {k: getattr(fr, k) if getattr(fr, k) is not None else getattr(top, k) for k in INTRINSICS}
    missing = tuple(k for k in INTRINSICS if values[k] is None)
    if not missing:
        parsed.size = (int(values["w"]), int(values["h"]))
    parsed.distortion = _frame_distortion(fr, top_distortion or {}, label, problems)
    c2w = np.asarray(fr.transform_matrix, dtype=np.float64)
    pose = pose_problems(c2w)
    problems.extend(Problem(TRANSFORMS, f"{label}: {msg}") for msg in pose)
    if not missing and not pose:
        parsed.camera = Camera(
            c2w,
            float(values["fl_x"]),
            float(values["fl_y"]),
            float(values["cx"]),
            float(values["cy"]),
            int(values["w"]),
            int(values["h"]),
        )
    return parsed, missing


def _tonemap(raw: Any, schema: TonemapSchema, out: ParsedCapture) -> Tonemap:
    """The tonemap, with the keys the format does not define: `oetf` is taken as `transfer` ("srgb" or "linear";
    refused when it contradicts it), `clip` must say what T does (true, or [0, 1]); others are ignored with a
    warning naming them."""
    extra = dict(schema.model_extra or {})
    transfer = schema.transfer
    if "oetf" in extra:
        oetf = extra.pop("oetf")
        given = isinstance(raw, dict) and "transfer" in raw
        if oetf not in ("srgb", "linear"):
            out.problems.append(Problem(TRANSFORMS, f"tonemap.oetf: {oetf!r} is not a transfer function this format "
                                        "knows ('srgb' or 'linear'; the key is an alias of tonemap.transfer)"))
        elif given and oetf != transfer:
            out.problems.append(Problem(TRANSFORMS, f"tonemap.oetf {oetf!r} contradicts tonemap.transfer "
                                        f"{transfer!r}; give one of them"))
        else:
            transfer = oetf
    if "clip" in extra:
        clip = extra.pop("clip")
        if clip is not True and clip != [0, 1]:
            out.problems.append(Problem(TRANSFORMS, f"tonemap.clip: {clip!r} is not supported; the tonemap always "
                                        "clips exposure * radiance to [0, 1] (true)"))
    if extra:
        out.warnings.append(Problem(TRANSFORMS, f"tonemap keys {', '.join(sorted(extra))} are not part of the format "
                                    f"(it knows {', '.join(TONEMAP_KEYS)}) and are ignored"))
    return Tonemap(schema.exposure, transfer)


def _validate_top(data: Any, problems: list[Problem]) -> tuple[TransformsSchema | None, set[str]]:
    """The top level without its frames. Fields with schema errors are reported, then dropped (defaults
    apply) so that the rest can still be checked; returns the model (None if hopeless) and dropped keys."""
    if not isinstance(data, dict):
        problems.append(
            Problem(TRANSFORMS, f"must hold a JSON object at the top level, not {type(data).__name__}")
        )
        return None, set()
    try:
        return TransformsSchema.model_validate(data), set()
    except ValidationError as exc:
        problems.extend(schema_problems(exc))
        bad = {str(e["loc"][0]) for e in exc.errors() if e["loc"]}
    if "frames" in bad:
        return None, bad
    try:
        return TransformsSchema.model_validate({k: v for k, v in data.items() if k not in bad}), bad
    except ValidationError:
        return None, bad


def _missing_intrinsics(missing: dict[tuple[str, ...], list[int]], problems: list[Problem]) -> None:
    for keys, frames in missing.items():
        shown = ", ".join(f"frames[{i}]" for i in frames[:5]) + (
            f" and {len(frames) - 5} more" if len(frames) > 5 else ""
        )
        problems.append(
            Problem(
                TRANSFORMS,
                f"{shown}: intrinsics {', '.join(keys)} missing (give them at the top level or in"
                " each frame)",
            )
        )


def parse_capture(root: str | Path) -> ParsedCapture:
    """Parse `root`/transforms.json and check structure and file existence; never raises for bad input.

    Schema errors in one frame or one top-level field do not stop the checks of the others.
    """
    root = Path(root).absolute()
    out = ParsedCapture(root)
    problems = out.problems
    path = root / TRANSFORMS
    if not path.is_file():
        problems.append(Problem(TRANSFORMS, "not found in the capture folder"))
        return out
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError:
        problems.append(Problem(TRANSFORMS, "is not UTF-8 text"))
        return out
    except json.JSONDecodeError as exc:
        problems.append(
            Problem(TRANSFORMS, f"is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})")
        )
        return out
    except RecursionError:
        problems.append(Problem(TRANSFORMS, f"{TOO_DEEP}; a capture's JSON is a few levels deep"))
        return out
    try:
        top, dropped = _validate_top(data, problems)
    except RecursionError:
        problems.append(Problem(TRANSFORMS, f"{TOO_DEEP}; a capture's JSON is a few levels deep"))
        return out
    if top is None:
        return out
    out.schema_ok = True
    if not top.frames:
        problems.append(Problem(TRANSFORMS, "has no frames: a capture needs at least one photo"))
    top_distortion = _distortion_values(top, "", problems)
    if top_distortion.get("k4", 0.0) != 0.0:
        problems.append(Problem(TRANSFORMS, K4_MESSAGE))
    if _camera_model_problem(top):
        problems.append(Problem(TRANSFORMS, str(_camera_model_problem(top))))
    seen: dict[Path, int] = {}
    missing: dict[tuple[str, ...], list[int]] = {}
    for i, raw in enumerate(top.frames):
        try:
            fr = FrameSchema.model_validate(raw)
        except ValidationError as exc:
            problems.extend(schema_problems(exc, prefix=("frames", i)))
            continue
        frame, lacking = _parse_frame(root, i, fr, top, problems, top_distortion)
        out.frames.append(frame)
        if lacking:
            missing.setdefault(lacking, []).append(i)
        if frame.image_path is not None:
            key = frame.image_path.resolve()
            if key in seen:
                problems.append(
                    Problem(
                        out.rel(frame.image_path),
                        f"is used by frames[{seen[key]}] and frames[{i}]; each frame needs its own photo",
                    )
                )
            else:
                seen[key] = i
    _missing_intrinsics(missing, problems)
    for entry, what in (("mesh", "mesh"), ("envmap", "environment map")):
        rel = getattr(top, entry)
        if rel is not None:
            found = _existing_file(root, rel, what, f'"{entry}"', problems, image=False)
            setattr(out, f"{entry}_path", found)
        elif entry not in dropped:
            problems.append(Problem(TRANSFORMS, f'has no "{entry}" entry naming the {what} file'))
    if top.envmap_to_world is not None:
        rot = np.asarray(top.envmap_to_world, dtype=np.float64)
        msgs = rotation_problems(rot, "envmap_to_world")
        problems.extend(Problem(TRANSFORMS, m) for m in msgs)
        if not msgs:
            out.envmap_to_world = rot
    out.envmap_scale = float(top.envmap_scale)
    out.tonemap = _tonemap(data.get("tonemap"), top.tonemap, out)
    return out


# ------------------------------------------------------------------------------------------ folder / zip


def is_zip(path: Path) -> bool:
    return path.is_file() and (path.suffix.lower() == ".zip" or zipfile.is_zipfile(path))


def _only_subfolder(folder: Path) -> Path | None:
    """The sub-folder of `folder` when it has exactly one (hidden ones and __MACOSX aside)."""
    subdirs = [d for d in folder.iterdir() if d.is_dir() and not d.name.startswith((".", "__MACOSX"))]
    return subdirs[0] if len(subdirs) == 1 else None


def find_capture_root(folder: Path, label: str) -> Path:
    """The folder holding transforms.json: `folder` itself, or the end of a chain of single folders inside it
    (a zip of `capture/` or of `examples/capture/`)."""
    current: Path | None = folder
    for _ in range(MAX_FOLDER_CHAIN):
        if current is None:
            break
        if (current / TRANSFORMS).is_file():
            return current
        current = _only_subfolder(current)
    raise CaptureError(
        [
            Problem(
                TRANSFORMS,
                f"not found in {label} (looked at its top level and inside a single top-level folder)",
            )
        ]
    )


@dataclass
class Opened:
    """A capture folder on disk; `workdir` is the temporary folder a zip was extracted to (or None)."""

    root: Path
    workdir: tempfile.TemporaryDirectory[str] | None


def open_capture_folder(
    path: str | Path,
    workdir: str | Path | None = None,
    max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES,
    max_files: int = DEFAULT_MAX_FILES,
    max_ratio: float = DEFAULT_MAX_RATIO,
) -> Opened:
    """Locate the capture root of a folder, a transforms.json path or a zip (extracted safely, into
    `workdir` when given, else into a new temporary folder that the caller must clean up)."""
    path = Path(path)
    label = path.name or str(path)
    if path.is_dir():
        return Opened(find_capture_root(path, label), None)
    if path.is_file() and path.name == TRANSFORMS:
        return Opened(path.parent, None)
    if not path.exists():
        raise CaptureError([Problem(label, "capture not found (expected a folder or a .zip file)")])
    if not is_zip(path):
        raise CaptureError([Problem(label, "is neither a capture folder nor a .zip archive")])
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="neumatex-capture-")
        dest = Path(tmp.name)
    else:
        dest = Path(workdir)
    try:
        extract_zip(path, dest, max_total_bytes, max_files, max_ratio)
        return Opened(find_capture_root(dest, label), tmp)
    except BaseException:
        if tmp is not None:
            tmp.cleanup()
        raise


def load_capture(path: str | Path, workdir: str | Path | None = None) -> Capture:
    """Load a capture folder or zip. A zip is extracted into `workdir` when given (the caller owns it), else
    into a temporary folder owned by the returned Capture (removed by `Capture.close()` or on collection).

    Raises CaptureError listing every structural problem (schema, intrinsics, poses, missing files). File
    contents (corrupt images, mesh data, envmap values, visibility) are checked by `validate_capture`.
    """
    opened = open_capture_folder(path, workdir)
    try:
        with allow_outside_paths(_ALLOW_OUTSIDE.get() and not is_zip(Path(path))):  # a zip is self-contained
            parsed = parse_capture(opened.root)
        for w in parsed.warnings:
            log.warning("warning: %s", w)
        return parsed.capture(opened.workdir)
    except BaseException:
        if opened.workdir is not None:
            opened.workdir.cleanup()
        raise
