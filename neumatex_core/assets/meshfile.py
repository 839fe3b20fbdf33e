"""The package's mesh file: a Wavefront OBJ with positions, uvs and normals sharing one index per corner.

Written with 9 significant digits, which round-trips float32 exactly, so a package re-renders bit for bit. The
reader parses exactly this subset (v, vt, vn, triangular `f a/a/a`), fast, and rejects anything else by name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neumatex_core.assets.manifest import AssetError
from neumatex_core.geometry.mesh import Mesh


def write_obj(path: Path, mesh: Mesh, comment: str = "") -> None:
    if mesh.uvs is None or mesh.vertex_normals is None:
        raise ValueError("the package mesh needs uvs and vertex normals")
    v, vt, vn = mesh.vertices, mesh.uvs, mesh.vertex_normals
    f = mesh.faces.astype(np.int64) + 1
    parts = [f"# NeuMatEx material asset mesh {comment}\n".replace(" \n", "\n"),
             ("v %.9g %.9g %.9g\n" * len(v)) % tuple(v.astype(np.float64).ravel()),
             ("vt %.9g %.9g\n" * len(vt)) % tuple(vt.astype(np.float64).ravel()),
             ("vn %.9g %.9g %.9g\n" * len(vn)) % tuple(vn.astype(np.float64).ravel()),
             ("f %d/%d/%d %d/%d/%d %d/%d/%d\n" * len(f)) % tuple(np.repeat(f, 3, axis=1).ravel())]  # fmt: skip
    path.write_text("".join(parts))


def read_obj(path: Path, label: str) -> Mesh:
    """The mesh `write_obj` wrote; AssetError naming `label` for anything else."""
    try:
        lines = path.read_text().split("\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise AssetError(f"{label}: cannot be read ({exc})") from None
    groups: dict[str, list[str]] = {"v": [], "vt": [], "vn": [], "f": []}
    for line in lines:
        if not line or line[0] == "#":
            continue
        key, _, rest = line.partition(" ")
        if key not in groups:
            raise AssetError(f"{label}: unexpected OBJ statement {key!r} (not a NeuMatEx package mesh)")
        groups[key].append(rest)
    try:
        v = np.array(" ".join(groups["v"]).split(), dtype=np.float64).reshape(-1, 3).astype(np.float32)
        vt = np.array(" ".join(groups["vt"]).split(), dtype=np.float64).reshape(-1, 2).astype(np.float32)
        vn = np.array(" ".join(groups["vn"]).split(), dtype=np.float64).reshape(-1, 3).astype(np.float32)
        corners = np.array(" ".join(groups["f"]).replace("/", " ").split(), dtype=np.int64).reshape(-1, 3, 3)
    except ValueError as exc:
        raise AssetError(f"{label}: malformed OBJ data ({exc})") from None
    if len(v) == 0 or len(corners) == 0 or len(vt) != len(v) or len(vn) != len(v):
        raise AssetError(f"{label}: needs vertices with one uv and one normal each and triangle faces")
    if not ((corners[:, :, 0] == corners[:, :, 1]) & (corners[:, :, 0] == corners[:, :, 2])).all():
        raise AssetError(f"{label}: faces must use the same index for position, uv and normal")
    faces = corners[:, :, 0] - 1
    if faces.min() < 0 or faces.max() >= len(v):
        raise AssetError(f"{label}: faces index vertices that do not exist")
    return Mesh(v, faces, vn, vt)
