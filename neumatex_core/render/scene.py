"""A renderable scene: a mesh (with its BVH), an environment map and a material field."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.raycast import RayCaster
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField


@dataclass
class Scene:
    """mesh: the object (world units); envmap: the only light; material: the material field on the mesh."""

    mesh: Mesh
    envmap: EnvironmentMap
    material: MaterialField
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    def __post_init__(self) -> None:
        self.raycaster = RayCaster(self.mesh)
        self.mesh_tensors = self.mesh.torch(self.device)
