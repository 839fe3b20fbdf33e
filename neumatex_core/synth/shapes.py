"""Procedural and shared-mesh shapes for synthetic objects, centred and scaled into the unit sphere.

A `ShapeSpec` names a kind and a seed; `build_shape(spec, meshes_dir)` makes the triangle mesh and a part label
per face (the primitive a face belongs to in a union, else 0) from them alone, so the same spec always gives the
same mesh. Kinds:

- `sphere`: an icosphere (4 subdivisions), stretched into an ellipsoid (axes 0.7..1);
- `torus`: major radius 1, minor 0.2..0.45, a 96 x 48 grid;
- `superquadric`: a superellipsoid (exponents 0.25..2.5 in latitude and longitude, axes 0.5..1), 96 x 48 grid,
  from boxes and cylinders through rounded shapes to star-like octahedra;
- `blob`: an icosphere (5 subdivisions) displaced along the radius by 3D fractal noise (amplitude 0.1..0.35,
  frequency 0.8..2.5);
- `union`: 2 or 3 of the above, each shrunk to radius 0.35..0.7, rotated and placed within 0.55 of the centre
  (meshes simply overlap: ray queries need no boolean union); parts = which primitive;
- `mesh`: a shared mesh (`../shared/data/meshes/NAME.obj`), rotated uniformly at random, scaled by 0.85..1.15
  per axis and twisted about +Y by up to 0.35 rad per unit height (mild deformation).

Every shape is finally rotated uniformly at random and normalised so its bounding-box centre is the origin and
its farthest vertex lies at `RADIUS` (inside the unit sphere, docs/architecture.md section 2). Shading is smooth
(area-weighted vertex normals).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from neumatex_core.geometry.mesh import Mesh, icosphere, load_mesh
from neumatex_core.synth.noise import fbm_numpy

RADIUS = 0.97  # the farthest vertex from the origin (float32 rounding stays far below 1)
PROCEDURAL_KINDS = ("sphere", "torus", "superquadric", "blob", "union")
SHAPE_KINDS = (*PROCEDURAL_KINDS, "mesh")
GRID_U, GRID_V = 96, 48  # longitude x latitude steps of the parametric shapes


@dataclass(frozen=True)
class ShapeSpec:
    """kind: one of SHAPE_KINDS; seed: fixes every shape parameter; mesh: the shared mesh's name (kind mesh)."""

    kind: str
    seed: int
    mesh: str = ""


@dataclass
class Shape:
    """mesh: the normalised triangle mesh; parts: [F] int64 part label per face; params: what was drawn."""

    mesh: Mesh
    parts: np.ndarray
    params: dict[str, Any]


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """[3, 3] uniformly distributed rotation (QR of a Gaussian matrix, signs fixed, det +1)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _grid_faces(nu: int, nv: int, poles: bool) -> np.ndarray:
    """Faces of a (u wrapping) x (v rows) grid; with `poles`, rows 1..nv-1 plus a top and a bottom vertex
    (indices nu*(nv-1) and nu*(nv-1)+1), else nv rows wrapping in v too (a torus)."""
    faces = []
    rows = nv - 1 if poles else nv
    last = rows - 1 if poles else rows
    for j in range(last):
        j1 = (j + 1) % rows
        for i in range(nu):
            i1 = (i + 1) % nu
            a, b, c, d = j * nu + i, j * nu + i1, j1 * nu + i, j1 * nu + i1
            faces += [(a, c, b), (b, c, d)]
    if poles:
        top, bottom = rows * nu, rows * nu + 1
        for i in range(nu):
            i1 = (i + 1) % nu
            faces.append((top, i, i1))
            faces.append((bottom, (rows - 1) * nu + i1, (rows - 1) * nu + i))
    return np.asarray(faces, dtype=np.int64)


def _spow(x: np.ndarray, e: float) -> np.ndarray:
    return np.sign(x) * np.abs(x) ** e


def superquadric(e_lat: float, e_lon: float, axes: np.ndarray, nu: int = GRID_U, nv: int = GRID_V) -> Mesh:
    """Superellipsoid with latitude / longitude exponents and semi-axes [3] (+Y is the polar axis)."""
    u = 2 * math.pi * np.arange(nu) / nu
    v = math.pi * np.arange(1, nv) / nv - math.pi / 2  # latitudes, poles excluded
    uu, vv = np.meshgrid(u, v)  # [nv-1, nu]
    x = axes[0] * _spow(np.cos(vv), e_lat) * _spow(np.cos(uu), e_lon)
    y = axes[1] * _spow(np.sin(vv), e_lat)
    z = axes[2] * _spow(np.cos(vv), e_lat) * _spow(np.sin(uu), e_lon)
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    verts = np.concatenate([verts, [[0.0, -axes[1], 0.0], [0.0, axes[1], 0.0]]])
    # Rows run from the south pole upwards: _grid_faces' first pole vertex closes row 0 (south), the second the last.
    return Mesh(verts.astype(np.float32), _grid_faces(nu, nv, poles=True)).with_smooth_normals()


def torus(minor: float, nu: int = GRID_U, nv: int = GRID_V) -> Mesh:
    """Torus of major radius 1 around +Y, tube radius `minor`."""
    u = 2 * math.pi * np.arange(nu) / nu
    v = 2 * math.pi * np.arange(nv) / nv
    uu, vv = np.meshgrid(u, v)
    ring = 1 + minor * np.cos(vv)
    verts = np.stack([ring * np.cos(uu), minor * np.sin(vv), ring * np.sin(uu)], -1).reshape(-1, 3)
    return Mesh(verts.astype(np.float32), _grid_faces(nu, nv, poles=False)).with_smooth_normals()


def _primitive(kind: str, rng: np.random.Generator) -> tuple[Mesh, dict[str, Any]]:
    if kind == "sphere":
        axes = rng.uniform(0.7, 1.0, 3)
        m = icosphere(4)
        return Mesh((m.vertices * axes).astype(np.float32), m.faces), {"axes": axes.round(6).tolist()}
    if kind == "torus":
        minor = float(rng.uniform(0.2, 0.45))
        return torus(minor), {"minor_radius": round(minor, 6)}
    if kind == "superquadric":
        e_lat, e_lon = (float(x) for x in rng.uniform(0.25, 2.5, 2))
        axes = rng.uniform(0.5, 1.0, 3)
        return superquadric(e_lat, e_lon, axes), {"exponents": [round(e_lat, 6), round(e_lon, 6)],
                                                  "axes": axes.round(6).tolist()}  # fmt: skip
    if kind == "blob":
        amp, freq = float(rng.uniform(0.1, 0.35)), float(rng.uniform(0.8, 2.5))
        noise_seed = int(rng.integers(2**31))
        m = icosphere(5)
        n = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
        r = 1 + amp * fbm_numpy(noise_seed, n * freq, octaves=3) * 1.6
        return Mesh((n * r[:, None]).astype(np.float32), m.faces), {"amplitude": round(amp, 6),
                                                                    "frequency": round(freq, 6)}  # fmt: skip
    raise ValueError(f"unknown primitive kind {kind!r}")


def _normalised(mesh: Mesh, rotation: np.ndarray) -> Mesh:
    rotated = Mesh((mesh.vertices.astype(np.float64) @ rotation.T).astype(np.float32), mesh.faces)
    return rotated.normalized(RADIUS).with_smooth_normals()


def _twist(v: np.ndarray, rate: float) -> np.ndarray:
    angle = rate * v[:, 1]
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[:, 0] + s * v[:, 2], v[:, 1], -s * v[:, 0] + c * v[:, 2]], -1)


def build_shape(spec: ShapeSpec, meshes_dir: Path | None = None) -> Shape:
    """The mesh (normalised into the unit sphere) and face parts of `spec`; see the module docstring."""
    rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 0x5A4E]))
    params: dict[str, Any] = {"kind": spec.kind}
    if spec.kind == "mesh":
        if meshes_dir is None:
            raise ValueError("a shared-mesh shape needs the meshes folder")
        base = load_mesh(Path(meshes_dir) / f"{spec.mesh}.obj").normalized()
        scale = rng.uniform(0.85, 1.15, 3)
        rate = float(rng.uniform(-0.35, 0.35))
        v = _twist((base.vertices.astype(np.float64) @ random_rotation(rng).T) * scale, rate)
        mesh = Mesh(v.astype(np.float32), base.faces)
        parts = np.zeros(mesh.num_faces, np.int64)
        params.update(mesh=spec.mesh, scale=scale.round(6).tolist(), twist=round(rate, 6))
    elif spec.kind == "union":
        count = int(rng.integers(2, 4))
        verts, faces, labels, prims = [], [], [], []
        offset = 0
        for k in range(count):
            kind = str(rng.choice(["sphere", "torus", "superquadric", "blob"]))
            prim, info = _primitive(kind, rng)
            size = float(rng.uniform(0.35, 0.7))
            centre = rng.uniform(-1, 1, 3)
            centre = centre / max(float(np.linalg.norm(centre)), 1e-9) * rng.uniform(0.0, 0.55)
            pv = prim.normalized(1.0).vertices.astype(np.float64) @ random_rotation(rng).T * size + centre
            verts.append(pv)
            faces.append(prim.faces + offset)
            labels.append(np.full(prim.num_faces, k, np.int64))
            offset += len(pv)
            prims.append({"kind": kind, **info, "size": round(size, 6), "centre": centre.round(6).tolist()})
        mesh = Mesh(np.concatenate(verts).astype(np.float32), np.concatenate(faces))
        parts = np.concatenate(labels)
        params["primitives"] = prims
    elif spec.kind in PROCEDURAL_KINDS:
        mesh, info = _primitive(spec.kind, rng)
        parts = np.zeros(mesh.num_faces, np.int64)
        params.update(info)
    else:
        raise ValueError(f"unknown shape kind {spec.kind!r}; expected one of {SHAPE_KINDS}")
    return Shape(_normalised(mesh, random_rotation(rng)), parts, params)
