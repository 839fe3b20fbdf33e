"""Triangle meshes: loading through trimesh, checking, normalising into the unit sphere.

A `Mesh` holds float32 numpy arrays (geometry is fixed: ray queries need no gradient) and hands torch
tensors to the renderer on demand.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

DEGENERATE_AREA = 1e-12  # a face's area below this times the squared bounding-box diagonal is zero
TEXT_FORMATS = (".obj",)  # decoded here (UTF-8, else Latin-1) so that a stray byte in a comment is harmless


class MeshError(ValueError):
    """A mesh file that cannot be used; the message names the file and the reason."""


@dataclass(frozen=True)
class Mesh:
    """An indexed triangle mesh.

    vertices: [V, 3] float32 world positions.
    faces: [F, 3] int64 vertex indices.
    vertex_normals: [V, 3] float32 unit shading normals, or None for flat shading.
    uvs: [V, 2] float32 texture coordinates, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray | None = None
    uvs: np.ndarray | None = None

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def face_normals(self) -> np.ndarray:
        """[F, 3] unit geometric normals (counter-clockwise winding), zero for degenerate faces."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.where(length > 0, n / np.maximum(length, 1e-30), 0.0).astype(np.float32)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre [3] (of the bounding box) and radius enclosing every vertex."""
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        centre = (lo + hi) / 2
        radius = float(np.linalg.norm(self.vertices - centre, axis=1).max())
        return centre.astype(np.float32), radius

    def normalization(self, radius: float = 1.0) -> tuple[np.ndarray, float]:
        """(centre [3], scale) with which `normalized` maps a point p to (p - centre) * scale."""
        centre, r = self.bounding_sphere()
        return centre, radius / max(r, 1e-12)

    def normalized(self, radius: float = 1.0) -> Mesh:
        """The mesh centred at the origin and scaled so that it fits in a sphere of `radius`."""
        centre, scale = self.normalization(radius)
        return Mesh(
            vertices=((self.vertices - centre) * scale).astype(np.float32),
            faces=self.faces,
            vertex_normals=self.vertex_normals,
            uvs=self.uvs,
        )

    def flat(self) -> Mesh:
        """The same surface with flat shading (shading normal = geometric normal)."""
        return Mesh(self.vertices, self.faces, None, self.uvs)

    def with_smooth_normals(self) -> Mesh:
        """Area-weighted vertex normals computed from the faces."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])  # area-weighted
        acc = np.zeros_like(self.vertices, dtype=np.float64)
        for k in range(3):
            np.add.at(acc, self.faces[:, k], n)
        length = np.linalg.norm(acc, axis=1, keepdims=True)
        normals = np.where(length > 0, acc / np.maximum(length, 1e-30), [0.0, 1.0, 0.0])
        return Mesh(self.vertices, self.faces, normals.astype(np.float32), self.uvs)

    def _area_samples(self, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """n points uniform over the area: their triangles [n], barycentrics [n, 3] and positions [n, 3] (float64);
        deterministic in seed."""
        rng = np.random.default_rng(seed)
        v = self.vertices[self.faces].astype(np.float64)
        area = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
        tri = rng.choice(len(area), size=n, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
        b = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)  # uniform barycentrics (sqrt warp)
        return tri, b, (b[:, :, None] * v[tri]).sum(1)

    def sample_surface(self, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor | None]:
        """n points [n, 3] float32 uniformly distributed over the area, and their uvs [n, 2] (None without
        uvs); deterministic in seed."""
        tri, b, positions = self._area_samples(n, seed)
        points = torch.from_numpy(positions.astype(np.float32))
        if self.uvs is None:
            return points, None
        uv = self.uvs[self.faces[tri]].astype(np.float64)
        return points, torch.from_numpy((b[:, :, None] * uv).sum(1).astype(np.float32))

    def sample_surface_faces(self, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """The points of `sample_surface(n, seed)` [n, 3] float32 and the faces they lie on [n] int64 (e.g. for a
        field whose values are per face, like a synthetic object's regions)."""
        tri, _, positions = self._area_samples(n, seed)
        return torch.from_numpy(positions.astype(np.float32)), torch.from_numpy(tri.astype(np.int64))

    def sample_surface_normals(self, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """The points of `sample_surface(n, seed)` [n, 3] and their unit shading normals [n, 3] (interpolated
        vertex normals, else the face's), float32."""
        tri, b, positions = self._area_samples(n, seed)
        if self.vertex_normals is not None:
            normals = (b[:, :, None] * self.vertex_normals[self.faces[tri]].astype(np.float64)).sum(1)
        else:
            normals = self.face_normals()[tri].astype(np.float64)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
        return torch.from_numpy(positions.astype(np.float32)), torch.from_numpy(normals.astype(np.float32))

    def torch(self, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """Tensors for shading: vertices, faces, face normals, (optional) vertex normals and uvs."""
        out = {
            "vertices": torch.from_numpy(self.vertices).to(device),
            "faces": torch.from_numpy(self.faces).to(device),
            "face_normals": torch.from_numpy(self.face_normals()).to(device),
        }
        if self.vertex_normals is not None:
            out["vertex_normals"] = torch.from_numpy(self.vertex_normals).to(device)
        if self.uvs is not None:
            out["uvs"] = torch.from_numpy(self.uvs).to(device)
        return out


def check_mesh_arrays(vertices: np.ndarray, faces: np.ndarray, name: str) -> list[str]:
    """Every reason the arrays cannot be rendered (empty when they can)."""
    problems: list[str] = []
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        problems.append(f"{name}: mesh has no vertices")
    elif not np.isfinite(vertices).all():
        bad = int((~np.isfinite(vertices)).any(axis=1).sum())
        problems.append(f"{name}: {bad} vertices have non-finite (NaN or infinite) coordinates")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        problems.append(f"{name}: mesh has no triangle faces")
    elif len(vertices) and (faces.min() < 0 or faces.max() >= len(vertices)):
        problems.append(f"{name}: faces index vertices that do not exist")
    elif not problems:
        problems += _surface_problems(vertices, faces, name)
    return problems


def _surface_problems(vertices: np.ndarray, faces: np.ndarray, name: str) -> list[str]:
    """A surface with no usable triangle: every face degenerate (zero area, relative to the mesh's size), or a
    mesh whose vertices all lie at one point."""
    v = vertices.astype(np.float64)
    extent = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    if extent <= 0.0:
        return [f"{name}: all vertices lie at one point: the mesh has no surface"]
    tri = v[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area > DEGENERATE_AREA * extent**2).any():
        return [f"{name}: all {len(faces)} faces are degenerate (zero area): no usable triangles"]
    return []


def _decode(data: bytes) -> str:
    """Text of a mesh file: UTF-8 (with or without BOM), else Latin-1 (which decodes any byte)."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def load_mesh(path: str | Path, smooth: bool = True) -> Mesh:
    """Load an OBJ, PLY, GLB/glTF or STL file through trimesh as one triangle mesh.

    Scenes with several geometries are concatenated. The file's own normals (OBJ `vn`, PLY nx ny nz, ...) are not
    used: with `smooth`, vertex normals are recomputed from the faces (area-weighted, `Mesh.with_smooth_normals`);
    otherwise there are none and shading is flat. UVs are kept when there is one per vertex. Raises MeshError naming
    the file.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    try:
        if path.suffix.lower() in TEXT_FORMATS:
            resolver = trimesh.resolvers.FilePathResolver(str(path))
            loaded = trimesh.load(io.StringIO(_decode(path.read_bytes())), file_type=path.suffix.lower()[1:],
                                  process=False, force="mesh", resolver=resolver)  # fmt: skip
        else:
            loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for bad files
        raise MeshError(f"{path}: cannot be read as a mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{path}: contains no triangle mesh")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3) if len(loaded.faces) else np.zeros((0, 3), np.int64)
    problems = check_mesh_arrays(vertices, faces, str(path))
    if problems:
        raise MeshError("; ".join(problems))
    uvs = None
    visual = getattr(loaded, "visual", None)
    if visual is not None and getattr(visual, "uv", None) is not None and len(visual.uv) == len(vertices):
        uvs = np.asarray(visual.uv, dtype=np.float32)
    mesh = Mesh(vertices.astype(np.float32), faces, None, uvs)
    return mesh.with_smooth_normals() if smooth else mesh


def icosphere(subdivisions: int = 4, radius: float = 1.0) -> Mesh:
    """A unit-centred sphere (trimesh icosphere) with smooth normals: the galleries' and tests' probe shape."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    vertices = np.asarray(sphere.vertices, dtype=np.float32)
    normals = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    return Mesh(vertices, np.asarray(sphere.faces, dtype=np.int64), normals.astype(np.float32))
