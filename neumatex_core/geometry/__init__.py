"""Meshes, cameras, ray queries and G-buffers."""

from neumatex_core.geometry.camera import Camera, preset_views
from neumatex_core.geometry.mesh import Mesh, MeshError, load_mesh
from neumatex_core.geometry.raycast import Hits, RayCaster

__all__ = ["Camera", "Hits", "Mesh", "MeshError", "RayCaster", "load_mesh", "preset_views"]
