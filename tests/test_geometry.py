"""Meshes, cameras, preset views, ray queries and G-buffers."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from conftest import MESHES

from neumatex_core.geometry import Camera, MeshError, RayCaster, load_mesh, preset_views
from neumatex_core.geometry.camera import camera_from_fov, look_at
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh


def sphere_mesh(radius: float = 0.5) -> Mesh:
    ico = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    return Mesh(np.asarray(ico.vertices, np.float32), np.asarray(ico.faces, np.int64)).with_smooth_normals()


def test_normalized_mesh_fits_unit_sphere():
    mesh = load_mesh(MESHES / "cow.obj").normalized()
    centre, radius = mesh.bounding_sphere()
    assert radius == pytest.approx(1.0, abs=1e-5)
    assert np.abs(centre).max() < 1e-5


def test_surface_samples_are_area_uniform_and_carry_uvs():
    # two triangles in the plane z = 0 with areas 1 and 3: the counts follow the areas within binomial noise
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 0], [-3, 0, 0], [0, -2, 0]], np.float32)
    uvs = np.array([[0, 0], [1, 0], [0, 1], [0, 0], [1, 0], [0, 1]], np.float32)
    mesh = Mesh(v, np.array([[0, 1, 2], [3, 4, 5]], np.int64), uvs=uvs)
    n = 20000
    points, uv = mesh.sample_surface(n, seed=5)
    assert points.shape == (n, 3) and uv is not None and uv.shape == (n, 2)
    assert float(points[:, 2].abs().max()) == 0.0
    first = points[:, 0] >= 0
    share, se = float(first.float().mean()), (0.25 * 0.75 / n) ** 0.5
    assert abs(share - 0.25) < 4 * se
    # uv x is a barycentric coordinate: density 2(1 - u) over a uniform triangle, mean 1/3, variance 1/18
    assert abs(float(uv[:, 0].mean()) - 1 / 3) < 4 * (1 / 18 / n) ** 0.5
    assert float(uv.sum(1).max()) <= 1 + 1e-6 and float(uv.min()) >= 0
    again, _ = mesh.sample_surface(n, seed=5)
    assert torch.equal(points, again) and mesh.flat().sample_surface(4)[1] is not None
    assert Mesh(v, mesh.faces).sample_surface(4)[1] is None
    # the same points with the faces they lie on (face 0 holds x >= 0, face 1 x <= 0)
    same, faces = mesh.sample_surface_faces(n, seed=5)
    assert torch.equal(same, points) and faces.dtype == torch.int64 and faces.shape == (n,)
    assert bool((faces[points[:, 0] > 0] == 0).all()) and bool((faces[points[:, 0] < 0] == 1).all())


def test_broken_meshes_are_rejected_with_file_name(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match="empty.obj.*no triangle faces"):
        load_mesh(empty)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="nan.obj.*non-finite"):
        load_mesh(nan)
    with pytest.raises(MeshError, match="missing.obj.*not found"):
        load_mesh(tmp_path / "missing.obj")


def test_preset_views_are_23_and_look_at_origin():
    cams = preset_views(64)
    assert len(cams) == 23
    for cam in cams:
        forward = -cam.c2w[:3, 2]
        to_origin = -cam.position / np.linalg.norm(cam.position)
        assert np.dot(forward, to_origin) == pytest.approx(1.0, abs=1e-9)
        assert np.allclose(cam.c2w[:3, :3].T @ cam.c2w[:3, :3], np.eye(3), atol=1e-9)
        assert np.linalg.det(cam.c2w[:3, :3]) == pytest.approx(1.0)
    elevations = [np.degrees(np.arcsin(c.position[1] / np.linalg.norm(c.position))) for c in cams[:17]]
    assert np.allclose(elevations, 20.0)
    canonical = np.array([c.position / np.linalg.norm(c.position) for c in cams[17:]])
    assert np.allclose(np.abs(canonical).sum(axis=1), 1.0)


def test_camera_convention_up_right_forward():
    """OpenGL convention: the top image row looks up (+Y), the right column looks right (+X)."""
    cam = camera_from_fov(look_at(np.array([0, 0, 3.0]), np.zeros(3), np.array([0, 1.0, 0])), 40, 20, 60)
    o, d = cam.rays_for_pixels(torch.tensor([20.0, 20.0, 39.9, 0.1]), torch.tensor([10.0, 0.1, 10.0, 10.0]))
    assert torch.allclose(d[0], torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)
    assert d[1, 1] > 0  # top row looks up
    assert d[2, 0] > 0 and d[3, 0] < 0  # right column looks right
    px, front = cam.project(np.array([[0.0, 0.0, 0.0], [0.3, 0.2, 0.0]]))
    assert front.all()
    assert np.allclose(px[0], [20, 10])
    assert px[1, 0] > 20 and px[1, 1] < 10


def test_ray_queries_hit_sphere_at_analytic_distance():
    mesh = sphere_mesh(0.5)
    rc = RayCaster(mesh)
    g = torch.Generator().manual_seed(0)
    offsets = (torch.rand(2000, 2, generator=g) - 0.5) * 1.4
    o = torch.cat([offsets, torch.full((2000, 1), 3.0)], dim=1)
    d = torch.tensor([[0.0, 0.0, -1.0]]).expand(2000, 3).contiguous()
    hits = rc.intersect(o, d)
    r2 = (offsets**2).sum(1)
    inside = r2 < 0.45**2
    outside = r2 > 0.5**2
    assert hits.valid[inside].all() and not hits.valid[outside].any()
    t_exact = 3.0 - torch.sqrt(0.25 - r2[inside])
    assert (hits.t[inside] - t_exact).abs().max() < 2e-3  # icosphere facets vs the true sphere
    occluded = rc.occluded(o, d, torch.full((2000,), 2.0))
    assert not occluded.any()  # the sphere starts at t >= 2.5
    assert (rc.occluded(o, d) == hits.valid).all()


def test_gbuffer_of_sphere():
    mesh = sphere_mesh(0.5)
    cam = preset_views(48)[0]
    gb = render_gbuffer(mesh, cam)
    assert gb.mask.shape == (48, 48)
    covered = gb.mask
    radius = gb.position[covered].norm(dim=-1)
    assert (radius - 0.5).abs().max() < 5e-3
    # Normals are unit, face the camera and match the sphere's radial direction.
    n = gb.normal[covered]
    assert torch.allclose(n.norm(dim=-1), torch.ones(n.shape[0]), atol=1e-4)
    radial = gb.position[covered] / radius.unsqueeze(-1)
    assert (n * radial).sum(-1).min() > 0.99
    assert (gb.triangle[~covered] == -1).all() and (gb.triangle[covered] >= 0).all()
    # Coverage is the projected disk: asin(0.5 / 3.2) of a 20-degree half field of view.
    expected = np.pi * (np.tan(np.arcsin(0.5 / 3.2)) / np.tan(np.radians(20)) * 24) ** 2
    assert covered.sum().item() == pytest.approx(expected, rel=0.05)


def test_camera_resized_scales_intrinsics():
    cam = Camera(np.eye(4), 100.0, 100.0, 32.0, 24.0, 64, 48).resized(128, 96)
    assert (cam.fl_x, cam.cx, cam.cy, cam.width, cam.height) == (200.0, 64.0, 48.0, 128, 96)
